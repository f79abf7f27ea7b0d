"""The real lrf node over real DDS on loopback: replay of the shipped bag, bad
input, services, latched outputs, /tf_static, and the result file's safety."""
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from conftest import ROOT  # noqa: E402
from lidar_cam_calib.core.geometry import inv_T, make_T, pose_errors, R_from_quat  # noqa: E402
from lidar_cam_calib.core.result import CalibrationResult  # noqa: E402
from lidar_cam_calib.ros.env import loopback_env  # noqa: E402

ERR_RE = re.compile(r"error vs truth: rotation ([0-9.]+) deg, translation ([0-9.]+) mm")


def run_cli(args, domain_id, timeout=600):
    cmd = [sys.executable, "-m", "lidar_cam_calib.cli"] + args + ["--domain-id", str(domain_id)]
    return subprocess.run(cmd, cwd=ROOT, env=loopback_env(domain_id), capture_output=True, text=True,
                          timeout=timeout)


def truth_of(bag):
    with open(os.path.join(bag, "truth.yaml")) as f:
        return np.array(yaml.safe_load(f)["T_camera_laser"], dtype=float)


# --------------------------------------------------------------------------- replay
@pytest.fixture(scope="module")
def replay_once(tmp_path_factory):
    """One replay of the demo bag through the node (shared by several tests)."""
    from conftest import DEMO_BAG

    out = tmp_path_factory.mktemp("replay")
    res = out / "result.yaml"
    ov = out / "overlay.png"
    r = run_cli(["calibrate", "lrf", DEMO_BAG, "--params", os.path.join(ROOT, "config", "lrf.yaml"),
                 "--truth", os.path.join(DEMO_BAG, "truth.yaml"), "--output", str(res),
                 "--overlay", str(ov)], 199)
    return r, res, ov


def test_replay_recovers_truth_and_writes_files(replay_once):
    r, res, ov = replay_once
    assert r.returncode == 0, r.stdout + r.stderr
    m = ERR_RE.search(r.stdout)
    assert m, r.stdout
    rot_deg, trans_mm = float(m.group(1)), float(m.group(2))
    # 6 observations with the paper's sensor noise: the 20-observation goal is
    # 0.15 deg / 2 mm; with 6 we ask for a third of the 2-observation goal.
    assert rot_deg < 0.35 and trans_mm < 5.0, r.stdout
    result = CalibrationResult.load(str(res))
    assert result.method == "lrf" and result.observations_used >= 5
    er, et = pose_errors(result.T_child_parent, truth_of(os.path.join(ROOT, "bags", "lrf_demo")))
    assert er == pytest.approx(rot_deg, abs=2e-3) and et == pytest.approx(trans_mm, abs=0.02)
    rs, ts = result.sigma()
    # the error is within a few sigma: the uncertainty means something
    assert 0 < rs and 0 < ts and er < 4 * rs + 0.02 and et < 4 * ts + 0.5
    assert ov.is_file() and ov.stat().st_size > 1000


def test_replay_is_deterministic(replay_once, tmp_path):
    r1, res1, _ = replay_once
    from conftest import DEMO_BAG

    res2 = tmp_path / "again.yaml"
    r2 = run_cli(["calibrate", "lrf", DEMO_BAG, "--params", os.path.join(ROOT, "config", "lrf.yaml"),
                  "--output", str(res2)], 198)
    assert r2.returncode == 0, r2.stderr
    a = CalibrationResult.load(str(res1))
    b = CalibrationResult.load(str(res2))
    np.testing.assert_array_equal(a.T_child_parent, b.T_child_parent)
    assert a.observations_used == b.observations_used
    sent1 = re.search(r"replayed (\d+) messages", r1.stdout).group(1)
    sent2 = re.search(r"replayed (\d+) messages", r2.stdout).group(1)
    assert sent1 == sent2


