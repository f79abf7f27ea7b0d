"""Street simulator for the targetless method: geometry truth, rolling sweep, rendering, bag, family."""
import dataclasses
import os

import numpy as np
import pytest
import yaml
from conftest import ROOT

from lidar_cam_calib.core.errors import ConfigError
from lidar_cam_calib.core.geometry import inv_T, pose_errors
from lidar_cam_calib.sim.street_world import (
    CYL,
    load_street_scenario,
    sample_street_family,
    simulate_drive,
)


def _scenario(speed_kmh=40.0, preset="vlp16", mixed=False, **cam):
    """Noise-free, short, small-image scenario."""
    return load_street_scenario({
        "name": "street_test", "seed": 3,
        "lidar": {"preset": preset, "range_sigma_m": 0.0, "dropout_prob": 0.0,
                  "crown_pass_prob": 0.0, "crown_depth_m": 0.0, "mixed_edge_returns": mixed},
        "camera": {"noise_sigma": 0.0, **cam},
        "motion": {"speed_kmh": speed_kmh, "speed_amplitude_kmh": 0.0},
        "timing": {"duration_s": 0.25},
    })


def _world_points(run, sw, per_point_time=True):
    c = sw.cloud
    P = np.stack([c["x"], c["y"], c["z"]], 1).astype(float)
    t = sw.stamp_s + (c["time"].astype(float) if per_point_time else 0.0 * P[:, 0])
    T = run.T_world_lidar(t)
    return np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3], t - run.scenario.timing.start_stamp_s


@pytest.fixture(scope="module")
def moving_run():
    return simulate_drive(_scenario(40.0), image_scale=0.2, with_labels=True)


def test_points_lie_on_primitives_and_sweep_bends_at_speed(moving_run):
    run = moving_run
    sw = run.sweeps[1]
    assert {"x", "y", "z", "intensity", "ring", "time"} <= set(sw.cloud)
    assert len(sw.cloud["x"]) > 15000 and sw.dynamic.shape == sw.cloud["x"].shape
    assert float(sw.cloud["time"].min()) >= 0 and float(sw.cloud["time"].max()) < 0.1
    Pw, trel = _world_points(run, sw)
    static = ~sw.dynamic
    d = run.world.distance_to_surfaces(Pw[static], t_rel=0.0)
    tol = 1e-4 + 0.5 * run.lidar.range_resolution_m  # the driver quantises ranges
    assert np.quantile(d, 0.999) < tol, "static points must lie on the primitives (noise-free)"
    if sw.dynamic.any():  # moving objects are placed per 1/72 sweep: within a few cm
        dd = np.array([run.world.distance_to_surfaces(p[None], t_rel=t)[0]
                       for p, t in zip(Pw[sw.dynamic][:50], trel[sw.dynamic][:50])])
        assert np.max(dd) < 0.05
    # Transforming with the sweep-start pose only (no de-skew) misplaces late points by v * t.
    Pw0, _ = _world_points(run, sw, per_point_time=False)
    # (judged on poles, trunks, posts: moving along the road keeps ground/facade points on them)
    late = static & (sw.cloud["time"] > 0.07) & (run.world.ptype_arr[sw.label] == CYL)
    assert late.sum() > 50
    d0 = run.world.distance_to_surfaces(Pw0[late], t_rel=0.0)
    v = 40.0 / 3.6
    assert np.median(d0) > 0.3 * v * 0.07, "rolling-sweep distortion missing at 40 km/h"


def test_no_distortion_at_standstill():
    run = simulate_drive(_scenario(0.0), duration_s=0.1, image_scale=0.2)
    sw = run.sweeps[0]
    Pw0, _ = _world_points(run, sw, per_point_time=False)
    d = run.world.distance_to_surfaces(Pw0[~sw.dynamic][::5], t_rel=0.0)
    assert np.quantile(d, 0.999) < 1e-4 + 0.5 * run.lidar.range_resolution_m
    assert np.allclose(run.T_world_lidar(sw.stamp_s), run.T_world_lidar(sw.stamp_s + 0.09))
    # with mixed returns at depth edges, a small fraction of points floats between surfaces
    run = simulate_drive(_scenario(0.0, mixed=True), duration_s=0.1, image_scale=0.2)
    sw = run.sweeps[0]
    Pw0, _ = _world_points(run, sw, per_point_time=False)
    d = run.world.distance_to_surfaces(Pw0[~sw.dynamic], t_rel=0.0)
    assert 0.001 < np.mean(d > 0.05) < 0.05


