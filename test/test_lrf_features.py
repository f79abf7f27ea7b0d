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
    sc = default_scenario()
    sc.poses.n_poses = 3
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
            p = Tlb[:3, :3] @ p + Tlb[:3, 3]
            u = Tlb[:3, :3] @ u
            q = np.array([*c, 0.0]) - p
            assert np.linalg.norm(q - (q @ u) * u) < 0.03, name


def test_depth_noise_is_estimated_from_the_image():
    from lidar_cam_calib.lrf.features import estimate_depth_noise
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:120, 0:160]
    z = 1.5 + 0.004 * u + 0.002 * v            # a tilted plane, 1.5-2.4 m
    k = 0.003
    noisy = z + rng.normal(0, 1, z.shape) * k * z ** 2
    est = estimate_depth_noise(noisy.astype(np.float32), prior_k=0.01)
    assert est.source == "data" and est.k_per_m == pytest.approx(k, rel=0.1)
    assert est.sigma(2.0) == pytest.approx(k * 4.0, rel=0.15)
    # 16UC1 millimetres: the rounding is seen and kept as a floor
    mm = np.round(noisy * 1000) / 1000
    assert estimate_depth_noise(mm.astype(np.float32), 0.01).floor_m == pytest.approx(0.001 / np.sqrt(12), rel=1e-3)
    # too small an image: the prior
    assert estimate_depth_noise(noisy[:5, :5].astype(np.float32), prior_k=0.007).k_per_m == 0.007


def test_board_model_parameters_are_described_and_checked():
    import dataclasses
    from lidar_cam_calib.core.calibrator import validate_config
    from lidar_cam_calib.core.errors import ConfigError
    from lidar_cam_calib.lrf.calibrator import LrfConfig
    from lidar_cam_calib.lrf.features import BoardModel
    names = [f.name for f in dataclasses.fields(BoardModel)]
    assert names == ["width_m", "height_m", "a_xy_m", "b_xy_m", "d_xy_m", "c_xyz_m"]
    cfg = LrfConfig()
    validate_config(cfg)
    for f in dataclasses.fields(LrfConfig):
        if f.name != "board":
            assert f.metadata.get("help"), f.name
    assert BoardModel().normal_angles_deg()[2] == pytest.approx(88.36, abs=0.05)
    with pytest.raises(ConfigError, match="outside"):
        BoardModel(a_xy_m=(0.0, 1.5)).validate()
    with pytest.raises(ConfigError, match="apex"):
        BoardModel(c_xyz_m=(0.0, 1.0, 0.0)).validate()
    with pytest.raises(ConfigError):
        validate_config(LrfConfig(laser_sigma_m=0.0))


def test_apex_down_board_is_found_in_depth_and_scan():
    from lidar_cam_calib.lrf.features import BoardModel, FeatureConfig
    from lidar_cam_calib.sim.scenario import default_scenario
    sc = default_scenario()
    sc.poses.n_poses = 2
    sc.camera.right_camera = False
    sc.camera.render_color = False
    # A near the top, B and D near the bottom edge, apex 0.3 m out near the bottom
    sc.board.a_xy_m = [0.0, 0.95]
    sc.board.b_xy_m = [-0.45, 0.1]
    sc.board.d_xy_m = [0.45, 0.05]
    sc.board.c_xyz_m = [0.05, 0.1, 0.3]
    sc.poses.board_base_height_range_m = [0.1, 0.3]
    run = sim.simulate(sc, np.random.default_rng(4))
    cfg = FeatureConfig(board=BoardModel.from_config(sc.board))
    for o in run.observations:
        fr = LrfFrame.from_sim(o)
        extract_scan_features(fr, cfg)
        df = extract_depth_features(fr, cfg)
        assert max(abs(a - m) for a, m in zip(df.angles_deg, cfg.board.normal_angles_deg())) < 2.0
