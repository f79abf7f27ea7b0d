"""Simulator for the ``board`` method: LiDAR presets, board casting, intensity, edge shrink,
rendered checker corners against the truth, the bag round trip and the scenario family."""
from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
import yaml
from conftest import ROOT

from lidar_cam_calib.core.geometry import inv_T, make_T, so3_exp, transform_points
from lidar_cam_calib.sim.board_world import (
    BoardScenario,
    BoardSpec,
    BoardWorld,
    CameraSpec,
    LidarSpec,
    PosesSpec,
    TimelineSpec,
    default_board_scenario,
    load_board_scenario,
    sample_board_family,
    simulate_board,
)
from lidar_cam_calib.sim.lidar import PRESETS

SCEN = os.path.join(ROOT, "config", "scenarios")


def _facing_lidar(dist_m: float, roll_deg: float = 0.0, yaw_deg: float = 0.0, z_m: float = 0.0) -> np.ndarray:
    """Board straight ahead of the LiDAR, patterned face towards it, long side horizontal."""
    R0 = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns: x_b, y_b, z_b
    z = np.array([0, 0, 1.0])
    R = so3_exp(z * np.deg2rad(yaw_deg)) @ R0 @ so3_exp(z * np.deg2rad(roll_deg))
    return make_T(R, np.array([dist_m, 0.0, z_m]))


def _facing_camera(world: BoardWorld, name: str, dist_m: float, roll_deg: float, yaw_deg: float) -> np.ndarray:
    """Board on the optical axis of camera ``name``, facing it, as T_lidar_board."""
    R_cb0 = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # board x right, y up, z to the camera
    R_cb = so3_exp(np.array([0, 1.0, 0]) * np.deg2rad(yaw_deg)) @ R_cb0 \
        @ so3_exp(np.array([0, 0, 1.0]) * np.deg2rad(roll_deg))
    T_cb = make_T(R_cb, np.array([0.02, -0.01, dist_m]))
    return inv_T(world.cameras[name].T_camera_lidar) @ T_cb


def _small_scenario(preset: str = "rs16", **lidar_kw) -> BoardScenario:
    return BoardScenario(
        name="t_board", seed=5,
        lidar=LidarSpec(preset=preset, **lidar_kw),
        cameras=[CameraSpec(name="cam_a", type="vga", encoding="mono8", rate_hz=10.0, xyz_m=[0.1, 0.05, -0.1])],
        poses=PosesSpec(n_poses=2, distance_m=[2.0, 3.5]),
        timeline=TimelineSpec(still_s=[0.5, 0.6], carry_s=[0.4, 0.5], memory_still_frames=1, memory_carry_frames=1))


# -- presets -----------------------------------------------------------------------------------
@pytest.mark.parametrize("key,rings,lo,hi", [("rs16", 16, -15.0, 15.0), ("vlp16", 16, -15.0, 15.0),
                                             ("vlp32", 32, -25.0, 15.0), ("hdl64", 64, -24.33, 2.0),
                                             ("os1_64", 64, -16.611, 16.611)])
def test_presets_rings_elevations_azimuth_and_time(key, rings, lo, hi):
    p = PRESETS[key]
    dirs, ring, az, t = p.ray_directions()
    assert p.n_rings == rings
    assert dirs.shape == (rings * p.n_columns, 3) and ring.dtype == np.uint16
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    assert sorted(np.unique(ring)) == list(range(rings))
    el = np.rad2deg(np.arcsin(dirs[:, 2]))
    table = p.ring_elevations_deg()
    np.testing.assert_allclose(el, table[ring], atol=1e-9)
    assert table.min() == pytest.approx(lo, abs=1e-3) and table.max() == pytest.approx(hi, abs=1e-3)
    assert 0.0 <= t.min() and t.max() < p.period_s
    # one column per azimuth step, turning clockwise seen from above
    col0 = np.flatnonzero(ring == ring[0])[:3]
    step = np.rad2deg(np.angle(np.exp(1j * (az[col0[1]] - az[col0[0]]))))
    assert step == pytest.approx(-p.azimuth_step_deg, abs=1e-9)
    if key == "os1_64":  # Ouster drivers number rings from the top beam down
        assert table[0] > table[-1]
    if key == "rs16":  # paper 000: 0-255 intensity, threshold 250
        assert p.intensity_scale == "uint8" and p.intensity_threshold == 250.0


def test_preset_fov_crop_keeps_only_the_sector():
    p = PRESETS["vlp16"]
    _d, _r, az, _t = p.ray_directions((-30.0, 45.0))
    a = np.rad2deg(az)
    assert a.min() >= -30.0 - 1e-9 and a.max() <= 45.0 + 1e-9
    assert a.size == pytest.approx(p.n_rings * 75.0 / p.azimuth_step_deg, rel=0.02)


