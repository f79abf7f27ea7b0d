"""`targetless_calib_node`: spinning LiDAR + camera on a moving car, no target
(paper 001), thin ROS shell.

Subscribes ``lidar_topic`` (PointCloud2, per-point time where the driver has
it), ``image_topic``, ``camera_info_topic`` and optionally ``mask_topic`` (a
mono8 mask of moving objects from any segmentation node, matched to images
by stamp). Sweeps and images go to the calibrator in arrival order; when a
window of frames is complete it is calibrated (SfM, object alignment, ICP,
curve refinement, PnP), the quality gates decide, and a new window starts.
All of the method lives in :mod:`lidar_cam_calib.targetless`.
"""
from __future__ import annotations

import collections
import sys
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from ..core.errors import InputError
from ..io.convert import camera_info_to_model, image_to_array, pointcloud2_to_arrays, stamp_to_s
from ..targetless.calibrator import TargetlessCalibrator, TargetlessConfig
from ..targetless.frame import CameraFrame, LidarSweep
from .node_base import CalibNodeBase, run_node


class TargetlessCalibNode(CalibNodeBase):
    method_name = "targetless"
    config_cls = TargetlessConfig

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("targetless_calib_node", **kwargs)
        self.camera = None
        self.masks: collections.OrderedDict = collections.OrderedDict()
        self._last_sweep: LidarSweep | None = None
        self.add_input("lidar", PointCloud2, "lidar_topic", "/points", "PointCloud2 of the spinning LiDAR "
                       "(per-point time where the driver publishes it).", self._on_cloud)
        self.add_input("image", Image, "image_topic", "/camera/image_raw", "Camera image (mono8, bgr8, rgb8).",
                       self._on_image)
        self.add_input("camera_info", CameraInfo, "camera_info_topic", "/camera/camera_info",
                       "CameraInfo of the image (its intrinsics).", self._on_info)
        self.add_input("mask", Image, "mask_topic", "", "Optional mono8 mask of moving objects from a segmentation "
                       "node (non-zero = dynamic), matched to images by stamp; empty: none.", self._on_mask,
                       required=False)
        self.get_logger().info(f"targetless calibration: lidar={self.param('lidar_topic')} "
                               f"image={self.param('image_topic')} mask={self.param('mask_topic') or 'none'}")
        self.announce_ready()

    def make_calibrator(self, cfg: TargetlessConfig) -> TargetlessCalibrator:
        return TargetlessCalibrator(cfg)

    def on_reset(self) -> None:
        self.masks.clear()
        self._last_sweep = None

    def after_fit(self) -> None:
        # the next window starts; the accepted windows stay and are fused with the next ones
        self.calib.next_window()

    # -- inputs -------------------------------------------------------------------------
    def _on_info(self, msg: CameraInfo) -> None:
        self.camera = camera_info_to_model(msg)

    def _on_mask(self, msg: Image) -> None:
        m = image_to_array(msg)
        if m.ndim != 2:
            raise InputError(f"mask must be a single-channel image (mono8), got encoding {msg.encoding!r}")
        self.masks[round(stamp_to_s(msg.header.stamp), 4)] = m != 0
        while len(self.masks) > 30:
            self.masks.popitem(last=False)

    def _on_cloud(self, msg: PointCloud2) -> None:
        t = stamp_to_s(msg.header.stamp)
        self.check_stamp("lidar", t, msg.data)
        arrays = pointcloud2_to_arrays(msg)
        if arrays["xyz"].shape[0] == 0:
            raise InputError("PointCloud2 has no valid point (empty, or every point NaN)")
        sweep = LidarSweep(t, arrays["xyz"], arrays.get("time_s"), arrays.get("intensity"),
                           msg.header.frame_id or "lidar", arrays.get("ring"))
        self._last_sweep = sweep
        self.submit_frame(sweep, t, auto=True, wait=False, max_queued=4)

    def _on_image(self, msg: Image) -> None:
        t = stamp_to_s(msg.header.stamp)
        self.check_stamp("image", t, msg.data)
        if self.camera is None:
            raise InputError(f"no CameraInfo received yet on {self.param('camera_info_topic')}: image dropped")
        img = image_to_array(msg)
        if img.dtype != np.uint8:
            raise InputError(f"image encoding {msg.encoding!r} is not 8-bit (mono8, bgr8, rgb8 expected)")
        mask = self.masks.get(round(t, 4))
        frame = CameraFrame(t, img, self.camera, mask, msg.header.frame_id or "camera_optical_frame")
        self.submit_frame(frame, t, auto=True, wait=False, max_queued=4)

    # -- outputs --------------------------------------------------------------------------
    def render_overlays(self, frame: Any, cal) -> dict:
        from ..targetless.overlay import render_overlay

        r = cal.results[""]
        imgs = getattr(self.calib, "last_window_images", None) or []
        img = frame if isinstance(frame, CameraFrame) else (imgs[-1] if imgs else None)
        if img is None or self._last_sweep is None:
            return {}
        return {"": render_overlay(img.image, img.camera, self._last_sweep.points, r.T_child_parent)}

    def method_status(self) -> dict:
        return {"camera_info": self.camera is not None, "masks": bool(self.param("mask_topic"))}


def main(args: list[str] | None = None) -> int:
    return run_node(TargetlessCalibNode, args if args is not None else sys.argv)


if __name__ == "__main__":
    sys.exit(main())
