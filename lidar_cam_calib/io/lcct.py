"""Reader for the CMU Laser-Camera Calibration Toolbox sample (``lcct_checkerboard_3dlaser``).

Turns the folder into :class:`~lidar_cam_calib.board.frame.BoardFrame` objects (one per board
pose: the ``.xyz`` scan in metres, no intensity, no rings, and the camera image), the camera
model from the Bouguet calibration (``fc``, ``cc``, ``kc`` = plumb_bob k1 k2 p1 p2 k3), the board
(8 x 6 squares of 30 mm, 7 x 5 inner corners; the panel's outer size is not published, the
default is measured roughly from the scans) and the toolbox's own result
(``sample_results/Laser_Cam_calib_2.m``: ``p_cam = R p_laser + t``) for comparison.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re

import numpy as np

from ..board.frame import BoardFrame, BoardGeometry, CameraImage
from ..core.camera import CameraModel
from ..core.errors import InputError
from ..core.geometry import make_T


@dataclasses.dataclass
class LcctData:
    frames: list
    camera: CameraModel
    board: BoardGeometry
    T_camera_laser_toolbox: np.ndarray | None
    camera_name: str = "camera"


def _read_toolbox_result(path: str) -> np.ndarray | None:
    if not os.path.exists(path):
        return None
    text = open(path, encoding="utf-8", errors="replace").read()
    mt = re.search(r"t\s*=\s*\[([^\]]*)\]", text)
    mr = re.search(r"R\s*=\s*\.\.\.\s*\[([^\]]*)\]", text)
    if not (mt and mr):
        return None
    num = r"[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?"
    t = np.array([float(v) for v in re.findall(num, mt.group(1))])
    R = np.array([float(v) for v in re.findall(num, mr.group(1))]).reshape(3, 3)
    return make_T(R, t)


def read_lcct(folder: str, board_size_m: tuple = (0.36, 0.30), max_poses: int | None = None) -> LcctData:
    """Read the sample folder; raises :class:`InputError` when it is incomplete."""
    import cv2
    calib = os.path.join(folder, "camera_calib_bouguet.json")
    if not os.path.exists(calib):
        raise InputError(f"{folder}: no camera_calib_bouguet.json (is this the lcct_checkerboard_3dlaser folder?)")
    with open(calib, encoding="utf-8") as f:
        c = json.load(f)
    w, h = (int(v) for v in c["image_size"])
    fx, fy = (float(v) for v in c["fc"])
    cx, cy = (float(v) - 1.0 for v in c["cc"])  # MATLAB 1-based pixel centres
    cam = CameraModel.from_K(w, h, fx, fy, cx, cy, D=[float(v) for v in c["kc"]], distortion_model="plumb_bob")
    sq = float(c["square_mm"]) / 1000.0
    board = BoardGeometry((int(c["n_sq_y"]) + 2, int(c["n_sq_x"]) + 2), sq, tuple(board_size_m))
    frames = []
    keys = sorted(c["images"], key=int)[:max_poses]
    for k in keys:
        img_p = os.path.join(folder, f"img_target{k}.jpg")
        xyz_p = os.path.join(folder, f"laser_target{k}.xyz")
        if not (os.path.exists(img_p) and os.path.exists(xyz_p)):
            continue
        img = cv2.imread(img_p, cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"cannot read {img_p}")
        pts = np.loadtxt(xyz_p, dtype=float).reshape(-1, 3)
        st = float(k)
        frames.append(BoardFrame(st, pts, None, None, None, "laser",
                                 {"camera": CameraImage(st, img, cam, "camera_optical_frame")}))
    if not frames:
        raise InputError(f"{folder}: no img_target<k>.jpg / laser_target<k>.xyz pairs")
    T = _read_toolbox_result(os.path.join(folder, "sample_results", "Laser_Cam_calib_2.m"))
    return LcctData(frames, cam, board, T)


__all__ = ["LcctData", "read_lcct"]