# -- LiDAR on the board ------------------------------------------------------------------------
@pytest.mark.parametrize("key", ["rs16", "vlp32", "os1_64"])  # 0-255, 0-1 and 16-bit scales
def test_board_points_on_plane_and_border_intensity(key):
    sc = _small_scenario(key, dropout_prob=0.0, mixed_pixel_prob=0.0)
    w = BoardWorld(sc, np.random.default_rng(1), full_size=False)
    T = _facing_lidar(3.0, roll_deg=40.0, yaw_deg=20.0)
    cloud, info = w.lidar_sweep(0.0, np.random.default_rng(2), T_lidar_board=T)
    p = w.preset
    P = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1).astype(float)
    Pb = transform_points(inv_T(T), P)
    lab = info["label"]
    on = (lab == 1) | (lab == 2)
    assert on.sum() > 100
    sig = p.range_sigma_m
    assert 0.3 * sig < Pb[on, 2].std() < 1.3 * sig
    assert np.all(np.abs(Pb[on, 2]) < 6 * sig + 0.005)
    thr = p.intensity_threshold
    inten = cloud["intensity"]
    assert inten.dtype == np.float32 and inten.max() <= p.intensity_max
    bw, bh = w.board.size_m[0] / 2, w.board.size_m[1] / 2
    cw, ch = w.board.checker_size_m[0] / 2, w.board.checker_size_m[1] / 2
    ax, ay = np.abs(Pb[:, 0]), np.abs(Pb[:, 1])
    deep_border = (lab == 1) & (ax < bw - 0.05) & (ay < bh - 0.05) & ((ax > cw + 0.05) | (ay > ch + 0.05))
    assert deep_border.sum() > 20
    assert np.mean(inten[deep_border] > thr) > 0.97
    assert np.all(inten[lab == 0] < thr)  # no distractor in this scene
    assert np.all(inten[lab == 2] < thr)


def test_edge_mixing_shrinks_the_board_by_millimetres():
    sc = _small_scenario("rs16", dropout_prob=0.0, mixed_pixel_prob=0.0, range_sigma_m=0.0)
    w = BoardWorld(sc, np.random.default_rng(1), full_size=False)
    T = _facing_lidar(3.0, roll_deg=45.0)
    cloud, info = w.lidar_sweep(0.0, np.random.default_rng(2), T_lidar_board=T)
    P = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1).astype(float)
    Pb = transform_points(inv_T(T), P)
    bw, bh = w.board.size_m[0] / 2, w.board.size_m[1] / 2
    hi = cloud["intensity"] > w.preset.intensity_threshold
    inset = np.minimum(bw - np.abs(Pb[hi, 0]), bh - np.abs(Pb[hi, 1]))
    assert inset.min() > 0.002  # every high-intensity return lies > 2 mm inside the edge
    # the edge returns themselves are there, with lowered intensity
    edge = (info["label"] > 0) & ~hi
    assert edge.sum() > 10
    # per ring, the thresholded end points are millimetres (not centimetres... at most a few) inside
    ends = []
    for r in np.unique(cloud["ring"][hi]):
        m = np.flatnonzero(hi & (cloud["ring"] == r))
        for k in (m[0], m[-1]):
            ends.append(min(bw - abs(Pb[k, 0]), bh - abs(Pb[k, 1])))
    ends = np.array(ends)
    assert 0.003 < np.median(ends) < 0.03


def test_moving_board_is_smeared_and_flagged_not_still():
    run = simulate_board(_small_scenario("vlp16"), np.random.default_rng(3), full_size=False)
    still = [f for f in run.frames if f.still]
    moving = [f for f in run.frames if not f.still]
    assert still and moving
    for f in still:
        assert any(np.allclose(f.T_lidar_board, T) for T in run.poses)
        assert set(f.images) == set(run.cameras)
    for f in moving:
        assert not any(np.allclose(f.T_lidar_board, T) for T in run.poses)
    assert set(still[0].cloud) == {"x", "y", "z", "intensity", "ring", "time"}
    stamps = [f.stamp_s for f in run.frames]
    assert stamps == sorted(stamps)
    assert run.noise["range_sigma_m"] == pytest.approx(PRESETS["vlp16"].range_sigma_m)


def test_carried_board_is_motion_blurred():
    sc = _small_scenario("vlp16")
    sc.cameras[0].exposure_time_s = 0.03
    sc.cameras[0].noise_sigma_dn = 0.0
    w = BoardWorld(sc, np.random.default_rng(1), full_size=False)
    c0, c1 = w.carries[0]
    tm = 0.5 * (c0 + c1)
    Ts = w.board_poses_exposed("cam_a", tm)
    assert len(Ts) == 5 and not np.allclose(Ts[0], Ts[-1])
    a, b = w.still_intervals[0]
    assert len(w.board_poses_exposed("cam_a", 0.5 * (a + b))) == 1
    sharp = w.render("cam_a", Ts[2], np.random.default_rng(0)).astype(float)
    blurred = w.render("cam_a", Ts, np.random.default_rng(0)).astype(float)
    def grad(im):
        return np.abs(np.diff(im, axis=1)).sum()

    assert grad(blurred) < grad(sharp)