def test_truth_projection_lands_on_landmark_pixels(moving_run):
    """LiDAR points on landmarks, moved by the ego poses at their times into the camera at its
    exposure, hit pixels rendered from the same primitive (the truth chain is consistent)."""
    run = moving_run
    lm_pids = {p for lm in run.landmarks for p in lm["pids"]}
    hits = total = 0
    for sw in run.sweeps:
        Pw, _ = _world_points(run, sw)
        for im in run.images:
            if abs(im.exposure_s - sw.stamp_s - 0.05) > 0.08:
                continue
            T_wc = run.T_world_lidar(im.exposure_s) @ inv_T(run.T_camera_lidar)
            Pc = (Pw - T_wc[:3, 3]) @ T_wc[:3, :3]
            uv, ok = run.camera.project(Pc)
            sel = ok & np.isin(sw.label, list(lm_pids)) & (Pc[:, 2] < 30)
            px = np.round(uv[sel]).astype(int)
            lab = im.label[np.clip(px[:, 1], 0, im.label.shape[0] - 1), np.clip(px[:, 0], 0, im.label.shape[1] - 1)]
            hits += int(np.sum(lab == sw.label[sel]))
            total += int(sel.sum())
    assert total > 100
    assert hits / total > 0.8, f"only {hits}/{total} landmark points land on their pixels"


def test_images_have_sift_texture_and_dynamic_mask():
    cv2 = pytest.importorskip("cv2")
    run = simulate_drive(_scenario(20.0), duration_s=0.12, image_scale=0.5)
    im = run.images[0]
    assert im.image.shape == (482, 644, 3) and im.image.dtype == np.uint8
    assert abs(im.stamp_s - im.exposure_s - run.time_offset_s) < 1e-6
    kp = cv2.SIFT_create().detect(cv2.cvtColor(im.image, cv2.COLOR_BGR2GRAY), None)
    assert len(kp) > 300
    assert im.dynamic_mask.shape == im.image.shape[:2]


