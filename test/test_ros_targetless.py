"""The target-less method through its real node: a simulated drive of the scenario family
(slow set) is written as a bag, replayed over DDS on loopback, and the node publishes a
calibration that passed its quality gates, near the truth and within its own sigma.

The clock offset is given to the node (as after a clock synchronisation): from one window it
is indistinguishable from a translation along the drive. Family seed 2 is one the method was
developed on; the figures on held-out seeds are in the README."""

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")

from live_node import run_cli

from lidar_cam_calib.core.geometry import pose_errors
from lidar_cam_calib.core.result import CalibrationResult


def test_simulated_drive_through_the_node(tmp_path):
    from lidar_cam_calib.sim.street_bag import write_street_bag
    from lidar_cam_calib.sim.street_world import sample_street_family
    from lidar_cam_calib.targetless.calibrator import TargetlessConfig

    sc = sample_street_family(2, "slow")
    # one window of n_frames images at >= 10 px motion, and a second of margin
    duration = max(2.5, (TargetlessConfig().n_frames + 2) / sc.camera.rate_hz + 0.3) + 1.0
    bag, truth_path = write_street_bag(sc, str(tmp_path), image_scale=0.5, duration_s=duration)
    truth = yaml.safe_load(open(truth_path))
    # the bag holds one window: published alone (fuse_min_windows 1; by default two windows must agree, which
    # test_targetless_calibrator checks without the node)
    params = {"lidar_topic": "/lidar/points", "time_offset_s": float(truth["time_offset_s"]),
              "time_offset_sigma_s": 0.002, "fuse_min_windows": 1}
    pf = tmp_path / "params.yaml"
    pf.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    out = tmp_path / "r.yaml"
    r = run_cli(["calibrate", "targetless", str(bag), "--params", str(pf), "--truth", str(truth_path),
                 "--output", str(out)], 86)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Hausdorff distance of the registered clouds" in r.stdout
    res = CalibrationResult.load(str(out))
    rot, tr = pose_errors(res.T_child_parent, np.array(truth["T_camera_lidar"], float))
    sr, st = res.sigma()
    # within the goals (0.2 deg, 3 cm). Measured at stop 20: 0.091 deg / 10.9 mm, reported 1-sigma
    # 0.105 deg / 18.0 mm (with the translation-only edge step of stop 12: 0.16 deg / 42 mm)
    assert rot < 0.2 and tr < 30.0, r.stdout
    assert rot < 3 * sr * np.sqrt(3) and tr < 3 * st * np.sqrt(3), (rot, tr, sr, st)
    assert res.metrics["hausdorff_m"] <= 0.05 and res.metrics["sfm_reprojection_px"] <= 2.0, res.metrics