def test_dropped_fields_are_absent():
    sc = _small_scenario("rs16", drop_fields=["time", "ring"])
    w = BoardWorld(sc, np.random.default_rng(1), full_size=False)
    cloud, _ = w.lidar_sweep(0.0, np.random.default_rng(2))
    assert set(cloud) == {"x", "y", "z", "intensity"}
    cloud, _ = BoardWorld(_small_scenario("hdl64"), np.random.default_rng(1), full_size=False).lidar_sweep(
        0.0, np.random.default_rng(2))
    assert "time" not in cloud and "ring" in cloud


# -- camera rendering --------------------------------------------------------------------------
@pytest.mark.parametrize("cam_type,roll,yaw,dist", [("mer132", 45.0, 20.0, 2.2), ("fisheye1280", -30.0, -15.0, 1.6)])
def test_rendered_corners_match_truth_projection(cam_type, roll, yaw, dist):
    sc = BoardScenario(name="t_render", seed=2, cameras=[CameraSpec(name="c", type=cam_type, encoding="bgr8")],
                       poses=PosesSpec(n_poses=1))
    w = BoardWorld(sc, np.random.default_rng(0))
    T = _facing_camera(w, "c", dist, roll, yaw)
    img = w.render("c", T, np.random.default_rng(1))
    cam = w.cameras["c"]
    assert img.shape == (cam.model.height, cam.model.width, 3) and img.dtype == np.uint8
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    ok, det = cv2.findChessboardCornersSB(gray, w.board.inner_corners, flags=cv2.CALIB_CB_ACCURACY)
    assert ok, "the 9x6 inner corners must be detectable"
    det = det.reshape(-1, 2)
    uv, valid = cam.model.project(transform_points(cam.T_camera_lidar @ T, w.board.inner_corners_board()))
    assert valid.all()
    d = np.linalg.norm(det[:, None, :] - uv[None, :, :], axis=2)
    err = d.min(axis=0)
    assert len(set(d.argmin(axis=0))) == len(uv)  # one-to-one
    assert err.mean() < 0.15 and err.max() < 0.5, (err.mean(), err.max())
    # the detector's outer corners wander a little; sub-pixel refinement agrees everywhere
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    ref = cv2.cornerSubPix(gray, det.reshape(-1, 1, 2).astype(np.float32), (5, 5), (-1, -1), crit).reshape(-1, 2)
    err_ref = np.linalg.norm(ref[:, None, :] - uv[None, :, :], axis=2).min(axis=0)
    assert err_ref.mean() < 0.1 and err_ref.max() < 0.3, (err_ref.mean(), err_ref.max())
    # colours: square (0, 0) at -x,-y is black, its +x neighbour white, the border in between
    b = w.board
    cw, ch, s = b.checker_size_m[0] / 2, b.checker_size_m[1] / 2, b.square_m
    pts = np.array([[-cw + s / 2, -ch + s / 2, 0], [-cw + 1.5 * s, -ch + s / 2, 0], [0, b.size_m[1] / 2 - 0.04, 0]])
    q, _ = cam.model.project(transform_points(cam.T_camera_lidar @ T, pts))
    g = [int(gray[round(v), round(u)]) for u, v in q]
    assert g[0] < 60 < g[2] < g[1]


def test_mono_camera_and_board_out_of_view_still_gives_an_image():
    sc = _small_scenario()
    w = BoardWorld(sc, np.random.default_rng(0), full_size=False)
    T_behind = _facing_lidar(3.0)
    T_behind[:3, 3] = [-4.0, 0.0, 0.0]
    img = w.render("cam_a", T_behind, np.random.default_rng(1))
    m = w.cameras["cam_a"].model
    assert img.shape == (m.height, m.width) and img.dtype == np.uint8
    assert not w.board_fully_in_view(w.cameras["cam_a"], T_behind)


# -- scenario, family, bag ---------------------------------------------------------------------
def test_scenario_files_load_and_unknown_keys_fail():
    demo = load_board_scenario(os.path.join(SCEN, "board_demo.yaml"))
    full = load_board_scenario(os.path.join(SCEN, "board_default.yaml"))
    assert len(demo.cameras) == 2 and demo.poses.n_poses <= 10
    assert full.lidar.preset == "rs16" and [c.type for c in full.cameras] == ["mer132", "zed2_left"]
    m = full.cameras[0].model()
    assert (m.width, m.height, m.fx, m.cx) == (1292, 964, 1097.9, 652.383)
    with pytest.raises(ValueError, match="lidar.bogus"):
        load_board_scenario({"lidar": {"bogus": 1}})
    with pytest.raises(ValueError, match="unknown LiDAR preset"):
        load_board_scenario({"lidar": {"preset": "nope"}})
    assert default_board_scenario().board.inner_corners == (9, 6)


