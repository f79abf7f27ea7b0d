"""`lidar-cam-calib bench latency`: how late the lrf node's input callbacks
run while it extracts features and fits (live, at sensor rates).

Starts the real lrf node (trigger auto), publishes simulated LaserScan at
25 Hz and depth images at 30 Hz stamped with the wall clock, holds each pose
long enough for an automatic capture (and a fit from the second one on),
and reads the node's ``max_input_delay_ms``: the largest delay between a
message's stamp and the start of its callback (transport included).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

from .env import apply_loopback_env, loopback_env


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lidar-cam-calib bench latency", description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=5, help="poses to hold (a capture each)")
    ap.add_argument("--hold-s", type=float, default=2.0, help="seconds at each pose")
    ap.add_argument("--scan-hz", type=float, default=25.0)
    ap.add_argument("--depth-hz", type=float, default=30.0)
    ap.add_argument("--domain-id", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0))
    a = ap.parse_args(argv)

    from ..io.convert import array_to_image, camera_model_to_camera_info, make_laserscan
    from ..io.msgtypes import RclpyFactory
    from ..sim.lrf_world import simulate
    from ..sim.scenario import load_scenario

    here = os.path.dirname(os.path.abspath(__file__))
    sc = load_scenario(os.path.join(here, "..", "..", "config", "scenarios", "lrf_demo.yaml"))
    obs = simulate(sc, np.random.default_rng(3)).observations
    apply_loopback_env(a.domain_id)
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, LaserScan
    from std_msgs.msg import String

    out = tempfile.mkdtemp(prefix="lcc_latency_")
    ns = f"/lcc_latency_{os.getpid()}"
    cmd = [sys.executable, "-m", "lidar_cam_calib.ros.lrf_node", "--ros-args", "-r", f"__ns:={ns}",
           "-r", f"/scan:={ns}/scan", "-r", f"/camera/depth/image_raw:={ns}/depth",
           "-r", f"/camera/depth/camera_info:={ns}/info", "-r", f"/tf_static:={ns}/tf_static",
           "-p", "trigger:=auto", "-p", "input_reliability:=reliable", "-p", f"output_path:={out}/r.yaml"]
    proc = subprocess.Popen(cmd, env=loopback_env(a.domain_id), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rclpy.init()
    node = rclpy.create_node(f"lcc_latency_{os.getpid()}")
    rel = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ps = node.create_publisher(LaserScan, f"{ns}/scan", rel)
    pd = node.create_publisher(Image, f"{ns}/depth", rel)
    pi = node.create_publisher(CameraInfo, f"{ns}/info", rel)
    status: list = []
    node.create_subscription(String, f"{ns}/lrf_calib_node/status", lambda m: status.append(json.loads(m.data)),
                             latched)
    f = RclpyFactory()
    try:
        end = time.monotonic() + 30
        while not (ps.get_subscription_count() and pd.get_subscription_count() and pi.get_subscription_count()):
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > end or proc.poll() is not None:
                print("error: the lrf node did not start", file=sys.stderr)
                return 2
        time.sleep(0.5)
        t_next = {"scan": time.monotonic(), "depth": time.monotonic()}
        for k in range(a.poses):
            o = obs[k % len(obs)]
            d16 = np.where(np.isfinite(o.depth_m), np.round(o.depth_m * 1000.0), 0).astype(np.uint16)
            hold = time.monotonic() + a.hold_s
            while time.monotonic() < hold:
                now = time.monotonic()
                if now >= t_next["scan"]:
                    ps.publish(make_laserscan(o.scan_ranges_m, o.scan_angle_min_rad, o.scan_angle_increment_rad,
                                              o.scan_range_min_m, o.scan_range_max_m, f,
                                              f.make_header(time.time(), "laser")))
                    t_next["scan"] += 1.0 / a.scan_hz
                if now >= t_next["depth"]:
                    h = f.make_header(time.time(), "camera_depth_optical_frame")
                    pi.publish(camera_model_to_camera_info(o.camera, f, h))
                    pd.publish(array_to_image(d16, "16UC1", f, h))
                    t_next["depth"] += 1.0 / a.depth_hz
                rclpy.spin_once(node, timeout_sec=0.001)
        end = time.monotonic() + 5
        while time.monotonic() < end and not (status and status[-1].get("busy") == ""):
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(1.2)
        for _ in range(40):
            rclpy.spin_once(node, timeout_sec=0.05)
        st = status[-1] if status else {}
        print(f"lrf node, scan {a.scan_hz:.0f} Hz + depth {a.depth_hz:.0f} Hz, {a.poses} poses held "
              f"{a.hold_s:.1f} s: {st.get('inputs_processed', 0)} inputs, {st.get('observations', 0)} observations, "
              f"fitted: {bool(st.get('sigma_deg_mm'))}")
        p50, p99 = st.get("input_delay_ms_p50_p99", [float("nan")] * 2)
        print(f"input callback delay (stamp -> callback start, transport included): median {p50:.1f} ms, "
              f"99th percentile {p99:.1f} ms, max {st.get('max_input_delay_ms', float('nan')):.1f} ms")
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