def test_bag_round_trip(tmp_path):
    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.bag import BagError, bag_topics, read_bag
    from lidar_cam_calib.io.msgtypes import RosbagsFactory
    from lidar_cam_calib.sim.street_bag import write_street_bag

    sc = dataclasses.replace(_scenario(30.0), name="street_bag_test")
    bag, truth_p = write_street_bag(sc, tmp_path, image_scale=0.15, duration_s=0.3)
    assert bag_topics(bag) == {"/lidar/points": "sensor_msgs/msg/PointCloud2",
                               "/camera/image_raw": "sensor_msgs/msg/Image",
                               "/camera/camera_info": "sensor_msgs/msg/CameraInfo"}
    truth = yaml.safe_load(truth_p.read_text())
    assert truth["message_counts"]["/lidar/points"] == 3
    assert truth["message_counts"]["/camera/image_raw"] == truth["message_counts"]["/camera/camera_info"] == 3
    assert truth["lidar_preset"] == "vlp16" and truth["speed_set"] == "slow"
    fac = RosbagsFactory()
    recs = list(read_bag(bag))
    assert [r.stamp_ns for r in recs] == sorted(r.stamp_ns for r in recs)
    pc = next(fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/lidar/points")
    arr = convert.pointcloud2_to_arrays(pc)
    assert pc.header.frame_id == "lidar" and arr["xyz"].shape[0] > 10000
    assert {"ring", "time_s", "intensity"} <= set(arr) and arr["time_s"].max() < 0.1
    info = next(fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/camera/camera_info")
    cam = convert.camera_info_to_model(info)
    run = simulate_drive(sc, image_scale=0.15, duration_s=0.3)
    assert np.allclose(cam.K, run.camera.K) and np.allclose(cam.D, run.camera.D)
    rot_deg, trans_mm = pose_errors(np.array(truth["T_camera_lidar"]), run.T_camera_lidar)
    assert rot_deg < 1e-8 and trans_mm < 1e-6
    img = next(fac.deserialize(r.raw, r.typename) for r in recs if r.topic == "/camera/image_raw")
    assert img.encoding == "bgr8" and img.header.frame_id == "camera_optical_frame"
    stamps_img = [r.stamp_ns for r in recs if r.topic == "/camera/image_raw"]
    assert abs(stamps_img[0] * 1e-9 - truth["images"][0]["stamp_s"]) < 1e-6
    with pytest.raises(BagError):
        write_street_bag(sc, tmp_path, image_scale=0.15, duration_s=0.1)
    bag2, _ = write_street_bag(sc, tmp_path, image_scale=0.15, duration_s=0.1, write_masks=True, overwrite=True)
    masks = [fac.deserialize(r.raw, r.typename) for r in read_bag(bag2, ["/camera/dynamic_mask"])]
    assert len(masks) == 1 and masks[0].encoding == "mono8"
    m = convert.image_to_array(masks[0])
    assert m.shape == (cam.height, cam.width) and set(np.unique(m)) <= {0, 255}


def test_family_varies_and_respects_speed_sets():
    slow = [sample_street_family(s, "slow") for s in range(12)]
    fast = [sample_street_family(s, "fast") for s in range(12)]
    assert all(5 <= sc.motion.speed_kmh - sc.motion.speed_amplitude_kmh and
               sc.motion.speed_kmh + sc.motion.speed_amplitude_kmh <= 30 for sc in slow)
    assert all(sc.motion.speed_kmh - sc.motion.speed_amplitude_kmh > 30 for sc in fast)
    assert all(sc.speed_set == "slow" for sc in slow) and all(sc.speed_set == "fast" for sc in fast)
    assert len({sc.lidar.preset for sc in slow + fast}) >= 3
    assert len({round(sc.camera.fx_px) for sc in slow}) == 12
    yaws = [sc.mount.camera_rpy_deg[2] for sc in slow + fast]
    assert max(abs(y) for y in yaws) > 60, "some cameras must look sideways/backwards"
    assert len({round(sc.timing.time_offset_s, 6) for sc in slow}) == 12
    assert sample_street_family(5, "slow") == sample_street_family(5, "slow")
    # the layout itself differs per seed too
    a = simulate_drive(sample_street_family(1), duration_s=0.1, image_scale=0.1)
    b = simulate_drive(sample_street_family(2), duration_s=0.1, image_scale=0.1)
    assert [lm["position"] for lm in a.landmarks] != [lm["position"] for lm in b.landmarks]
    assert not np.allclose(a.T_camera_lidar, b.T_camera_lidar)


def test_lidar_texture_and_paint_reflectance_from_streams_of_their_own():
    """The family draws the LiDAR's reflectance texture (0-0.4 per return) and the road paint's reflectance
    (0.25-0.6, worn to new) from a stream of their own. Rendered, the texture changes the intensities alone:
    the same seed with and without it gives the same points, and neighbouring road returns on a ring differ
    far more often by a quarter of the sweep's 95th intensity percentile (KITTI's road: 12 %)."""
    fam = [sample_street_family(s, sp).lidar for s in range(12) for sp in ("slow", "fast")]
    assert all(0.0 <= f.intensity_texture <= 0.4 and 0.25 <= f.paint_reflectivity <= 0.6 for f in fam)
    assert len({round(f.intensity_texture, 6) for f in fam}) == len(fam)
    assert max(f.intensity_texture for f in fam) > 0.3 and min(f.intensity_texture for f in fam) < 0.1
    sc = _scenario(10.0, preset="hdl64")
    runs = {}
    for tex in (0.0, 0.3):
        s2 = dataclasses.replace(sc, lidar=dataclasses.replace(sc.lidar, intensity_texture=tex))
        runs[tex] = simulate_drive(s2, duration_s=0.1, image_scale=0.1).sweeps[0].cloud
    a, b = runs[0.0], runs[0.3]
    assert set(a) == set(b) and "ring" in a
    for k in set(a) - {"intensity"}:
        assert np.array_equal(a[k], b[k]), k
    assert not np.allclose(a["intensity"], b["intensity"])

    def road_steps(c):
        o = np.lexsort((np.arctan2(c["y"], c["x"]), c["ring"]))
        z, inten, ring = c["z"][o], c["intensity"][o].astype(float), c["ring"][o]
        on = (ring[1:] == ring[:-1]) & (z[1:] < -1.5) & (z[:-1] < -1.5)
        return np.mean(np.abs(np.diff(inten))[on] > 0.25 * np.percentile(inten, 95))

    assert road_steps(a) < 0.02 and road_steps(b) > 0.05, (road_steps(a), road_steps(b))
    with pytest.raises(ConfigError, match="intensity_texture"):
        load_street_scenario({"lidar": {"intensity_texture": -0.1}})
    with pytest.raises(ConfigError, match="paint_reflectivity"):
        load_street_scenario({"lidar": {"paint_reflectivity": 1.5}})


def test_family_draws_only_lenses_the_renderer_can_render():
    # fast seed 410 drew k1 = -0.21 on an 82 deg field: the image corners had no ray ("too strong to render")
    from lidar_cam_calib.sim.street_world import _lens_unfolded
    folded = [(sp, s) for sp in ("slow", "fast") for s in range(400)
              if not _lens_unfolded(sample_street_family(s, sp).camera)]
    assert folded == []
    sc = sample_street_family(410, "fast")
    assert -0.2 < sc.camera.D[0] < 0.0
    run = simulate_drive(sc, duration_s=0.1, image_scale=0.25)
    assert len(run.images) >= 1 and run.images[0].image.std() > 5
    # the check itself refuses what folds
    cam = dataclasses.replace(sc.camera, D=[-0.35, 0.0, 0.0, 0.0, 0.0])
    assert not _lens_unfolded(cam)


def test_config_errors_and_shipped_scenarios():
    with pytest.raises(ConfigError, match="unknown"):
        load_street_scenario({"lidar": {"presett": "hdl64"}})
    with pytest.raises(ConfigError, match="preset"):
        load_street_scenario({"lidar": {"preset": "hdl128"}})
    with pytest.raises(ConfigError, match="duration"):
        load_street_scenario({"timing": {"duration_s": 0}})
    with pytest.raises(ConfigError, match="speed"):
        sample_street_family(0, "medium")
    for name in ("targetless_demo.yaml", "targetless_default.yaml"):
        path = os.path.join(ROOT, "config", "scenarios", name)
        sc = load_street_scenario(path)
        assert sc.name == name[:-5]