def test_board_spec_corners_follow_paper_eq1():
    c = BoardSpec().inner_corners_board()
    assert c.shape == (54, 3)
    np.testing.assert_allclose(c[0], [-4 * 0.055, -2.5 * 0.055, 0])
    np.testing.assert_allclose(c[1] - c[0], [0.055, 0, 0])
    np.testing.assert_allclose(c[9] - c[0], [0, 0.055, 0])
    with pytest.raises(ValueError):
        BoardSpec(squares=(20, 7))  # 1.1 m of checker in a 1.0 m board


def test_family_varies_presets_cameras_and_is_deterministic():
    draws = [sample_board_family(s) for s in range(12)]
    assert len({d.lidar.preset for d in draws}) >= 3
    assert len({len(d.cameras) for d in draws}) >= 2
    assert len({c.type for d in draws for c in d.cameras}) >= 3
    assert len({d.poses.n_poses for d in draws}) >= 5
    assert {c.encoding for d in draws for c in d.cameras} == {"mono8", "bgr8"}
    assert sample_board_family(4).to_dict() == sample_board_family(4).to_dict()
    assert sample_board_family(4, poses=7, lidar="hdl64").poses.n_poses == 7
    assert sample_board_family(4, lidar="os1").lidar.preset == "os1_64"
    # a drawn scenario survives the YAML round trip
    again = load_board_scenario(yaml.safe_load(yaml.safe_dump(draws[3].to_dict())))
    assert again.to_dict() == draws[3].to_dict()


def test_family_scenario_places_every_pose_in_some_camera():
    sc = sample_board_family(11, poses=4)
    w = BoardWorld(sc, np.random.default_rng(sc.seed), full_size=False)
    for T in w.poses:
        assert any(w.board_fully_in_view(c, T) for c in w.cameras.values())


def test_bag_round_trip(tmp_path):
    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.bag import read_bag
    from lidar_cam_calib.io.msgtypes import RosbagsFactory
    from lidar_cam_calib.sim.board_bag import write_board_bag

    sc = _small_scenario("rs16", azimuth_range_deg=[-60.0, 60.0])
    sc.cameras.append(CameraSpec(name="cam_b", type="vga", encoding="bgr8", rate_hz=7.0, time_offset_s=-0.02,
                                 xyz_m=[0.1, -0.05, -0.1], rpy_deg=[0, 0, -20.0]))
    bag, truth_path = write_board_bag(sc, tmp_path, seed=9)
    with open(truth_path, encoding="utf-8") as fh:
        truth = yaml.safe_load(fh)
    assert truth["lidar_frame"] == "lidar" and truth["preset"] == "rs16"
    assert set(truth["cameras"]) == {"cam_a", "cam_b"}
    for name, c in truth["cameras"].items():
        assert c["frame_id"] == f"{name}_optical_frame" and c["image_topic"] == f"/{name}/image_raw"
        T = np.array(c["T_camera_lidar"])
        assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert truth["board"]["squares"] == [10, 7] and truth["noise"]["range_sigma_m"] > 0
    fac = RosbagsFactory()
    counts, last, seen = {}, {}, {}
    for rec in read_bag(bag):
        counts[rec.topic] = counts.get(rec.topic, 0) + 1
        assert rec.stamp_ns > last.get(rec.topic, -1)
        last[rec.topic] = rec.stamp_ns
        if rec.topic not in seen:
            seen[rec.topic] = fac.deserialize(rec.raw, rec.typename)
    assert counts == truth["message_counts"]
    assert set(counts) == {"/lidar/points", "/cam_a/image_raw", "/cam_a/camera_info", "/cam_b/image_raw",
                           "/cam_b/camera_info"}
    cloud = convert.pointcloud2_to_arrays(seen["/lidar/points"])
    assert {"xyz", "intensity", "ring", "time_s"} <= set(cloud)
    assert cloud["xyz"].shape[0] > 1000 and cloud["time_s"].max() < 0.1
    assert seen["/lidar/points"].header.frame_id == "lidar"
    img = convert.image_to_array(seen["/cam_b/image_raw"])
    assert img.shape == (480, 640, 3) and seen["/cam_b/image_raw"].encoding == "bgr8"
    model = convert.camera_info_to_model(seen["/cam_a/camera_info"])
    assert model.width == 640 and model.fx == pytest.approx(520.0)
    with pytest.raises(Exception, match="exists"):
        write_board_bag(sc, tmp_path, seed=9)