def test_better_calibration_on_disk_is_kept(demo_bag, tmp_path, domain_id):
    out = tmp_path / "calib.yaml"
    T = make_T(np.eye(3), [1.0, 2.0, 3.0])
    tiny = CalibrationResult("lrf", "laser", "camera_depth_optical_frame", T, np.eye(6) * 1e-14,
                             observations_used=99)
    out.write_text(tiny.to_yaml())
    before = out.read_text()
    r = run_cli(["calibrate", "lrf", demo_bag, "--params", os.path.join(ROOT, "config", "lrf.yaml"),
                 "--output", str(out)], domain_id)
    assert r.returncode == 0, r.stderr
    assert out.read_text() == before
    assert not (tmp_path / "calib.yaml.bak").exists()
    assert "kept" in r.stdout and "better calibration" in r.stdout


def test_unwritable_output_is_reported_not_fatal(demo_bag, tmp_path, domain_id):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    r = run_cli(["calibrate", "lrf", demo_bag, "--params", os.path.join(ROOT, "config", "lrf.yaml"),
                 "--output", str(blocker / "calib.yaml")], domain_id)
    assert r.returncode == 5, r.stdout + r.stderr
    assert "NOT saved" in r.stderr and "cannot write result" in r.stderr
    assert "Traceback" not in r.stderr
    # the calibration itself still came through on the topic
    assert "T_camera_depth_optical_frame_laser" in r.stdout


def test_truncated_bag_is_a_clear_error(demo_bag, tmp_path, domain_id):
    bag = tmp_path / "cut"
    shutil.copytree(demo_bag, bag)
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    r = run_cli(["calibrate", "lrf", str(bag), "--params", os.path.join(ROOT, "config", "lrf.yaml"),
                 "--output", str(tmp_path / "o.yaml")], domain_id)
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    assert re.search(r"truncated|corrupt|incomplete", r.stderr, re.I), r.stderr


def test_missing_bag_is_a_clear_error(tmp_path, domain_id):
    r = run_cli(["calibrate", "lrf", str(tmp_path / "nope")], domain_id)
    assert r.returncode == 2 and "bag not found" in r.stderr and "Traceback" not in r.stderr


# --------------------------------------------------------------------------- live node
class LiveNode:
    """The lrf node as its own process + a test client node in this process."""

    def __init__(self, tmp_path, domain_id, extra=None):
        self.env = loopback_env(domain_id)
        os.environ.update(self.env)
        params = {"trigger": "service", "input_reliability": "reliable",
                  "output_path": str(tmp_path / "calib.yaml")}
        params.update(extra or {})
        cmd = [sys.executable, "-m", "lidar_cam_calib.ros.lrf_node", "--ros-args",
               "--params-file", os.path.join(ROOT, "config", "lrf.yaml")]
        for k, v in params.items():
            cmd += ["-p", f"{k}:={v}"]
        self.log = open(tmp_path / "node.log", "w")
        self.proc = subprocess.Popen(cmd, env=self.env, stdout=self.log, stderr=subprocess.STDOUT)
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from geometry_msgs.msg import TransformStamped
        from sensor_msgs.msg import CameraInfo, Image, LaserScan
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node("lrf_test_client", context=self.ctx)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        rel = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_scan = self.node.create_publisher(LaserScan, "/scan", rel)
        self.pub_depth = self.node.create_publisher(Image, "/camera/depth/image_raw", rel)
        self.pub_info = self.node.create_publisher(CameraInfo, "/camera/depth/camera_info", rel)
        self.status = []
        self.transforms = []
        self.tf_static = []
        self.node.create_subscription(String, "/lrf_calib_node/status",
                                      lambda m: self.status.append(yaml.safe_load(m.data)), 50)
        self.node.create_subscription(TransformStamped, "/lrf_calib_node/transform",
                                      self.transforms.append, latched)
        try:
            from tf2_msgs.msg import TFMessage  # type: ignore

            tfq = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.node.create_subscription(TFMessage, "/tf_static", self.tf_static.append, tfq)
            self.has_tf2 = True
        except ImportError:
            self.has_tf2 = False
        self.cli_capture = self.node.create_client(Trigger, "/lrf_calib_node/capture")
        self.cli_recal = self.node.create_client(Trigger, "/lrf_calib_node/recalibrate")
        self.Trigger = Trigger
        self.spin_until(lambda: self.cli_capture.service_is_ready() and self.cli_recal.service_is_ready()
                        and all(p.get_subscription_count() > 0
                                for p in (self.pub_scan, self.pub_depth, self.pub_info)), 30, "node start")

    def spin_until(self, pred, timeout, what):
        end = time.monotonic() + timeout
        while not pred():
            assert self.proc.poll() is None, f"node died while waiting for {what}: {self.read_log()}"
            assert time.monotonic() < end, f"timeout waiting for {what}: {self.read_log()}"
            self.ex.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.02)

    def call(self, client):
        fut = client.call_async(self.Trigger.Request())
        self.spin_until(fut.done, 30, "service response")
        return fut.result()

    def publish_and_capture(self, scan, img):
        """Publish a scan + depth pair, let the node take them, call ~/capture."""
        self.pub_scan.publish(scan)
        self.pub_depth.publish(img)
        self.spin_for(0.5)
        return self.call(self.cli_capture)

    def read_log(self):
        self.log.flush()
        with open(self.log.name) as f:
            return f.read()[-3000:]

    def close(self):
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.log.close()


