"""BoardCalibrator: collect placements, fit every camera, refuse what cannot be calibrated."""
from __future__ import annotations

import numpy as np
import pytest
from test_board_lidar import (BOARD, board_pose, camera_model, default_T_camera_lidar, lidar_sweep, make_frame,
                              poses_family, render_board_image)

from lidar_cam_calib.board.calibrator import BoardCalibrator, BoardConfig
from lidar_cam_calib.board.frame import BoardFrame, CameraImage
from lidar_cam_calib.board.overlay import render_frame_overlay
from lidar_cam_calib.core.calibrator import Calibrator
from lidar_cam_calib.core.errors import NotReadyError
from lidar_cam_calib.core.geometry import inv_T, make_T, pose_errors
from lidar_cam_calib.core.result import CalibrationSet

CAM_A = camera_model(640, 480, 560.0)
CAM_B = camera_model(640, 480, 500.0, D=(-0.05, 0.01, 0.0, 0.0, 0.0))
T_A = default_T_camera_lidar()
T_B = default_T_camera_lidar(dx=0.12, dy=-0.2, dz=-0.05, rpy_deg=(0.5, 1.0, -10.0))
CAMS = {"A": (CAM_A, T_A), "B": (CAM_B, T_B)}


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(5)
    return [make_frame(T, CAMS, rng, stamp=float(i)) for i, T in enumerate(poses_family(rng, 9))]


@pytest.fixture(scope="module")
def fitted(frames):
    cal = BoardCalibrator(BoardConfig(camera_names=["A", "B", "C"]))
    verdicts = [cal.add(f) for f in frames]
    return cal, verdicts, cal.fit()


def test_collect_and_fit_every_camera(fitted):
    cal, verdicts, cs = fitted
    assert isinstance(cal, Calibrator)
    assert sum(v.accepted for v in verdicts) >= 8, [v.reason for v in verdicts]
    assert isinstance(cs, CalibrationSet)
    for name, T in (("A", T_A), ("B", T_B)):
        r = cs.results[name]
        rot, tr = pose_errors(r.T_child_parent, T)
        assert rot < 0.15 and tr < 6.0, (name, rot, tr)
        assert r.parent_frame == "lidar" and r.child_frame == f"{name}_optical_frame"
        sr, st = r.sigma()
        assert 0 < sr < 0.3 and 0 < st < 15
        for k in ("reprojection_px", "normalized_plane_error_mm", "frames_used", "observability", "advice"):
            assert k in r.metrics
        assert r.metrics["reprojection_px"] < 1.0
    # camera C never saw the board: refused with the reason, the others still calibrated
    assert "never saw" in cs.refused["C"]
    cc = cs.extras["camera_to_camera"]["A->B"]
    rot, tr = pose_errors(np.array(cc["T"]), T_B @ inv_T(T_A))
    assert rot < 0.15 and tr < 6.0
    assert cc["shared_placements"] >= 6
    back = CalibrationSet.from_yaml(cs.to_yaml())
    assert set(back.results) == {"A", "B"} and "C" in back.refused


def test_status_reports_frames_sigma_and_missing(fitted):
    cal, _v, _cs = fitted
    st = cal.status()
    assert st["frames_per_camera"]["A"] >= 8 and st["frames_per_camera"]["C"] == 0
    assert "rotation_deg" in st["sigma"]["A"] and "refused" in st["sigma"]["C"]
    assert st["missing"]["C"] and "show the board" in st["missing"]["C"][0]
    import json
    json.dumps(st)


def test_bad_frames_rejected_with_reasons(frames):
    cal = BoardCalibrator(BoardConfig(camera_names=["A", "B"]))
    with pytest.raises(NotReadyError):
        cal.fit()
    f0 = frames[0]
    # no board anywhere: LiDAR sweep without the board
    rng = np.random.default_rng(1)
    cl = lidar_sweep(make_T(np.eye(3), [50.0, 0, 0]), rng)
    empty = BoardFrame(0.5, np.column_stack([cl["x"], cl["y"], cl["z"]]), cl["intensity"], cl["ring"])
    v = cal.add(empty)
    assert not v.accepted and "no board" in v.reason
    # board in the LiDAR, not in any image
    blank = {n: CameraImage(f0.stamp_s, np.full_like(ci.image, 90), ci.camera, ci.frame_id)
             for n, ci in f0.images.items()}
    v = cal.add(BoardFrame(f0.stamp_s, f0.points, f0.intensity, f0.ring, None, "lidar", blank))
    assert not v.accepted and "no camera image" in v.reason
    # missing CameraInfo for one camera: the other one still counts
    ims = dict(f0.images)
    ims["B"] = CameraImage(f0.stamp_s, ims["B"].image, None, "B_optical_frame")
    v = cal.add(BoardFrame(f0.stamp_s, f0.points, f0.intensity, f0.ring, None, "lidar", ims))
    assert v.accepted and "not in B" in v.reason
    assert "CameraInfo" in cal.camera_reasons["B"]
    # the same placement again
    v = cal.add(frames[0])
    assert not v.accepted and "where it was" in v.reason


def test_same_poses_refused_and_moving_board_survived(frames):
    # every placement nearly the same: refused for that camera
    rng = np.random.default_rng(9)
    cal = BoardCalibrator(BoardConfig(camera_names=["A"], duplicate_distance_m=0.0, min_placements=3,
                                      min_frames_per_camera=3))
    T = board_pose(2.6, 0.1, 0.0, 10, 10, 40)
    for i in range(4):
        Ti = T @ make_T(np.eye(3), [0.01 * i, 0, 0])
        cal.add(make_frame(Ti, {"A": CAMS["A"]}, rng, stamp=float(i)))
    with pytest.raises(Exception, match="nearly the same"):
        cal.fit()
    # the failed fit is reported by status() and not repeated on every refresh
    calls = []
    real_fit = cal._fit
    cal._fit = lambda *a: calls.append(1) or real_fit(*a)
    for _ in range(3):
        st = cal.status()
        assert "nearly the same" in st["advice"] and not st["done"]
    assert calls == []
    # a moving board: the image of one placement is from 25 cm away
    cal = BoardCalibrator(BoardConfig(camera_names=["A"]))
    for f in frames[:7]:
        cal.add(BoardFrame(f.stamp_s, f.points, f.intensity, f.ring, None, "lidar", {"A": f.images["A"]}))
    f = frames[7]
    T_true = None
    for fr_pose in poses_family(np.random.default_rng(5), 9)[7:8]:
        T_true = fr_pose
    moved = T_A @ T_true @ make_T(np.eye(3), [0.25, 0.0, 0.0])
    img = render_board_image(CAM_A, moved, rng=rng)
    cal.add(BoardFrame(f.stamp_s, f.points, f.intensity, f.ring, None, "lidar",
                       {"A": CameraImage(f.stamp_s, img, CAM_A, "A_optical_frame")}))
    cs = cal.fit()
    rot, tr = pose_errors(cs.results["A"].T_child_parent, T_A)
    assert rot < 0.2 and tr < 8.0, (rot, tr)


def test_overlay_draws_points(fitted, frames):
    cal, _v, cs = fitted
    out = render_frame_overlay(frames[0], "A", cs.results["A"].T_child_parent, cal.observations[0], BOARD)
    assert out.shape == (480, 640, 3) and out.dtype == np.uint8
    base = np.dstack([frames[0].images["A"].image] * 3).astype(int)
    assert np.abs(out.astype(int) - (0.75 * base).astype(int)).max() > 50
