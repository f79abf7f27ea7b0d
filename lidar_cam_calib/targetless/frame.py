"""Frames the targetless calibrator takes: one LiDAR sweep or one camera image (ROS-free).

The node converts sensor_msgs/PointCloud2 into :class:`LidarSweep` and
sensor_msgs/Image (+ CameraInfo, + optional mask Image) into
:class:`CameraFrame`; the two streams are fed independently in stamp order.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.camera import CameraModel
from ..core.errors import InputError


@dataclasses.dataclass
class LidarSweep:
    """``points`` (N,3) in the LiDAR frame at each point's measurement time
    (not motion-compensated), in the driver's order; ``time_s`` (N,) seconds
    after ``stamp_s`` when the driver publishes it (else None: estimated from
    the azimuth); ``ring`` (N,) the laser of each point when the driver
    publishes it (else None: found from the order or the elevations)."""
    stamp_s: float
    points: np.ndarray
    time_s: np.ndarray | None = None
    intensity: np.ndarray | None = None
    frame_id: str = "lidar"
    ring: np.ndarray | None = None

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=float).reshape(-1, 3)
        ok = np.all(np.isfinite(p), axis=1) & (np.linalg.norm(p, axis=1) > 0.3)
        if self.time_s is not None:
            t = np.asarray(self.time_s, dtype=float).ravel()
            if t.size != ok.size:
                raise InputError(f"LiDAR sweep has {ok.size} points but {t.size} per-point times")
            self.time_s = t[ok]
        if self.intensity is not None:
            i = np.asarray(self.intensity, dtype=float).ravel()
            self.intensity = i[ok] if i.size == ok.size else None
        if self.ring is not None:
            r = np.asarray(self.ring).ravel()
            self.ring = r[ok] if r.size == ok.size else None
        self.points = p[ok]

    @classmethod
    def from_arrays(cls, stamp_s: float, cloud: dict, frame_id: str = "lidar") -> "LidarSweep":
        """From a dict of x, y, z[, time, intensity, ring] arrays (io.convert / simulator)."""
        pts = np.stack([np.asarray(cloud[k], float) for k in ("x", "y", "z")], axis=1)
        return cls(float(stamp_s), pts, cloud.get("time"), cloud.get("intensity"), frame_id, cloud.get("ring"))


@dataclasses.dataclass
class CameraFrame:
    """``image`` HxW (mono8) or HxWx3 (bgr8) uint8; ``mask`` optional HxW
    bool, True on pixels of moving objects (from an upstream segmentation)."""
    stamp_s: float
    image: np.ndarray
    camera: CameraModel
    mask: np.ndarray | None = None
    frame_id: str = "camera"

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.dtype != np.uint8 or img.ndim not in (2, 3):
            raise InputError(f"image must be HxW or HxWx3 uint8, got {img.dtype} {img.shape}")
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but CameraInfo says "
                             f"{self.camera.width}x{self.camera.height}")
        if self.mask is not None:
            m = np.asarray(self.mask).astype(bool)
            if m.shape != img.shape[:2]:
                raise InputError(f"mask is {m.shape[1]}x{m.shape[0]}, image {img.shape[1]}x{img.shape[0]}")
            self.mask = m
        self.image = img
