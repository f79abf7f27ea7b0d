"""A real calibration node as its own process, and a test client in this one
(real rclpy, real DDS on loopback). Shared by the live-node tests."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import yaml

from conftest import ROOT
from lidar_cam_calib.ros.env import loopback_env

LRF_PARAMS = os.path.join(ROOT, "config", "lrf.yaml")


def bag_subset(src: str, dst: str, keep) -> str:
    """Write the records of bag ``src`` for which ``keep(index, rec)`` holds to ``dst``."""
    from lidar_cam_calib.io.bag import BagWriter, read_bag

    with BagWriter(dst) as bw:
        for i, rec in enumerate(read_bag(src)):
            if keep(i, rec):
                bw.write(rec.topic, rec.typename, rec.stamp_ns, rec.raw)
    return dst


def run_cli(args, domain_id, timeout=600, env_extra=None):
    env = loopback_env(domain_id)
    env.update(env_extra or {})
    cmd = [sys.executable, "-m", "lidar_cam_calib.cli"] + list(args)
    if args and args[0] == "calibrate" and "--domain-id" not in args:
        cmd += ["--domain-id", str(domain_id)]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


class LiveNode:
    """The lrf node (``module``) with ``params``; publishers for its inputs,
    subscriptions to its outputs, service and parameter clients."""

    def __init__(self, tmp_path, domain_id, extra=None, module="lidar_cam_calib.ros.lrf_node",
                 name="lrf_calib_node", params_file=LRF_PARAMS, wait=True):
        import rclpy
        from geometry_msgs.msg import TransformStamped
        from rcl_interfaces.srv import DescribeParameters, SetParameters
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, LaserScan
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        self.rclpy = rclpy
        self.env = loopback_env(domain_id)
        os.environ.update(self.env)
        self.name = name
        params = {"trigger": "service", "input_reliability": "reliable",
                  "output_path": str(tmp_path / "calib.yaml")}
        params.update(extra or {})
        cmd = [sys.executable, "-m", module, "--ros-args"]
        if params_file:
            cmd += ["--params-file", params_file]
        for k, v in params.items():
            cmd += ["-p", f"{k}:={v}"]
        self.log_path = tmp_path / f"node_{time.monotonic_ns()}.log"
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(cmd, env=self.env, stdout=self.log, stderr=subprocess.STDOUT)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"test_client_{os.getpid()}", context=self.ctx)
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
        self.yaml = []
        self.node.create_subscription(String, f"/{name}/status", lambda m: self.status.append(yaml.safe_load(m.data)),
                                      latched)
        self.node.create_subscription(TransformStamped, f"/{name}/transform", self.transforms.append, latched)
        self.node.create_subscription(String, f"/{name}/result_yaml", lambda m: self.yaml.append(m.data), latched)
        try:
            from tf2_msgs.msg import TFMessage  # type: ignore

            self.node.create_subscription(TFMessage, "/tf_static", self.tf_static.append, latched)
            self.has_tf2 = True
        except ImportError:
            self.has_tf2 = False
        self.Trigger = Trigger
        self.cli_capture = self.node.create_client(Trigger, f"/{name}/capture")
        self.cli_recal = self.node.create_client(Trigger, f"/{name}/recalibrate")
        self.cli_setp = self.node.create_client(SetParameters, f"/{name}/set_parameters")
        self.cli_desc = self.node.create_client(DescribeParameters, f"/{name}/describe_parameters")
        if wait:
            self.spin_until(lambda: self.cli_capture.service_is_ready() and self.cli_recal.service_is_ready()
                            and all(p.get_subscription_count() > 0
                                    for p in (self.pub_scan, self.pub_depth, self.pub_info)), 30, "node start")
            self.spin_for(0.5)  # discovery completes on the node's side too

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

    def call(self, client, request=None, timeout=60):
        fut = client.call_async(request if request is not None else self.Trigger.Request())
        self.spin_until(fut.done, timeout, "service response")
        return fut.result()

    def capture(self):
        return self.call(self.cli_capture)

    def send(self, *msgs, settle=0.4):
        for m in msgs:
            {"LaserScan": self.pub_scan, "Image": self.pub_depth, "CameraInfo": self.pub_info}[
                type(m).__name__].publish(m)
        self.spin_for(settle)

    def reasons(self):
        return [s.get("last_reason") or "" for s in self.status]

    def set_param(self, name, value):
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters

        pv = ParameterValue()
        if isinstance(value, bool):
            pv.type, pv.bool_value = ParameterType.PARAMETER_BOOL, value
        elif isinstance(value, int):
            pv.type, pv.integer_value = ParameterType.PARAMETER_INTEGER, value
        elif isinstance(value, float):
            pv.type, pv.double_value = ParameterType.PARAMETER_DOUBLE, value
        elif isinstance(value, str):
            pv.type, pv.string_value = ParameterType.PARAMETER_STRING, value
        else:
            pv.type, pv.double_array_value = ParameterType.PARAMETER_DOUBLE_ARRAY, [float(v) for v in value]
        self.spin_until(self.cli_setp.service_is_ready, 10, "set_parameters service")
        req = SetParameters.Request(parameters=[Parameter(name=name, value=pv)])
        return self.call(self.cli_setp, req).results[0]

    def read_log(self):
        self.log.flush()
        with open(self.log_path) as f:
            return f.read()[-6000:]

    def close(self):
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.ctx)
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.log.close()


def lrf_messages(obs, stamp_s, factory, scan_ranges=None, depth=None, encoding="16UC1"):
    """LaserScan, depth Image and CameraInfo of one simulated observation."""
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
