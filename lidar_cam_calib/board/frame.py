"""Frames and board geometry for the board method (ROS-free).

A :class:`BoardFrame` is one LiDAR sweep plus the images of the cameras taken
at about the same time; the ROS node builds it from PointCloud2 + Image +
CameraInfo, the benchmark from the simulator, :mod:`lidar_cam_calib.io.lcct`
from the CMU toolbox sample.

Board frame (:class:`BoardGeometry`): origin at the board centre, x along the
long side, y along the short side, z out of the printed pattern (towards the
sensors that see it). Inner corners are ordered x fastest.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.camera import CameraModel
from ..core.errors import ConfigError, InputError


@dataclasses.dataclass(frozen=True)
class BoardGeometry:
    """``squares``: (long, short) number of squares; ``square_m``: side of
    one square; ``size_m``: outer size of the whole board (long, short), the
    pattern centred in it."""
    squares: tuple = (10, 7)
    square_m: float = 0.055
    size_m: tuple = (1.0, 0.7)

    def __post_init__(self) -> None:
        sq = tuple(int(v) for v in self.squares)
        sz = tuple(float(v) for v in self.size_m)
        if len(sq) != 2 or min(sq) < 3:
            raise ConfigError(f"board_squares={list(self.squares)}: need two numbers >= 3 (e.g. [10, 7])")
        if len(sz) != 2 or min(sz) <= 0:
            raise ConfigError(f"board_size_m={list(self.size_m)}: need two positive sizes in metres")
        if sq[0] < sq[1]:
            sq = (sq[1], sq[0])
        if sz[0] < sz[1]:
            sz = (sz[1], sz[0])
        if self.square_m <= 0 or sq[0] * self.square_m > sz[0] + 1e-9 or sq[1] * self.square_m > sz[1] + 1e-9:
            raise ConfigError(f"board_square_m={self.square_m}: a {sq[0]}x{sq[1]} pattern of it does not fit "
                              f"on a {sz[0]}x{sz[1]} m board")
        object.__setattr__(self, "squares", sq)
        object.__setattr__(self, "size_m", sz)

    @property
    def pattern_size(self) -> tuple:
        """Inner corners (columns along x, rows along y), as OpenCV wants it."""
        return (self.squares[0] - 1, self.squares[1] - 1)

    @property
    def n_corners(self) -> int:
        a, b = self.pattern_size
        return a * b

    def inner_corners_board(self) -> np.ndarray:
        """(n, 3) inner corners in the board frame, x fastest (paper eq. 1)."""
        nx, ny = self.pattern_size
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        x = (i.ravel() - (nx - 1) / 2.0) * self.square_m
        y = (j.ravel() - (ny - 1) / 2.0) * self.square_m
        return np.column_stack([x, y, np.zeros_like(x)])

    def outline_board(self) -> np.ndarray:
        """(4, 3) outer corners of the board in the board frame."""
        a, b = self.size_m[0] / 2, self.size_m[1] / 2
        return np.array([[-a, -b, 0], [a, -b, 0], [a, b, 0], [-a, b, 0]], dtype=float)


@dataclasses.dataclass
class CameraImage:
    """One camera's image at ``stamp_s`` (mono8 HxW or bgr8 HxWx3)."""
    stamp_s: float
    image: np.ndarray
    camera: CameraModel | None
    frame_id: str = "camera_optical_frame"


@dataclasses.dataclass
class BoardFrame:
    """One LiDAR sweep (LiDAR frame, metres) and the images that go with it.

    ``intensity``, ``ring``, ``time``: per-point arrays or None when the
    cloud has no such field. ``images``: camera name -> :class:`CameraImage`."""
    stamp_s: float
    points: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None
    time: np.ndarray | None = None
    lidar_frame: str = "lidar"
    images: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"BoardFrame.points must be (N, 3), got shape {p.shape}")
        self.points = p
        n = p.shape[0]
        for name in ("intensity", "ring", "time"):
            v = getattr(self, name)
            if v is None:
                continue
            v = np.asarray(v).ravel()
            if v.shape[0] != n:
                raise InputError(f"BoardFrame.{name} has {v.shape[0]} values for {n} points")
            setattr(self, name, v)

    @classmethod
    def from_cloud(cls, stamp_s: float, cloud: dict, lidar_frame: str = "lidar",
                   images: dict | None = None) -> "BoardFrame":
        """From a dict of arrays x, y, z[, intensity][, ring][, time]
        (:func:`lidar_cam_calib.io.convert.pointcloud2_to_arrays`'s output)."""
        try:
            pts = np.column_stack([np.asarray(cloud[k], dtype=float).ravel() for k in ("x", "y", "z")])
        except KeyError as e:
            raise InputError(f"point cloud has no field {e.args[0]!r}: need x, y, z") from e

        def opt(k):
            v = cloud.get(k)
            return None if v is None else np.asarray(v).ravel()
        return cls(float(stamp_s), pts, opt("intensity"), opt("ring"), opt("time"), lidar_frame,
                   dict(images or {}))


__all__ = ["BoardFrame", "BoardGeometry", "CameraImage"]
