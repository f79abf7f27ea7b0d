"""`board_calib_node`: 3D LiDAR + one or more cameras, reflective-border
checkerboard (paper 000), thin ROS shell.

Subscribes the LiDAR's PointCloud2 (``lidar_topic``) and, for every name N in
``camera_names``, ``N.image_topic`` and ``N.camera_info_topic``. Each sweep is
paired with the nearest image of every camera (each camera on its own clock,
within ``max_image_skew_s``) one sweep later, when the images around it have
arrived. A placement is taken when the board has been still for
``still_time_s`` (``trigger`` auto/both) or on ``~/capture``; the base fits
after every new placement once enough are in and publishes one transform per
camera. All of the method lives in :mod:`lidar_cam_calib.board`.
"""
from __future__ import annotations

import collections
import functools
import sys
from typing import Any

from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from ..board.calibrator import BoardCalibrator, BoardConfig
from ..board.frame import BoardFrame, CameraImage
from ..board.lidar_board import BoardNotFound
from ..board.overlay import render_overlay
from ..core.errors import InputError
from ..io.convert import camera_info_to_model, image_to_array, pointcloud2_to_arrays, stamp_to_s
from .node_base import CalibNodeBase, run_node

TRIGGERS = ("service", "auto", "both")


class BoardCalibNode(CalibNodeBase):
    method_name = "board"
    config_cls = BoardConfig

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("board_calib_node", **kwargs)
        names = list(self.cfg.camera_names)
        if len(set(names)) != len(names):
            from ..core.errors import ConfigError

            raise ConfigError(f"parameter camera_names={names} lists a camera twice")
        self.models: dict = {}
        self.images: dict = {n: collections.deque(maxlen=16) for n in names}
        self._pending: BoardFrame | None = None     # the newest sweep, waiting for its images
        self.latest_frame: BoardFrame | None = None  # the newest sweep with its images
        self._considering = 0
        self.add_input("lidar", PointCloud2, "lidar_topic", "/lidar/points", "sensor_msgs/PointCloud2 of the "
                       "LiDAR (x, y, z; intensity, ring and time when the driver has them).", self._on_cloud)
        for n in names:
            self.add_input(f"{n}.image", Image, f"{n}.image_topic", f"/{n}/image_raw",
                           f"Image of camera {n} (mono8, bgr8, rgb8, ...).", functools.partial(self._on_image, n))
            self.add_input(f"{n}.camera_info", CameraInfo, f"{n}.camera_info_topic", f"/{n}/camera_info",
                           f"CameraInfo of camera {n} (its intrinsics).", functools.partial(self._on_info, n))
            self.declare_param(f"{n}.frame_id", "", f"Optical frame of camera {n} (default: the image's "
                               "frame_id).", read_only=True)
        self.get_logger().info(f"board calibration: lidar={self.param('lidar_topic')} cameras={names} "
                               f"trigger={self.param('trigger')}")
        self.announce_ready()

    def declare_node_params(self) -> None:
        self.declare_param("trigger", "both", "When to take a placement: service (~/capture only), auto (the "
                           "board still for still_time_s) or both.", choices=TRIGGERS)

    def make_calibrator(self, cfg: BoardConfig) -> BoardCalibrator:
        return BoardCalibrator(cfg)

    def on_config_changed(self, cfg: BoardConfig) -> None:
        # the board geometry and detectors follow the config: a new calibrator, keeping its placements
        old = self.calib
        self.calib = BoardCalibrator(cfg)
        self.calib.observations, self.calib.cameras = old.observations, old.cameras
        self.calib.frame_ids, self.calib.lidar_frame = old.frame_ids, old.lidar_frame

    def on_reset(self) -> None:
        self._pending = None
        self.latest_frame = None
        for q in self.images.values():
            q.clear()

    # -- inputs ---------------------------------------------------------------------
    def _on_info(self, name: str, msg: CameraInfo) -> None:
        self.models[name] = camera_info_to_model(msg)

    def _on_image(self, name: str, msg: Image) -> None:
        t = stamp_to_s(msg.header.stamp)
        self.check_stamp(f"{name}.image", t, msg.data)
        img = image_to_array(msg)
        if img.dtype != "uint8":
            raise InputError(f"camera {name}: image encoding {msg.encoding!r} is not 8-bit; the board is found "
                             "in mono8 or colour images")
        frame_id = self.param(f"{name}.frame_id") or msg.header.frame_id or f"{name}_optical_frame"
        self.images[name].append(CameraImage(t, img, None, frame_id))

    def _on_cloud(self, msg: PointCloud2) -> None:
        t = stamp_to_s(msg.header.stamp)
        self.check_stamp("lidar", t, msg.data)
        arrays = pointcloud2_to_arrays(msg)
        if arrays["xyz"].shape[0] == 0:
            raise InputError("PointCloud2 has no valid point (empty, or every point NaN)")
        frame = BoardFrame(t, arrays["xyz"], arrays.get("intensity"), arrays.get("ring"), arrays.get("time_s"),
                           msg.header.frame_id or "lidar")
        prev, self._pending = self._pending, frame
        if prev is not None:   # the images around the previous sweep have arrived by now
            self._complete(prev)

    def _attach_images(self, frame: BoardFrame) -> None:
        """Attach to ``frame`` the image of every camera nearest its stamp."""
        skew = float(self.cfg.max_image_skew_s)
        for n, q in self.images.items():
            best = min(q, key=lambda ci: abs(ci.stamp_s - frame.stamp_s), default=None)
            if best is not None and abs(best.stamp_s - frame.stamp_s) <= skew:
                frame.images[n] = CameraImage(best.stamp_s, best.image, self.models.get(n), best.frame_id)

    def _complete(self, frame: BoardFrame) -> None:
        self._attach_images(frame)
        self.latest_frame = frame
        if self.param("trigger") in ("auto", "both"):
            if self.pub_ack is None and self._considering > 0:
                return  # live: the worker is busy (fitting); this sweep is skipped for stillness
            self._considering += 1
            self.submit(functools.partial(self._consider, frame, self._generation), wait=False)

    def _consider(self, frame: BoardFrame, gen: int) -> tuple[bool, str]:
        """Worker: is the board still? then this sweep is a placement."""
        try:
            if gen != self._generation:
                return False, "sweep from before ~/recalibrate"
            try:
                lb = self.calib.detect_lidar(frame)
            except BoardNotFound as e:
                self.calib.still.update(frame.stamp_s, None, None)
                return False, str(e)
            if not self.calib.still.update(frame.stamp_s, lb.centre, lb.normal):
                return False, "board not still yet"
            return self._process_frame(frame, frame.stamp_s, True, gen, lidar_board=lb)
        finally:
            self._considering -= 1

    def on_capture(self) -> tuple[bool, str]:
        frame = self._pending or self.latest_frame
        if frame is None:
            return False, f"no PointCloud2 received yet on {self.param('lidar_topic')}"
        if frame is self._pending:
            self._attach_images(frame)
        stale = self.fresh_enough(frame.stamp_s)
        if stale:
            return False, stale
        missing = [n for n in self.cfg.camera_names if n not in self.models]
        if len(missing) == len(self.cfg.camera_names):
            return False, "no CameraInfo received yet for any camera (" + ", ".join(
                self.param(f"{n}.camera_info_topic") for n in missing) + ")"
        return self.submit_frame(frame, frame.stamp_s, auto=False, wait=True)

    # -- outputs ----------------------------------------------------------------------
    def render_overlays(self, frame: BoardFrame, cal) -> dict:
        out = {}
        for n, r in cal.results.items():
            ci = frame.images.get(n)
            if ci is not None and ci.camera is not None:
                out[n] = render_overlay(ci.image, ci.camera, frame.points, r.T_child_parent)
        return out

    def method_status(self) -> dict:
        return {"trigger": self.param("trigger"),
                "camera_info": {n: n in self.models for n in self.cfg.camera_names},
                "images_received": {n: len(q) > 0 for n, q in self.images.items()}}


def main(args: list[str] | None = None) -> int:
    return run_node(BoardCalibNode, args if args is not None else sys.argv)


if __name__ == "__main__":
    sys.exit(main())
