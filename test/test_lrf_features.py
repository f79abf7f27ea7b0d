import numpy as np
import pytest

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.lrf.features import FeatureError, extract_depth_features, extract_scan_features
from lidar_cam_calib.lrf.frame import LrfFrame

sim = pytest.importorskip("lidar_cam_calib.sim.lrf_world")


def _frame(ranges, depth):
    cam = CameraModel.from_K(64, 36, 30.0, 30.0, 32, 18)
    return LrfFrame(0.0, ranges, -np.pi, 2 * np.pi / len(ranges), 0.1, 30.0, depth, cam)


def test_bad_inputs_give_reasons():
    f = _frame(np.full(1000, np.inf), np.full((36, 64), np.nan, np.float32))
    with pytest.raises(FeatureError, match="no valid ranges"):
        extract_scan_features(f)
    with pytest.raises(FeatureError, match="no valid depth pixels"):
        extract_depth_features(f)
    f0 = _frame(np.full(1000, 2.0), np.zeros((36, 64), np.float32))
    with pytest.raises(FeatureError, match="no valid depth pixels"):
        extract_depth_features(f0)
    with pytest.raises(FeatureError, match="board not found"):
        extract_scan_features(f0)  # a circle of constant range: no fold


def test_scan_features_on_sim_match_truth():
    from lidar_cam_calib.sim.scenario import default_scenario
    sc = default_scenario(); sc.poses.n_poses = 3
    run = sim.simulate(sc, np.random.default_rng(1))
    T = run.truth.T_camera_laser
    for o in run.observations:
        sf = extract_scan_features(LrfFrame.from_sim(o))
        # true board planes in the laser frame: the corners must lie on the true edge lines
        Tlb = np.linalg.inv(T) @ T @ np.linalg.inv(o.T_world_agv @ run.truth.T_agv_laser) @ o.T_world_board
        board = sim.FoldedBoard.from_config(sc.board)
        lines = board.edge_lines()
        for name, c in zip(("AB", "AC", "AD"), sf.corners_m):
            p, u = lines[name]
            p = Tlb[:3, :3] @ p + Tlb[:3, 3]; u = Tlb[:3, :3] @ u
            q = np.array([*c, 0.0]) - p
            assert np.linalg.norm(q - (q @ u) * u) < 0.03, name
