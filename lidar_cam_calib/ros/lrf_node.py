"""`lrf_calib_node`: 2D laser scanner + depth camera (paper 003), thin ROS shell.

Subscribes LaserScan, a depth Image (16UC1 mm or 32FC1 m) and its CameraInfo,
pairs scan and depth with the approximate-time synchroniser, and takes one
observation per ``~/capture`` call (the AGV has stopped) and/or by itself when
the scan has been static for ``static_time_s`` (``trigger`` parameter). Every
pair that arrives while the AGV stands still is fed to the calibrator's stop
accumulator (depth averaged per pixel, scans stacked), so one observation
comes from all frames of a stop and one bad frame does not lose it; a refused
input or motion starts the stop again. The base fits, adopts and publishes;
all of the method lives in :mod:`lidar_cam_calib.lrf`.
"""
from __future__ import annotations

import sys
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, LaserScan

from ..io.convert import camera_info_to_model, depth_image_to_m, stamp_to_s, validate_laserscan
from ..io.sync import ApproxTimeSync
from ..lrf.calibrator import LrfCalibrator, LrfConfig, StaticDetector
from ..lrf.frame import LrfFrame
from ..lrf.overlay import render_overlay
from .node_base import CalibNodeBase, run_node

TRIGGERS = ("service", "auto", "both")


