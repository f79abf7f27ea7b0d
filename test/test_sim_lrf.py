"""Tests of the lrf simulator (folded board, 2D laser, stereo depth camera, bag writer)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.geometry import inv_T, transform_points
from lidar_cam_calib.sim.lrf_world import (FACE_ABC, FACE_ACD, FACE_BASE, LABEL_NONE, DepthCameraModel,
                                           FoldedBoard, LaserModel, LrfWorld, simulate)
from lidar_cam_calib.sim.scenario import Scenario, default_scenario, load_scenario

CONFIG = Path(__file__).resolve().parents[1] / "config" / "scenarios"

SMALL = {
    "name": "lrf_test",
    "seed": 11,
    "camera": {"width_px": 160, "height_px": 90},
    "poses": {"n_poses": 4, "min_pixels_per_face": 20},
    "timeline": {"static_s": 0.6, "drive_s": 0.4, "scan_hz": 10.0, "depth_hz": 5.0},
}


def _square(center, u, v, half):
    c, u, v = (np.asarray(x, dtype=float) for x in (center, u, v))
    return np.stack([c - half * u - half * v, c + half * u - half * v,
                     c + half * u + half * v, c - half * u + half * v])


# --------------------------------------------------------------------------- ray casting
def test_laser_beam_straight_at_face_is_exact():
    las = LaserModel(angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / 3600, n_beams=3600,
                     range_sigma_m=0.0)
    # A 1 m square 2.5 m ahead (x), tilted about z and about y so it is not trivially aligned.
    n = np.array([np.cos(0.3), np.sin(0.3), 0.2])
    n /= np.linalg.norm(n)
    u = np.cross(n, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    face = _square([2.5, 0.0, 0.0], u, v, 0.5)
    r, lab = las.cast([face])
    k0 = 1800  # angle 0
    assert abs(las.angles_rad[k0]) < 1e-12
    assert r[k0] == pytest.approx(2.5, abs=1e-12)
    assert lab[k0] == 0
    # Every hit lies on the face plane (exact intersection), beams behind hit nothing.
    hit = np.isfinite(r)
    pts = np.concatenate([las.directions[hit] * r[hit, None], np.zeros((hit.sum(), 1))], axis=1)
    assert np.max(np.abs((pts - [2.5, 0, 0]) @ n)) < 1e-12
    assert np.all(np.abs(las.angles_rad[hit]) < np.radians(30))
    assert np.all(lab[~hit] == LABEL_NONE) and np.isinf(r[~hit]).all()
    # Noise-free ranges survive apply_noise unchanged (float32), no-return is +inf.
    out = las.scan([face], rng=np.random.default_rng(0), noise=False)
    assert out.dtype == np.float32 and out[k0] == np.float32(2.5) and np.isposinf(out[0])


def test_laser_angle_convention_counter_clockwise():
    las = LaserModel(n_beams=360, angle_min_rad=-np.pi, angle_increment_rad=np.radians(1.0), range_sigma_m=0.0)
    face = _square([0.0, 3.0, 0.0], [1, 0, 0], [0, 0, 1], 0.2)  # on the laser's left (+y)
    r, lab = las.cast([face])
    ang = las.angles_rad[np.isfinite(r)]
    assert np.all(np.abs(ang - np.pi / 2) < np.radians(5))  # +90 deg = left
    assert r[270] == pytest.approx(3.0, abs=1e-12)


def test_laser_noise_statistics():
    las = LaserModel(n_beams=3600, angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / 3600,
                     range_sigma_m=0.0125)
    face = _square([2.0, 0.0, 0.0], [0, 1, 0], [0, 0, 1], 1.5)
    r0, _ = las.cast([face])
    noisy = las.apply_noise(r0, np.random.default_rng(1)).astype(float)
    hit = np.isfinite(r0)
    err = noisy[hit] - r0[hit]
    assert hit.sum() > 500
    assert np.std(err) == pytest.approx(0.0125, rel=0.1)
    assert abs(np.mean(err)) < 0.003


def test_depth_of_fronto_parallel_plane_equals_distance():
    cam = CameraModel.from_K(120, 80, 100.0, 100.0, 59.5, 39.5)
    dc = DepthCameraModel(cam, sigma_disparity_px=0.0)
    wall = _square([0.0, 0.0, 2.5], [1, 0, 0], [0, 1, 0], 10.0)  # fills the view
    z, lab = dc.cast([wall])
    assert np.all(lab == 0)
    assert np.max(np.abs(z - 2.5)) < 1e-12
    # A small square 1.5 m away in front of it: depth 1.5 where it projects, 2.5 elsewhere.
    sq = _square([0.2, -0.1, 1.5], [1, 0, 0], [0, 1, 0], 0.15)
    img = dc.render([wall, sq], noise=False)
    uv, _ = cam.project(sq)
    u0, v0 = uv.min(axis=0)
    u1, v1 = uv.max(axis=0)
    vv, uu = np.mgrid[0:80, 0:120]
    inside = (uu > u0 + 0.5) & (uu < u1 - 0.5) & (vv > v0 + 0.5) & (vv < v1 - 0.5)
    outside = (uu < u0 - 0.5) | (uu > u1 + 0.5) | (vv < v0 - 0.5) | (vv > v1 + 0.5)
    assert inside.sum() > 300
    assert np.all(img[inside] == np.float32(1.5))
    assert np.all(img[outside] == np.float32(2.5))


def test_depth_noise_follows_disparity_model():
    cam = CameraModel.from_K(200, 150, 150.0, 150.0, 99.5, 74.5)
    dc = DepthCameraModel(cam, sigma_disparity_px=0.1, baseline_m=0.12)
    wall = _square([0.0, 0.0, 4.0], [1, 0, 0], [0, 1, 0], 10.0)
    img = dc.render([wall], rng=np.random.default_rng(2))
    sigma = 0.1 / (150.0 * 0.12) * 16.0
    assert np.std(img - 4.0) == pytest.approx(sigma, rel=0.05)
    # Beyond depth_max -> invalid (NaN by default).
    far = DepthCameraModel(cam, depth_max_m=3.0).render([wall], rng=np.random.default_rng(2))
    assert np.isnan(far).all()


# --------------------------------------------------------------------------- board
def test_board_edges_are_plane_intersections():
    b = FoldedBoard()
    n, d = b.planes()
    v = b.vertices
    # Vertices lie on their planes (n.p + d = 0).
    for f, names in ((FACE_BASE, "PBDQA"), (FACE_ABC, "ABC"), (FACE_ACD, "ACD")):
        for k in names:
            assert abs(n[f] @ v[k] + d[f]) < 1e-12, (f, k)
    # Any two faces: the direction of their intersection line is the shared edge.
    pairs = {"AB": (FACE_BASE, FACE_ABC), "AC": (FACE_ABC, FACE_ACD), "AD": (FACE_ACD, FACE_BASE)}
    for name, (pt, dirn) in b.edge_lines().items():
        i, j = pairs[name]
        line = np.cross(n[i], n[j])
        line /= np.linalg.norm(line)
        assert abs(abs(line @ dirn) - 1.0) < 1e-12
        assert abs(n[i] @ pt + d[i]) < 1e-12 and abs(n[j] @ pt + d[j]) < 1e-12
        end = v[name[1]]
        assert np.linalg.norm(np.cross(end - pt, dirn)) < 1e-12  # far vertex on the line too
    # Three faces well apart: pairwise normal angles > 30 deg, normals independent.
    for i in range(3):
        for j in range(i + 1, 3):
            assert np.degrees(np.arccos(np.clip(n[i] @ n[j], -1, 1))) > 30
    assert abs(np.linalg.det(n)) > 0.1
    # Normals point to the front (board +z).
    assert np.all(n[:, 2] > 0)


def test_board_scan_crosses_AB_AC_AD_in_order():
    """A horizontal scan at mid height in front of the board sees E-F-G-H-I left to right."""
    b = FoldedBoard()
    las = LaserModel(range_sigma_m=0.0)
    # Laser 2 m in front of the board at height 0.5, looking at it: laser x = -board z,
    # laser y = -board x (viewer's left = board -x), laser z = board y.
    T_laser_board = np.array([[0, 0, -1, 2.0], [-1, 0, 0, 0.0], [0, 1, 0, -0.5], [0, 0, 0, 1.0]])
    faces = [transform_points(T_laser_board, f) for f in b.faces()]
    r, lab = las.cast(faces)
    hit = lab >= 0
    seq = lab[hit][::-1]  # beams by increasing angle go right->left; reverse = left->right
    runs = [seq[0]] + [s for p, s in zip(seq[:-1], seq[1:]) if s != p]
    assert runs == [FACE_BASE, FACE_ABC, FACE_ACD, FACE_BASE]
    pts = np.concatenate([las.directions[hit] * r[hit, None], np.zeros((hit.sum(), 1))], axis=1)
    pb = transform_points(inv_T(T_laser_board), pts)
    assert np.max(np.abs(pb[:, 1] - 0.5)) < 1e-9
    g = pb[lab[hit] != FACE_BASE]
    c_z, h = b.vertices["C"][2], b.height_m
    assert g[:, 2].max() == pytest.approx(c_z * 0.5 / h, abs=2e-3)  # G on AC protrudes c_z * y / h


# --------------------------------------------------------------------------- scenario
def test_scenario_yaml_files_load_and_unknown_keys_fail():
    d = load_scenario(CONFIG / "lrf_default.yaml")
    assert d.poses.n_poses == 20 and d.laser.range_sigma_m == pytest.approx(0.0125)
    assert d.laser.resolution_deg == pytest.approx(0.042) and d.camera.baseline_m == pytest.approx(0.12)
    demo = load_scenario(CONFIG / "lrf_demo.yaml")
    assert demo.poses.n_poses == 6 and demo.camera.width_px <= 640
    assert isinstance(default_scenario(), Scenario)
    with pytest.raises(ValueError, match="laser.bogus_key"):
        load_scenario({"laser": {"bogus_key": 1}})
    with pytest.raises(ValueError, match="nonsense"):
        load_scenario({"nonsense": 1})


# --------------------------------------------------------------------------- simulate
@pytest.fixture(scope="module")
def small_run():
    return simulate(SMALL)


def test_every_pose_sees_three_faces_in_both_sensors(small_run):
    sc = load_scenario(SMALL)
    world = LrfWorld(sc)
    assert len(small_run.observations) == sc.poses.n_poses
    for ob in small_run.observations:
        vis = ob.visibility
        for face in ("base", "abc", "acd"):
            assert vis["laser"][face] >= sc.poses.min_laser_points_per_face
            assert vis["camera"][face] >= sc.poses.min_pixels_per_face
            assert vis["camera_right"][face] >= sc.poses.min_pixels_per_face
        ok, why = world.check_visibility(ob.T_world_agv, ob.T_world_board)
        assert ok, why
        # distance and sensor outputs as specified
        dist = np.linalg.norm(ob.T_world_board[:2, 3] - ob.T_world_agv[:2, 3])
        assert 1.0 < dist < 4.6
        assert ob.scan_ranges_m.dtype == np.float32 and ob.scan_ranges_m.size == 8571
        assert ob.depth_m.shape == (90, 160) and ob.depth_m.dtype == np.float32
        assert ob.depth_right_m.shape == (90, 160) and ob.color_bgr.shape == (90, 160, 3)
        assert ob.camera.width == 160 and ob.camera_right is not None


def test_truth_composition_and_laser_points_on_camera_planes(small_run):
    world = LrfWorld(SMALL)
    tr = small_run.truth
    assert np.allclose(tr.T_camera_laser, inv_T(tr.T_agv_camera) @ tr.T_agv_laser)
    # Paper Table 3 like mount: laser 128 mm behind, 60 mm right of, 10 mm above the camera.
    assert np.allclose(tr.T_camera_laser[:3, 3], [0.06, -0.01, -0.128], atol=1e-9)
    assert np.allclose(tr.T_right_left[:3, 3], [-0.12, 0, 0]) and np.allclose(tr.T_right_left[:3, :3], np.eye(3))
    assert np.allclose(tr.T_camera_right_laser, tr.T_right_left @ tr.T_camera_laser)
    n_b, d_b = world.board.planes()
    for ob in small_run.observations:
        T_wl = ob.T_world_agv @ tr.T_agv_laser
        T_wc = ob.T_world_agv @ tr.T_agv_camera
        corners = world.board.corners()
        in_laser = transform_points(inv_T(T_wl) @ ob.T_world_board, corners)
        in_cam = transform_points(inv_T(T_wc) @ ob.T_world_board, corners)
        assert np.max(np.abs(transform_points(tr.T_camera_laser, in_laser) - in_cam)) < 1e-12
        # Noise-free laser points on each face, moved with the truth, lie on the camera's plane.
        r, lab = world.cast_scan(ob.T_world_agv, ob.T_world_board)
        T_cb = inv_T(T_wc) @ ob.T_world_board
        for f in (FACE_BASE, FACE_ABC, FACE_ACD):
            m = lab == f
            p_l = np.concatenate([world.laser.directions[m] * r[m, None], np.zeros((m.sum(), 1))], axis=1)
            p_c = transform_points(tr.T_camera_laser, p_l)
            n_c = T_cb[:3, :3] @ n_b[f]
            d_c = d_b[f] - n_c @ T_cb[:3, 3]
            assert np.max(np.abs(p_c @ n_c + d_c)) < 1e-9
        # The noisy depth image agrees with the noise-free one to a few sigma.
        z, labc = world.cast_depth(ob.T_world_agv, ob.T_world_board)
        board = (labc >= 0) & (labc <= 2)
        dz = ob.depth_m.ravel()[board] - z[board]
        k = world.depth_cam.k_noise
        assert np.all(np.abs(dz) < 6 * k * z[board] ** 2 + 1e-6)


def test_simulation_is_deterministic_with_seed(small_run):
    again = simulate(SMALL)
    other = simulate({**SMALL, "seed": 12})
    for a, b in zip(small_run.observations, again.observations):
        assert np.array_equal(a.T_world_agv, b.T_world_agv)
        assert np.array_equal(a.scan_ranges_m, b.scan_ranges_m)
        assert np.array_equal(a.depth_m, b.depth_m, equal_nan=True)
    assert not np.allclose(small_run.observations[0].T_world_agv, other.observations[0].T_world_agv)
    # Pose set is varied: distances and headings spread over their ranges.
    dist = [np.linalg.norm(o.T_world_board[:2, 3] - o.T_world_agv[:2, 3]) for o in small_run.observations]
    assert np.ptp(dist) > 0.8


# --------------------------------------------------------------------------- bag
def test_bag_roundtrip(tmp_path):
    pytest.importorskip("lidar_cam_calib.io.bag")
    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.bag import bag_topics, read_bag
    from lidar_cam_calib.io.msgtypes import RosbagsFactory
    from lidar_cam_calib.sim.lrf_bag import build_timeline, write_lrf_bag

    sc = load_scenario(SMALL)
    bag, truth_path = write_lrf_bag(sc, tmp_path)
    assert bag.is_dir() and truth_path == tmp_path / "lrf_test" / "truth.yaml"
    topics = bag_topics(bag)
    expect = {"/scan": "sensor_msgs/msg/LaserScan", "/camera/depth/image_raw": "sensor_msgs/msg/Image",
              "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo",
              "/camera/color/image_raw": "sensor_msgs/msg/Image",
              "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
              "/camera_right/depth/image_raw": "sensor_msgs/msg/Image",
              "/camera_right/depth/camera_info": "sensor_msgs/msg/CameraInfo"}
    assert topics == expect
    scans, depths, statics = build_timeline(sc.poses.n_poses, sc.timeline)
    # 4 poses: 3 x (0.6 + 0.4 s) + 0.6 s = 3.6 s -> 37 scans at 10 Hz, 18 depth frames at 5 Hz.
    assert len(scans) == 37 and len(depths) == 18
    fac = RosbagsFactory()
    last, counts, frames = {}, {}, {}
    recs = list(read_bag(bag))
    for rec in recs:
        assert rec.stamp_ns > last.get(rec.topic, -1), rec.topic
        last[rec.topic] = rec.stamp_ns
        counts[rec.topic] = counts.get(rec.topic, 0) + 1
        msg = fac.deserialize(rec.raw, rec.typename)
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == rec.stamp_ns
        frames.setdefault(rec.topic, msg.header.frame_id)
    assert counts["/scan"] == 37
    for t in expect:
        if t != "/scan":
            assert counts[t] == 18, t
    assert frames["/scan"] == "laser"
    assert frames["/camera/depth/image_raw"] == "camera_depth_optical_frame"
    assert frames["/camera_right/depth/image_raw"] == "camera_right_depth_optical_frame"
    assert all(a.stamp_ns <= b.stamp_ns for a, b in zip(recs[:-1], recs[1:]))
    truth = yaml.safe_load(truth_path.read_text())
    ref = simulate(sc)
    assert np.allclose(truth["T_camera_laser"], ref.truth.T_camera_laser, atol=1e-9)
    assert truth["seed"] == 11 and truth["scenario"] == "lrf_test"
    assert len(truth["static_intervals"]) == 4
    assert truth["topics"]["scan"] == "/scan"
    assert np.allclose(truth["right_camera"]["T_right_left"]["translation_m"], [-0.12, 0, 0])
    # Poses in the truth file are the simulate() poses; a static depth frame matches them.
    iv = truth["static_intervals"][1]
    assert np.allclose(iv["T_world_agv"], ref.observations[1].T_world_agv)
    world = LrfWorld(sc)
    z, _ = world.cast_depth(np.array(iv["T_world_agv"]), np.array(iv["T_world_board"]))
    for rec in recs:
        if rec.topic == "/camera/depth/image_raw" and iv["start_s"] * 1e9 <= rec.stamp_ns <= iv["end_s"] * 1e9:
            d = convert.depth_image_to_m(fac.deserialize(rec.raw, rec.typename)).ravel()
            ok = np.isfinite(d) & np.isfinite(z)
            assert ok.mean() > 0.95
            # Error normalised by the model sigma k z^2 is ~N(0, 1): median |e| = 0.674.
            e = (d[ok] - z[ok]) / (world.depth_cam.k_noise * z[ok] ** 2)
            assert 0.6 < np.median(np.abs(e)) < 0.75
            assert abs(np.median(e)) < 0.05
            break
    else:
        pytest.fail("no depth frame in a static interval")
    # Scan messages carry the laser geometry.
    scan = fac.deserialize(next(r for r in recs if r.topic == "/scan").raw, "sensor_msgs/msg/LaserScan")
    assert len(scan.ranges) == 8571 and scan.angle_min == pytest.approx(-np.pi)
    assert scan.angle_increment == pytest.approx(2 * np.pi / 8571)
