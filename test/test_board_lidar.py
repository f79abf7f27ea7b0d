"""LiDAR side of the board method: detection, rings, edges, virtual corners.

Also holds the small synthetic scene (ray-cast spinning LiDAR, rendered
checkerboard images) the other board tests import; the method never sees it.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from lidar_cam_calib.board.frame import BoardFrame, BoardGeometry, CameraImage
from lidar_cam_calib.board.lidar_board import (BoardNotFound, LidarDetectConfig, StillBoardDetector,
                                               detect_board, recover_rings)
from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.geometry import R_BODY_OPTICAL, R_from_rpy, inv_T, make_T, pose_errors

BOARD = BoardGeometry()


# ----------------------------------------------------------------------------
# synthetic scene (test fixture only)
# ----------------------------------------------------------------------------
def board_pose(x, y, z, yaw_deg, tilt_deg, roll_deg):
    """Board facing the LiDAR at (x, y, z): z axis towards the origin."""
    c = np.array([x, y, z], float)
    zb = -c / np.linalg.norm(c)
    up = np.array([0, 0, 1.0])
    xb = np.cross(up, zb)
    xb /= np.linalg.norm(xb)
    yb = np.cross(zb, xb)
    R0 = np.column_stack([xb, yb, zb])
    R = R0 @ R_from_rpy(*np.radians([tilt_deg, yaw_deg, roll_deg]))
    return make_T(R, c)


def lidar_sweep(T_lidar_board, rng, elev_deg=None, az_step_deg=0.2, sigma_m=0.01, shrink_m=0.004,
                intensity=True, board=BOARD, bright=200.0, dark=20.0):
    """Ray-cast one spinning-LiDAR sweep: the board (reflective border,
    dark checker area) plus a floor at z = -1.2 m and a wall at x = 8 m."""
    elev = np.radians(np.arange(-15, 16, 2.0) if elev_deg is None else np.asarray(elev_deg))
    az = np.radians(np.arange(-180, 180, az_step_deg))
    E, A = np.meshgrid(elev, az, indexing="ij")
    ring = np.broadcast_to(np.arange(len(elev))[:, None], E.shape).ravel()
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    rng_best = np.full(len(d), np.inf)
    inten = np.full(len(d), np.nan)
    # floor
    t = np.where(d[:, 2] < -1e-3, -1.2 / np.minimum(d[:, 2], -1e-3), np.inf)
    upd = t < rng_best
    rng_best[upd], inten[upd] = t[upd], dark * 0.8
    # wall
    t = np.where(d[:, 0] > 1e-3, 8.0 / np.maximum(d[:, 0], 1e-3), np.inf)
    upd = t < rng_best
    rng_best[upd], inten[upd] = t[upd], dark
    # board
    R, c = T_lidar_board[:3, :3], T_lidar_board[:3, 3]
    n = R[:, 2]
    den = d @ n
    t = np.where(np.abs(den) > 1e-6, (c @ n) / np.where(np.abs(den) > 1e-6, den, 1), np.inf)
    loc = (d * np.where(np.isfinite(t), t, 0.0)[:, None] - c) @ R
    a, b = board.size_m[0] / 2 - shrink_m, board.size_m[1] / 2 - shrink_m
    onb = (t > 0) & (np.abs(loc[:, 0]) < a) & (np.abs(loc[:, 1]) < b)
    pa = board.squares[0] * board.square_m / 2
    pb = board.squares[1] * board.square_m / 2
    in_pat = (np.abs(loc[:, 0]) < pa) & (np.abs(loc[:, 1]) < pb)
    upd = onb & (t < rng_best)
    rng_best[upd] = t[upd]
    inten[upd] = np.where(in_pat[upd], dark * 1.5, bright)
    hit = np.isfinite(rng_best) & (rng_best < 30)
    r = rng_best[hit] + rng.normal(0, sigma_m, hit.sum())
    pts = d[hit] * r[:, None]
    inten = inten[hit] * rng.uniform(0.8, 1.2, hit.sum())
    return {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "ring": ring[hit],
            "intensity": inten if intensity else None}


def default_T_camera_lidar(dx=0.1, dy=0.0, dz=-0.08, rpy_deg=(1.0, -1.5, 2.0)):
    R_lidar_cam = R_from_rpy(*np.radians(rpy_deg)) @ R_BODY_OPTICAL
    return inv_T(make_T(R_lidar_cam, [dx, dy, dz]))


def camera_model(w=1280, h=960, f=1100.0, D=(-0.1, 0.08, 0.0, 0.0, 0.0)):
    return CameraModel.from_K(w, h, f, f, w / 2 - 4.0, h / 2 + 3.0, D=list(D), distortion_model="plumb_bob")


def render_board_image(cam: CameraModel, T_camera_board, board=BOARD, rng=None, noise=2.0, flip=False):
    """Mono8 image of the checkerboard (white border) by inverse mapping every pixel to the board."""
    rays = cam.pixel_rays()
    R, c = T_camera_board[:3, :3], T_camera_board[:3, 3]
    n = R[:, 2]
    den = rays @ n
    t = (c @ n) / np.where(np.abs(den) > 1e-9, den, 1e-9)
    loc = (rays * t[:, None] - c) @ R
    sq = board.square_m
    nx, ny = board.squares
    gx = np.floor(loc[:, 0] / sq + nx / 2)
    gy = np.floor(loc[:, 1] / sq + ny / 2)
    inpat = (gx >= 0) & (gx < nx) & (gy >= 0) & (gy < ny)
    onb = (np.abs(loc[:, 0]) < board.size_m[0] / 2) & (np.abs(loc[:, 1]) < board.size_m[1] / 2) & (t > 0)
    val = np.full(len(rays), 90.0)
    val[onb] = 235.0
    black = inpat & onb & (((gx + gy) % 2 == 0) ^ flip)
    val[black] = 25.0
    img = val.reshape(cam.height, cam.width).astype(np.float32)
    import cv2
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    if rng is not None:
        img = img + rng.normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def poses_family(rng, n):
    out = []
    for _ in range(n):
        out.append(board_pose(rng.uniform(2.2, 4.5), rng.uniform(-0.9, 0.9), rng.uniform(-0.3, 0.4),
                              rng.uniform(-30, 30), rng.uniform(-25, 25), rng.uniform(25, 55) * rng.choice([-1, 1])))
    return out


def make_frame(T_lb, cams: dict, rng, stamp=0.0, intensity=True, with_ring=True, **kw):
    cl = lidar_sweep(T_lb, rng, intensity=intensity, **kw)
    images = {}
    for name, (cam, T_cl) in cams.items():
        T_cb = T_cl @ T_lb
        img = render_board_image(cam, T_cb, rng=rng)
        images[name] = CameraImage(stamp, img, cam, f"{name}_optical_frame")
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    return BoardFrame(stamp, pts, cl["intensity"], cl["ring"] if with_ring else None, None, "lidar", images)


# ----------------------------------------------------------------------------
# tests
# ----------------------------------------------------------------------------
def _err(b, T):
    """Pose error allowing the 180 deg ambiguity about the normal."""
    Rz = make_T(R_from_rpy(0, 0, math.pi), [0, 0, 0])
    return min(pose_errors(b.T_lidar_board, T), pose_errors(b.T_lidar_board @ Rz, T))


def test_board_found_by_intensity_and_corners_accurate():
    rng = np.random.default_rng(1)
    errs = []
    for T in poses_family(rng, 6):
        cl = lidar_sweep(T, rng)
        pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
        b = detect_board(pts, cl["intensity"], cl["ring"], BOARD)
        assert b.mode == "intensity"
        assert b.rings_on_board >= 4
        assert b.normal @ b.centre < 0  # z towards the LiDAR
        errs.append(_err(b, T))
    rot, tr = np.array(errs).T
    assert np.median(tr) < 15.0 and tr.max() < 35.0, tr
    assert np.median(rot) < 1.0, rot


def test_board_found_by_geometry_without_intensity_and_rings():
    rng = np.random.default_rng(2)
    T = board_pose(3.0, 0.3, 0.1, 10, 10, 40)
    cl = lidar_sweep(T, rng, intensity=False)
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    b = detect_board(pts, None, None, BOARD)
    assert b.mode == "geometry"
    rot, tr = _err(b, T)
    assert tr < 30 and rot < 2.0


def test_saturated_intensity_falls_back_to_geometry():
    rng = np.random.default_rng(3)
    T = board_pose(3.0, -0.4, 0.0, -10, 5, -35)
    cl = lidar_sweep(T, rng)
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    b = detect_board(pts, np.full(len(pts), 255.0), cl["ring"], BOARD)
    assert b.mode == "geometry"
    assert _err(b, T)[1] < 30


def test_recover_rings_from_elevation():
    rng = np.random.default_rng(4)
    cl = lidar_sweep(board_pose(3, 0, 0, 0, 0, 40), rng, sigma_m=0.0)
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    r = recover_rings(pts)
    # same partition as the true ring ids
    pairs = set(zip(r.tolist(), cl["ring"].tolist()))
    assert len(pairs) == len(set(r.tolist())) == len(set(cl["ring"].tolist()))


def test_no_board_and_too_few_rings_raise_clear_errors():
    rng = np.random.default_rng(5)
    cl = lidar_sweep(board_pose(3, 0, 0, 0, 0, 40), rng)
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    far = np.linalg.norm(pts - [3, 0, 0], axis=1) > 1.0
    with pytest.raises(BoardNotFound, match="no board"):
        detect_board(pts[far], cl["intensity"][far], cl["ring"][far], BOARD)
    # a board far away crossed by two rings only
    cl = lidar_sweep(board_pose(7.0, 0, 0.0, 0, 0, 0), rng, elev_deg=[-15, -1, 1, 15], az_step_deg=0.2)
    pts = np.column_stack([cl["x"], cl["y"], cl["z"]])
    with pytest.raises(BoardNotFound, match="rings"):
        detect_board(pts, cl["intensity"], cl["ring"], BOARD, LidarDetectConfig(min_rings=4, min_points=10))


def test_virtual_corners_follow_eq1():
    T = board_pose(3, 0, 0, 0, 0, 30)
    from lidar_cam_calib.board.lidar_board import LidarBoard
    b = LidarBoard(T, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0),
                   5, 0.0, 0.0, 0.0, "test")
    V = b.virtual_corners(BOARD)
    assert V.shape == (54, 3)
    nx, ny = T[:3, 0], T[:3, 1]
    k = 1 * 9 + 2  # i = 2, j = 1
    expect = T[:3, 3] - (4 - 2) * 0.055 * nx - (2.5 - 1) * 0.055 * ny
    assert np.allclose(V[k], expect)


def test_still_detector_fires_once_per_stop():
    det = StillBoardDetector(still_time_s=0.5, tol_m=0.02)
    c, n = np.array([3.0, 0, 0]), np.array([-1.0, 0, 0])
    fired = [det.update(t, c + (0 if t >= 1.0 else 0.1 * t), n) for t in np.arange(0, 3, 0.1)]
    assert sum(fired) == 1
    assert det.update(3.1, None, None) is False
