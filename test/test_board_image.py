"""Camera side of the board method: sub-pixel corners, corner order, the board's symmetry."""
from __future__ import annotations

import numpy as np
import pytest
from test_board_lidar import (BOARD, board_pose, camera_model, default_T_camera_lidar, render_board_image)

from lidar_cam_calib.board.image_corners import (CornersNotFound, canonical_order, detect_image_corners,
                                                 rotate_180)
from lidar_cam_calib.core.errors import InputError
from lidar_cam_calib.core.geometry import pose_errors

CAM = camera_model(640, 480, 520.0)
T_CL = default_T_camera_lidar()


def _truth_uv(T_cb):
    P = BOARD.inner_corners_board() @ T_cb[:3, :3].T + T_cb[:3, 3]
    return CAM.project(P)[0]


@pytest.mark.parametrize("pose", [(2.5, 0.0, 0.0, 10, 5, 35), (3.0, -0.5, 0.2, -25, -10, -40),
                                  (2.2, 0.4, -0.2, 30, 15, 0)])
def test_corners_subpixel_and_order_matches_board(pose):
    rng = np.random.default_rng(7)
    T_cb = T_CL @ board_pose(*pose)
    img = render_board_image(CAM, T_cb, rng=rng)
    ic = detect_image_corners(img, CAM, BOARD)
    uvt = _truth_uv(T_cb)
    # the order is the board's up to the 180 deg turn about the normal
    e_same = np.sqrt(np.mean(np.sum((ic.uv - uvt) ** 2, axis=1)))
    e_rot = np.sqrt(np.mean(np.sum((ic.uv[::-1] - uvt) ** 2, axis=1)))
    assert min(e_same, e_rot) < 0.5, (e_same, e_rot)  # sub-pixel (the test renderer aliases)
    # z of the board towards the camera
    assert ic.T_camera_board[:3, 2] @ ic.T_camera_board[:3, 3] < 0
    Tt = T_cb if e_same < e_rot else T_cb @ np.diag([-1.0, -1, 1, 1])
    rot, tr = pose_errors(ic.T_camera_board, Tt)
    assert rot < 0.5 and tr < 15


def test_colour_image_and_mirrored_order_are_canonicalised():
    rng = np.random.default_rng(8)
    T_cb = T_CL @ board_pose(2.8, 0.2, 0.0, -15, 10, 30)
    img = render_board_image(CAM, T_cb, rng=rng)
    ic = detect_image_corners(np.dstack([img, img, img]), CAM, BOARD)
    # feed a mirrored grid (x reversed): canonical_order must restore z towards the camera
    g = ic.uv.reshape(6, 9, 2)[:, ::-1].reshape(-1, 2)
    x = ic.xn.reshape(6, 9, 2)[:, ::-1].reshape(-1, 2)
    uv2, xn2, T2 = canonical_order(g, x, BOARD)
    assert T2[:3, 2] @ T2[:3, 3] < 0
    assert min(np.abs(uv2 - ic.uv).max(), np.abs(uv2[::-1] - ic.uv).max()) < 1e-9
    r = rotate_180(ic, BOARD)
    assert np.allclose(r.uv, ic.uv[::-1])
    assert pose_errors(r.T_camera_board @ np.diag([-1.0, -1, 1, 1]), ic.T_camera_board)[1] < 1e-9


def test_no_board_and_bad_inputs_raise():
    with pytest.raises(CornersNotFound, match="checkerboard"):
        detect_image_corners(np.full((480, 640), 100, np.uint8), CAM, BOARD)
    with pytest.raises(InputError, match="CameraInfo"):
        detect_image_corners(np.zeros((480, 640), np.uint8), None, BOARD)
    with pytest.raises(InputError, match="640x480"):
        detect_image_corners(np.zeros((240, 320), np.uint8), CAM, BOARD)