def messages_for(obs, stamp_s, factory, scan_ranges=None, depth=None, encoding="16UC1"):
    from lidar_cam_calib.io.convert import array_to_image, camera_model_to_camera_info, make_laserscan

    h_scan = factory.make_header(stamp_s, "laser")
    h_cam = factory.make_header(stamp_s + 0.004, "camera_depth_optical_frame")
    ranges = obs.scan_ranges_m if scan_ranges is None else scan_ranges
    scan = make_laserscan(ranges, obs.scan_angle_min_rad, obs.scan_angle_increment_rad,
                          obs.scan_range_min_m, obs.scan_range_max_m, factory, h_scan)
    d = obs.depth_m if depth is None else depth
    if encoding == "16UC1":
        d16 = np.where(np.isfinite(d), np.round(d * 1000.0), 0).astype(np.uint16)
        img = array_to_image(d16, "16UC1", factory, h_cam)
    else:
        img = array_to_image(d, encoding, factory, h_cam)
    info = camera_model_to_camera_info(obs.camera, factory, h_cam)
    return scan, img, info


@pytest.fixture
def sim_run():
    from lidar_cam_calib.sim.lrf_world import simulate
    from lidar_cam_calib.sim.scenario import load_scenario

    sc = load_scenario(os.path.join(ROOT, "config", "scenarios", "lrf_demo.yaml"))
    return simulate(sc, np.random.default_rng(11))