class LrfCalibNode(CalibNodeBase):
    method_name = "lrf"
    config_cls = LrfConfig

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("lrf_calib_node", **kwargs)
        self.static = StaticDetector(self.param("static_time_s"), self.param("static_range_tol_m"))
        self.sync = ApproxTimeSync(["scan", "depth"], self.param("sync_slop_s"))
        self.camera = None
        self._camera_info_key = None
        self.latest_pair: tuple[Any, Any] | None = None
        self._stop_frames = 0                     # frames fed to the current stop
        self._first_pairs: list = []              # pairs since the static detector's reference scan
        self._stop_last: LrfFrame | None = None   # the newest of them (for the overlay)
        self.add_input("scan", LaserScan, "scan_topic", "/scan", "sensor_msgs/LaserScan input.", self._on_scan)
        self.add_input("depth", Image, "depth_topic", "/camera/depth/image_raw",
                       "Depth image input (16UC1 mm or 32FC1 m).", self._on_depth)
        self.add_input("camera_info", CameraInfo, "camera_info_topic", "/camera/depth/camera_info",
                       "CameraInfo of the depth image.", self._on_camera_info)
        self.get_logger().info(
            f"lrf calibration: scan={self.param('scan_topic')} depth={self.param('depth_topic')} "
            f"info={self.param('camera_info_topic')} trigger={self.param('trigger')}")
        self.announce_ready()

    def declare_node_params(self) -> None:
        self.declare_param("trigger", "both", "When to take an observation: service (~/capture only), auto (scene "
                           "static for static_time_s) or both.", choices=TRIGGERS)
        self.declare_param("static_time_s", 1.0, "The scan must be unchanged this long before an automatic capture.",
                           range=(0.1, 60.0))
        self.declare_param("static_range_tol_m", 0.005, "Smallest range change that counts as motion: the "
                           "median |range change| against the stop's first scan, smoothed over 15 beams. The "
                           "threshold rises above it with the laser noise measured from the scans.",
                           range=(0.001, 1.0))
        self.declare_param("sync_slop_s", 0.05, "Largest stamp difference between a scan and a depth image that "
                           "are paired.", range=(0.001, 1.0))

    def make_calibrator(self, cfg: LrfConfig) -> LrfCalibrator:
        return LrfCalibrator(cfg)

    def on_reset(self) -> None:
        self.sync.reset()
        self.latest_pair = None
        self._stop_frames = 0
        self._first_pairs = []
        self.static = StaticDetector(self.param("static_time_s"), self.param("static_range_tol_m"))

    # -- inputs (input callback group, in arrival order) -----------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        key = (msg.width, msg.height, tuple(msg.k), tuple(msg.d), msg.distortion_model)
        if key != self._camera_info_key:
            self.camera = camera_info_to_model(msg)  # a clear error on an uncalibrated K
            self._camera_info_key = key

    def _on_scan(self, msg: LaserScan) -> None:
        t = stamp_to_s(msg.header.stamp)
        ranges = validate_laserscan(msg)
        self.check_stamp("scan", t, ranges)
        fired = self.static.update(t, ranges)
        if not self.static.still:
            self._stop_frames = 0   # the AGV moves: the next stop starts afresh
            since = self.static.since_s
            self._first_pairs = [p for p in self._first_pairs if self._pair_t0(p) >= since]
        elif self._first_pairs:
            # the stop began at the reference scan: the pairs that arrived since then are of it too
            first, self._first_pairs = self._first_pairs, []
            for pair in first:
                self._on_pair(pair)
        for pair in self.sync.push("scan", t, msg):
            self._on_pair(pair)
        if self.param("trigger") in ("auto", "both") and fired:
            ok, why = self._capture(auto=True, fired_at_s=t)
            if not ok:
                self.reject(why)

    def _on_depth(self, msg: Image) -> None:
        t = stamp_to_s(msg.header.stamp)
        depth_image_to_m(msg)  # a wrong encoding or size is refused at once, with its reason
        self.check_stamp("depth", t, msg.data)
        for pair in self.sync.push("depth", t, msg):
            self._on_pair(pair)

    def _on_pair(self, pair: tuple) -> None:
        """A synchronised scan + depth pair: the latest one, and one more frame
        of the current stop while the scan is static."""
        self.latest_pair = pair
        if self.camera is None:
            return
        if not self.static.still:
            if self.static.since_s is not None and self._pair_t0(pair) >= self.static.since_s:
                self._first_pairs = (self._first_pairs + [pair])[-8:]
            return
        if self.fresh_enough(*(stamp_to_s(m.header.stamp) for m in pair)):
            return
        frame = self._frame(pair)
        gen = self._generation
        self._stop_frames += 1
        replay = self.pub_ack is not None
        if replay or self._jobs.qsize() < 4:   # live: while a fit runs, extra frames of the stop are skipped
            self.submit(lambda: self._feed(frame, gen), wait=False)

    @staticmethod
    def _pair_t0(pair: tuple) -> float:
        return min(stamp_to_s(m.header.stamp) for m in pair)

    def _feed(self, frame: LrfFrame, gen: int) -> tuple[bool, str]:
        if gen != self._generation:
            return False, "frame from before ~/recalibrate"
        self._busy = "averaging a stop"
        v = self.calib.feed(frame)
        self._stop_last = frame
        return v.accepted, v.reason

    def refuse_input(self, stream: str, msg: Any, reason: str) -> None:
        super().refuse_input(stream, msg, reason)
        if stream in ("scan", "depth"):
            self._first_pairs = []
        if stream in ("scan", "depth") and self._stop_frames:
            # a capture must not use frames older than a refused input: the stop starts again
            self._stop_frames = 0
            gen = self._generation
            self.submit(lambda: self._drop_stop(gen), wait=False)

    def _drop_stop(self, gen: int) -> tuple[bool, str]:
        if gen == self._generation:
            self.calib.drop_stop()
        return True, "stop dropped"

    # -- observations -------------------------------------------------------------
    def on_capture(self) -> tuple[bool, str]:
        return self._capture(auto=False)

    def _capture(self, auto: bool, fired_at_s: float | None = None) -> tuple[bool, str]:
        if self.camera is None:
            return False, f"no CameraInfo received yet on {self.param('camera_info_topic')}"
        with self._lock:
            pair = self.latest_pair
        if pair is None:
            return False, (f"no synchronised pair yet (scan on {self.param('scan_topic')}, depth on "
                           f"{self.param('depth_topic')} within {self.param('sync_slop_s')} s)")
        scan, depth_msg = pair
        scan_t, depth_t = stamp_to_s(scan.header.stamp), stamp_to_s(depth_msg.header.stamp)
        stale = self.fresh_enough(scan_t, depth_t)
        if stale:
            return False, stale
        if auto and fired_at_s is not None and scan_t < fired_at_s - self.param("static_time_s"):
            return False, "static scene but no depth image paired during the stop: observation skipped"
        with self._lock:
            if self.latest_pair is pair:
                self.latest_pair = None  # a pair is never used for a second observation
        gen = self._generation
        if self._stop_frames:
            # every frame of this stop, averaged (the latest pair is among them)
            self._stop_frames = 0
            return self.submit(lambda: self.process(self.calib.end_stop, self._stop_last, scan_t, auto, gen),
                               wait=not auto)
        frame = self._frame(pair)
        # A service call waits for the answer; the automatic capture from the
        # scan callback does not (the worker fits while inputs keep flowing),
        # except in lock-step replay, where the ack waits for the work anyway.
        return self.submit_frame(frame, max(scan_t, depth_t), auto, wait=not auto)

    def _frame(self, pair: tuple) -> LrfFrame:
        scan, depth_msg = pair
        return LrfFrame(
            stamp_s=stamp_to_s(scan.header.stamp),
            scan_ranges_m=np.asarray(scan.ranges, dtype=np.float32),
            scan_angle_min_rad=float(scan.angle_min),
            scan_angle_increment_rad=float(scan.angle_increment),
            scan_range_min_m=float(scan.range_min),
            scan_range_max_m=float(scan.range_max),
            depth_m=depth_image_to_m(depth_msg),
            camera=self.camera,
            laser_frame=scan.header.frame_id or "laser",
            camera_frame=depth_msg.header.frame_id or "camera_depth_optical_frame",
        )

    def render_overlays(self, frame: LrfFrame, cal) -> dict:
        return {"": render_overlay(frame, cal.results[""].T_child_parent)}

    def method_status(self) -> dict:
        return {"camera_info": self.camera is not None, "trigger": self.param("trigger")}


def main(args: list[str] | None = None) -> int:
    return run_node(LrfCalibNode, args if args is not None else sys.argv)


if __name__ == "__main__":
    sys.exit(main())
