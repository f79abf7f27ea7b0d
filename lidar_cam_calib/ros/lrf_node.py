"""`lrf_calib_node`: 2D laser scanner + depth camera (paper 003), thin ROS shell.

Subscribes LaserScan, a depth Image (16UC1 mm or 32FC1 m) and its CameraInfo,
pairs scan and depth with the approximate-time synchroniser, and takes one
observation per ``~/capture`` call (the AGV has stopped) and/or by itself when
the scan has been static for ``static_time_s`` (``trigger`` parameter). From
two observations on it fits after each new one and publishes the result.
All the method lives in :mod:`lidar_cam_calib.lrf`; this file only converts,
feeds and publishes.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, LaserScan

from ..io.convert import camera_info_to_model, depth_image_to_m
from ..io.sync import ApproxTimeSync
from ..lrf.calibrator import LrfCalibrator, LrfConfig, StaticDetector
from ..lrf.features import BoardModel
from ..lrf.frame import LrfFrame
from ..lrf.overlay import render_overlay
from rcl_interfaces.msg import ParameterDescriptor

from .node_base import CalibNodeBase, run_node, stamp_to_s

TRIGGERS = ("service", "auto", "both")


class LrfCalibNode(CalibNodeBase):
    method_name = "lrf"

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("lrf_calib_node", **kwargs)
        self.declare_str("scan_topic", "/scan", "sensor_msgs/LaserScan input.")
        self.declare_str("depth_topic", "/camera/depth/image_raw", "Depth image input (16UC1 mm or 32FC1 m).")
        self.declare_str("camera_info_topic", "/camera/depth/camera_info", "CameraInfo of the depth image.")
        self.declare_str("trigger", "both",
                         "When to take an observation: 'service' (~/capture only), 'auto' (scene static for "
                         "static_time_s) or 'both'.")
        self.declare_float("static_time_s", 1.0, "Scan must be unchanged this long before an automatic capture.", 0.1, 60.0)
        self.declare_float("static_range_tol_m", 0.03, "Median |range change| below which the scan counts as static.",
                           0.001, 1.0)
        self.declare_float("sync_slop_s", 0.05, "Max stamp difference between a scan and a depth image to pair them.",
                           0.001, 1.0)
        # Every scalar field of LrfConfig is a parameter of the same name; the
        # board geometry is board_width_m, board_height_m, board_a_xy_m, board_c_xyz_m.
        self._cfg_names = []
        for f in dataclasses.fields(LrfConfig):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            if isinstance(default, (bool, int, float, str)):
                self._declare_typed(f.name, default, f.metadata.get("help", f"LrfConfig.{f.name}"))
                self._cfg_names.append(f.name)
        for f in dataclasses.fields(BoardModel):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            self._declare(f"board_{f.name}", [float(v) for v in default] if isinstance(default, tuple)
                          else float(default), ParameterDescriptor(description=f"folded board: {f.name} "
                                                                   "(board frame: x right, y up, z out, m)"))

        trig = self.param("trigger")
        if trig not in TRIGGERS:
            raise ValueError(f"trigger must be one of {TRIGGERS}, got {trig!r}")
        if self.param("solver") not in ("ours", "paper"):
            raise ValueError("solver must be 'ours' or 'paper'")
        self.calib = LrfCalibrator(self._config())
        self.static = StaticDetector(self.param("static_time_s"), self.param("static_range_tol_m"))
        self.sync = ApproxTimeSync(["scan", "depth"], self.param("sync_slop_s"))
        self.camera = None
        self._camera_info_key = None
        self.latest_pair: tuple[LaserScan, Image] | None = None
        self._last_scan_stamp = -1.0

        qos = self.sensor_qos()
        self.create_subscription(LaserScan, self.param("scan_topic"), self.guarded("scan", self._on_scan), qos)
        self.create_subscription(Image, self.param("depth_topic"), self.guarded("depth", self._on_depth), qos)
        self.create_subscription(CameraInfo, self.param("camera_info_topic"),
                                 self.guarded("camera_info", self._on_camera_info), qos)
        self.get_logger().info(
            f"lrf calibration: scan={self.param('scan_topic')} depth={self.param('depth_topic')} "
            f"info={self.param('camera_info_topic')} trigger={trig}")
        self.announce_ready()

    def _declare_typed(self, name: str, default, desc: str) -> None:
        if isinstance(default, bool):
            self.declare_bool(name, default, desc)
        elif isinstance(default, int):
            self.declare_int(name, default, desc, 0, 2**31 - 1)
        elif isinstance(default, float):
            self.declare_float(name, default, desc, 0.0, 1e6)
        else:
            self.declare_str(name, default, desc)

    def _config(self) -> LrfConfig:
        board = BoardModel(**{f.name: (tuple(self.param(f"board_{f.name}"))
                                       if isinstance(self.param(f"board_{f.name}"), (list, tuple))
                                       else self.param(f"board_{f.name}"))
                              for f in dataclasses.fields(BoardModel)})
        return LrfConfig(board=board, **{n: self.param(n) for n in self._cfg_names})

    # -- inputs ----------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        key = (msg.width, msg.height, tuple(msg.k), tuple(msg.d), msg.distortion_model)
        if key != self._camera_info_key:
            self.camera = camera_info_to_model(msg)  # raises a clear ValueError on bad K
            self._camera_info_key = key

    def _on_scan(self, msg: LaserScan) -> None:
        t = stamp_to_s(msg.header.stamp)
        if t < self._last_scan_stamp:
            raise ValueError(f"scan stamps out of order ({t:.3f} s after {self._last_scan_stamp:.3f} s): dropped")
        self._last_scan_stamp = t
        for pair in self.sync.push("scan", t, msg):
            self.latest_pair = pair
        if self.param("trigger") in ("auto", "both"):
            if self.static.update(t, np.asarray(msg.ranges, dtype=np.float32)):
                self._capture(auto=True, fired_at_s=t)

    def _on_depth(self, msg: Image) -> None:
        depth_image_to_m(msg)  # reject a wrong encoding or size at once, with its reason
        for pair in self.sync.push("depth", stamp_to_s(msg.header.stamp), msg):
            self.latest_pair = pair

    # -- observations ---------------------------------------------------------
    def on_capture(self) -> tuple[bool, str]:
        return self._capture(auto=False)

    def on_recalibrate(self) -> tuple[bool, str]:
        n = len(self.calib.observations)
        self.calib.reset()
        self.latest_pair = None
        self.last_reason = ""
        return True, f"dropped {n} observations; collecting again"

    def _capture(self, auto: bool, fired_at_s: float | None = None) -> tuple[bool, str]:
        if self.camera is None:
            msg = f"no CameraInfo received yet on {self.param('camera_info_topic')}"
            self.reject(msg)
            return False, msg
        if self.latest_pair is None:
            msg = (f"no synchronised pair yet (scan on {self.param('scan_topic')}, depth on "
                   f"{self.param('depth_topic')} within {self.param('sync_slop_s')} s)")
            self.reject(msg)
            return False, msg
        scan, depth_msg = self.latest_pair
        scan_t = stamp_to_s(scan.header.stamp)
        if auto and fired_at_s is not None and scan_t < fired_at_s - self.param("static_time_s"):
            msg = "static scene but no depth image paired during the stop: observation skipped"
            self.reject(msg)
            return False, msg
        frame = LrfFrame(
            stamp_s=scan_t,
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
        verdict = self.calib.add(frame)
        if not verdict.accepted:
            self.reject(verdict.reason)
            return False, verdict.reason
        self.latest_pair = None  # never reuse a pair for a second observation
        self.last_reason = ""
        n = len(self.calib.observations)
        note = f"observation {n} accepted" + (" (automatic)" if auto else "")
        if self.calib.ready():
            note += "; " + self._fit_and_publish(frame, scan.header.stamp)
        self.get_logger().info(note)
        self.publish_status()
        return True, note

    def _fit_and_publish(self, frame: LrfFrame, stamp) -> str:
        try:
            result = self.calib.fit(solver=self.param("solver"))
        except Exception as e:  # noqa: BLE001 - degenerate poses etc.
            self.last_reason = f"fit failed: {e}"
            return self.last_reason
        result.input_topics = {"scan": self.param("scan_topic"), "depth": self.param("depth_topic"),
                               "camera_info": self.param("camera_info_topic")}
        file_note = self.publish_result(result, stamp)
        try:
            self.publish_overlay(render_overlay(frame, result.T_child_parent), stamp, result.child_frame)
        except Exception as e:  # noqa: BLE001
            self.get_logger().warning(f"overlay failed: {e}")
        r, t = result.sigma()
        return f"published: sigma {r:.3f} deg / {t:.2f} mm; {file_note}"

    def status_dict(self) -> dict:
        d = super().status_dict()
        try:
            cal = self.calib.status()
        except Exception as e:  # noqa: BLE001
            cal = {"status_error": str(e)}
        # The node's own reason (bad message, missing CameraInfo, ...) wins over
        # the calibrator's, which only knows about observations.
        reason = self.last_reason or cal.get("last_reason", "")
        d.update(cal)
        d["last_reason"] = reason
        d["camera_info"] = self.camera is not None
        d["dropped_out_of_order"] = getattr(self.sync, "dropped_out_of_order", 0)
        if self.last_result is not None:
            d["sigma_deg_mm"] = list(self.last_result.sigma())
        return d


def main(args: list[str] | None = None) -> int:
    return run_node(LrfCalibNode, args if args is not None else sys.argv)


if __name__ == "__main__":
    sys.exit(main())