def test_live_node_bad_input_services_and_outputs(tmp_path, domain_id, sim_run):
    from lidar_cam_calib.io.msgtypes import RclpyFactory

    f = RclpyFactory()
    obs = sim_run.observations
    live = LiveNode(tmp_path, domain_id)
    try:
        # 1. nothing received yet
        r = live.call(live.cli_capture)
        assert not r.success and "CameraInfo" in r.message

        # 2. an uncalibrated CameraInfo (K = 0) is refused with a reason, node stays up
        scan, img, info = messages_for(obs[0], 10.0, f)
        info.k = [0.0] * 9
        live.pub_info.publish(info)
        live.spin_for(0.5)
        r = live.call(live.cli_capture)
        assert not r.success and "CameraInfo" in r.message
        assert any("uncalibrated" in (s.get("last_reason") or "") for s in live.status), \
            [s.get("last_reason") for s in live.status]

        # 3. good CameraInfo, but a scan of inf/NaN/zero ranges and an all-invalid depth image
        scan, img, info = messages_for(obs[0], 11.0, f)
        live.pub_info.publish(info)
        bad = np.full_like(obs[0].scan_ranges_m, np.inf)
        bad[::3] = np.nan
        bad[1::3] = 0.0
        scan, img, _ = messages_for(obs[0], 11.0, f, scan_ranges=bad, depth=np.zeros_like(obs[0].depth_m))
        r = live.publish_and_capture(scan, img)
        assert not r.success and re.search(r"scan|depth", r.message), r.message

        # 4. wrong depth encoding
        scan, img, _ = messages_for(obs[0], 12.0, f)
        img.encoding = "rgb8"
        live.pub_scan.publish(scan)
        live.pub_depth.publish(img)
        live.spin_for(0.5)
        assert any("16UC1" in (s.get("last_reason") or "") for s in live.status), \
            [s.get("last_reason") for s in live.status]

        # 5. the board only partly seen: cut the scan to one side of the board
        part = obs[0].scan_ranges_m.copy()
        ang = obs[0].scan_angle_min_rad + obs[0].scan_angle_increment_rad * np.arange(part.size)
        part[ang > np.median(ang[np.isfinite(part) & (np.abs(ang) < 0.6)])] = np.inf
        scan, img, _ = messages_for(obs[0], 13.0, f, scan_ranges=part)
        r = live.publish_and_capture(scan, img)
        assert not r.success and "scan" in r.message, r.message

        # 6. a good observation is accepted; the same pose again is refused
        scan, img, _ = messages_for(obs[0], 14.0, f)
        r = live.publish_and_capture(scan, img)
        assert r.success, r.message
        scan, img, _ = messages_for(obs[0], 15.0, f)
        r = live.publish_and_capture(scan, img)
        assert not r.success and "similar" in r.message, r.message

        # 7. stamps out of order are dropped with a reason
        scan, img, _ = messages_for(obs[1], 14.5, f)
        live.pub_scan.publish(scan)
        live.spin_for(0.5)
        assert any("out of order" in (s.get("last_reason") or "") for s in live.status), live.status[-3:]

        # 8. second and third poses: the node fits and publishes
        for i, t in ((1, 20.0), (2, 25.0)):
            scan, img, _ = messages_for(obs[i], t, f)
            r = live.publish_and_capture(scan, img)
            assert r.success, r.message
        assert "published" in r.message
        live.spin_until(lambda: len(live.transforms) > 0, 10, "~/transform")
        ts = live.transforms[-1]
        assert ts.header.frame_id == "laser" and ts.child_frame_id == "camera_depth_optical_frame"
        tr = ts.transform.translation
        q = ts.transform.rotation
        T_parent_child = make_T(R_from_quat([q.x, q.y, q.z, q.w]), [tr.x, tr.y, tr.z])
        er, et = pose_errors(inv_T(T_parent_child), sim_run.truth.T_camera_laser)
        assert er < 1.0 and et < 15.0, (er, et)
        assert os.path.isfile(tmp_path / "calib.yaml")
        st = live.status[-1]
        assert st["observations"] == 3

        # 9. /tf_static carries the same transform (tf2 meaning: child pose in parent)
        if live.has_tf2:
            live.spin_until(lambda: len(live.tf_static) > 0, 10, "/tf_static")
            tfs = live.tf_static[-1].transforms
            assert len(tfs) == 1 and tfs[0].header.frame_id == "laser"
            assert tfs[0].child_frame_id == "camera_depth_optical_frame"
            assert tfs[0].transform.translation.x == pytest.approx(tr.x)
            assert tfs[0].transform.rotation.w == pytest.approx(q.w)

        # 10. recalibrate drops the observations
        r = live.call(live.cli_recal)
        assert r.success and "dropped 3" in r.message
        live.spin_for(0.3)
        assert live.status[-1]["observations"] == 0
        assert live.proc.poll() is None
    finally:
        live.close()


def test_tf_static_path_is_exercised_in_ci():
    """`make test` builds a TFMessage type so the /tf_static branch is tested;
    outside it the test above skips only that part."""
    if os.environ.get("CI"):
        import importlib

        assert importlib.util.find_spec("tf2_msgs") is not None, "make test must build tf2_msgs"
