"""One synchronised laser + depth frame for the lrf method (ROS-free).

The ROS node converts sensor_msgs/LaserScan + depth sensor_msgs/Image +
sensor_msgs/CameraInfo into this; the simulator's observations map onto it
with :meth:`LrfFrame.from_sim`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.camera import CameraModel


@dataclasses.dataclass
class LrfFrame:
    """``scan_*``: the LaserScan fields (ranges in metres, angles in radians,
    angle counter-clockwise about the laser z axis from its x axis).
    ``depth_m``: HxW float32 z-depth in metres in the camera optical frame
    (NaN, 0 or inf = invalid). ``camera``: intrinsics of the depth image."""
    stamp_s: float
    scan_ranges_m: np.ndarray
    scan_angle_min_rad: float
    scan_angle_increment_rad: float
    scan_range_min_m: float
    scan_range_max_m: float
    depth_m: np.ndarray
    camera: CameraModel
    laser_frame: str = "laser"
    camera_frame: str = "camera_depth_optical_frame"

    def __post_init__(self) -> None:
        self.scan_ranges_m = np.asarray(self.scan_ranges_m, dtype=np.float32).ravel()
        d = np.asarray(self.depth_m)
        if d.dtype != np.float32:
            d = d.astype(np.float32)
        self.depth_m = d

    @classmethod
    def from_sim(cls, obs, right: bool = False, laser_frame: str = "laser",
                 camera_frame: str | None = None) -> LrfFrame:
        """From a simulator observation (duck-typed; ``right`` uses the right camera)."""
        depth = obs.depth_right_m if right else obs.depth_m
        cam = obs.camera_right if right else obs.camera
        return cls(float(obs.stamp_s), obs.scan_ranges_m, float(obs.scan_angle_min_rad),
                   float(obs.scan_angle_increment_rad), float(obs.scan_range_min_m),
                   float(obs.scan_range_max_m), depth, cam, laser_frame,
                   camera_frame or ("camera_right_depth_optical_frame" if right else "camera_depth_optical_frame"))
