"""Reader and bag converter for the CMU Laser-Camera Calibration Toolbox sample
(``lcct_checkerboard_3dlaser``).

:func:`read_lcct` turns the folder into :class:`~lidar_cam_calib.board.frame.BoardFrame`
objects (one per board pose: the ``.xyz`` scan in metres, no intensity, no rings, and the
camera image), the camera model from the Bouguet calibration (``fc``, ``cc``, ``kc`` = plumb_bob
k1 k2 p1 p2 k3), the board and the toolbox's own result (``sample_results/Laser_Cam_calib_2.m``:
``p_cam = R p_laser + t``, metres) for comparison. :func:`write_lcct_bag` writes the same data
as an MCAP bag for the real node (``lidar-cam-calib lcct2bag``, then ``lidar-cam-calib calibrate board``
with ``config/board_lcct.yaml``).

* ``cc`` is used as it is: the corners of the calibration (``x_pixels``) are on OpenCV's pixel
  grid already (ours from ``findChessboardCorners`` + ``cornerSubPix`` are within 0.05 px of
  them; with ``cc - 1`` they were 1.0 px off in both axes), i.e. the Bouguet calibration used
  the [0, 0] = centre of the first pixel convention.
* The board: 8 x 6 squares of 30 mm (7 x 5 inner corners) on a panel of about 0.27 x 0.21 m
  (measured in the scans: the panel's plane points span 0.272-0.278 x 0.216-0.230 m, the pattern
  centred on it); the panel is held by a stand whose arms touch its back.
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


def read_lcct(folder: str, board_size_m: tuple = (0.27, 0.21), max_poses: int | None = None) -> LcctData:
    """Read the sample folder; raises :class:`InputError` when it is incomplete."""
    import cv2
    calib = os.path.join(folder, "camera_calib_bouguet.json")
    if not os.path.exists(calib):
        raise InputError(f"{folder}: no camera_calib_bouguet.json (is this the lcct_checkerboard_3dlaser folder?)")
    with open(calib, encoding="utf-8") as f:
        c = json.load(f)
    w, h = (int(v) for v in c["image_size"])
    fx, fy = (float(v) for v in c["fc"])
    cx, cy = (float(v) for v in c["cc"])  # on OpenCV's pixel grid already (see the module docstring)
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


TOPIC_POINTS = "/laser/points"
TOPIC_IMAGE = "/camera/image_raw"
TOPIC_INFO = "/camera/camera_info"
LASER_FRAME = "laser"
CAMERA_FRAME = "camera_optical_frame"
DEFAULT_START_STAMP_S = 1131926400.0  # 2005-11-14, the toolbox's result date


def write_lcct_bag(folder, out_dir, name: str = "lcct_checkerboard_3dlaser", overwrite: bool = False,
                   frames_per_pose: int = 3, period_s: float = 0.5, carry_s: float = 2.0,
                   max_poses: int | None = None, encoding: str = "bgr8",
                   start_stamp_s: float = DEFAULT_START_STAMP_S):
    """Write the sample as ``<out_dir>/<name>/`` (rosbag2 MCAP, zstd chunks) + ``truth.yaml``.

    Each pose is held still for ``frames_per_pose`` sweeps ``period_s`` apart (the same scan
    and image repeated: the scanner took one), each sweep with its image and CameraInfo 10 ms
    later; nothing is published for ``carry_s`` between poses (the board was carried). Topics:
    ``/laser/points`` (PointCloud2 x, y, z only, frame ``laser``), ``/camera/image_raw``
    (``encoding`` bgr8 or mono8, frame ``camera_optical_frame``), ``/camera/camera_info``.
    ``truth.yaml`` holds the toolbox's own result as ``cameras: {camera: {T_camera_lidar}}``
    (``truth_source: toolbox``: it is not an independent truth). Returns (bag_path, truth_path)."""
    import shutil
    from pathlib import Path

    import cv2
    import yaml

    from ..core.geometry import quat_from_R
    from . import convert
    from .bag import BagWriter
    from .msgtypes import RosbagsFactory, stamp_to_ns

    if encoding not in ("bgr8", "mono8"):
        raise InputError(f"encoding {encoding!r}: use bgr8 or mono8")
    if frames_per_pose < 2:
        raise InputError("frames_per_pose must be >= 2 (a still board is seen at least twice)")
    d = read_lcct(folder, max_poses=max_poses)
    if d.T_camera_laser_toolbox is None:
        raise InputError(f"{folder}: no sample_results/Laser_Cam_calib_2.m (the toolbox's result)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = out_dir / name
    if overwrite and bag_path.is_dir():
        shutil.rmtree(bag_path)
    fac = RosbagsFactory()
    counts: dict = {}
    still = []
    t = float(start_stamp_s)
    with BagWriter(bag_path, compress=True) as bw:
        def put(topic, typ, stamp, msg):
            bw.write(topic, typ, stamp_to_ns(stamp), msg)
            counts[topic] = counts.get(topic, 0) + 1
        for i, f in enumerate(d.frames):
            img = f.images["camera"].image
            if encoding == "mono8":
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            t0 = t
            for _ in range(frames_per_pose):
                put(TOPIC_POINTS, "sensor_msgs/msg/PointCloud2", t,
                    convert.arrays_to_pointcloud2(f.points, fac, fac.make_header(t, LASER_FRAME)))
                hdr = fac.make_header(t + 0.01, CAMERA_FRAME)
                put(TOPIC_IMAGE, "sensor_msgs/msg/Image", t + 0.01, convert.array_to_image(img, encoding, fac, hdr))
                put(TOPIC_INFO, "sensor_msgs/msg/CameraInfo", t + 0.01,
                    convert.camera_model_to_camera_info(d.camera, fac, hdr))
                t += period_s
            still.append({"index": i, "start_s": t0, "end_s": t - period_s + 0.01,
                          "image": f"img_target{int(f.stamp_s)}.jpg", "scan": f"laser_target{int(f.stamp_s)}.xyz"})
            t += carry_s
    T = d.T_camera_laser_toolbox
    m = d.camera
    stage1 = _read_toolbox_result(os.path.join(folder, "sample_results", "Laser_Cam_calib_1.m"))
    doc = {
        "scenario": "lcct_checkerboard_3dlaser",
        "bag": bag_path.name,
        "truth_source": "toolbox",
        "description": ("Real data: the CMU Laser-Camera Calibration Toolbox sample (15 board poses, dense 3D "
                        "laser without intensity or rings, 640x480 camera). T_camera_lidar is the TOOLBOX'S OWN "
                        "RESULT (sample_results/Laser_Cam_calib_2.m, p_camera = T @ p_laser), not an independent "
                        "truth; its stage I result (Laser_Cam_calib_1.m) is under toolbox_stage1."),
        "lidar_frame": LASER_FRAME,
        "lidar_topic": TOPIC_POINTS,
        "lidar": {"model": "dense 3D laser (actuated line scanner)", "fields": ["x", "y", "z"]},
        "cameras": {d.camera_name: {
            "T_camera_lidar": np.asarray(T, float).round(12).tolist(),
            "translation_m": T[:3, 3].round(12).tolist(),
            "quaternion_xyzw": quat_from_R(T[:3, :3]).round(12).tolist(),
            "frame_id": CAMERA_FRAME, "image_topic": TOPIC_IMAGE, "camera_info_topic": TOPIC_INFO,
            "encoding": encoding, "width": int(m.width), "height": int(m.height),
            "K": np.asarray(m.K).round(9).tolist(), "D": np.asarray(m.D).round(12).tolist(),
            "distortion_model": m.distortion_model}},
        "toolbox_stage1": {"T_camera_lidar": None if stage1 is None else np.asarray(stage1, float).round(12).tolist()},
        "board": {"squares": list(d.board.squares), "square_m": float(d.board.square_m),
                  "size_m": list(d.board.size_m), "inner_corners": list(d.board.pattern_size)},
        "start_s": float(start_stamp_s),
        "still_intervals": still,
        "message_counts": counts,
    }
    truth_path = bag_path / "truth.yaml"
    with open(truth_path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    return bag_path, truth_path


__all__ = ["LcctData", "read_lcct", "write_lcct_bag"]

