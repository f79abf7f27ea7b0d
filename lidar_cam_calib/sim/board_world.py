"""Simulator for the ``board`` method (paper 000): a spinning LiDAR and 1-3 cameras on a rig,
a checkerboard with a retro-reflective border carried between still poses, in a textured room.

Frames
------
* LiDAR frame (``lidar``): x forward, y left, z up; the world of the simulation (the rig does
  not move). The floor is at ``z = -scene.lidar_height_m``.
* Board frame: origin at the board centre, x along the long side, y along the short side, z out
  of the patterned face. The checker pattern is centred; its square (0, 0) (lowest x and y) is
  black. Inner corner (i, j) is at ``((i - (nx - 2) / 2) d, (j - (ny - 2) / 2) d, 0)``
  (paper 000 eq. 1), listed row-major with i (along x) fastest.
* Camera optical frames (``<name>_optical_frame``): z forward, x right, y down.
  ``T_camera_lidar`` maps LiDAR points into the camera optical frame.

Models
------
* Camera images are ray-cast per pixel through the camera model (the pixel's distorted
  coordinates are undistorted to a ray, so the rendered image carries exactly the model's
  distortion). The checker, the checker/border boundary and the board outline are box-filtered
  analytically over the pixel footprint in board coordinates (no aliasing), then Gaussian blur
  (defocus), exposure, Gaussian read noise and 8-bit quantisation. mono8 or bgr8. A board moving
  during the exposure (``exposure_time_s``) is motion-blurred (five sub-exposure poses averaged).
  Pixels outside the distortion model's invertible region see nothing (a fisheye beyond 90 deg).
* The LiDAR casts the preset's beams against the board rectangle and the room (floor, walls,
  optional ceiling, optional retro-reflective distractor patch on a wall). Each beam near the
  board is split into sub-rays over its divergence footprint (Gaussian weights): the return
  intensity mixes border / checker / background by footprint fraction (so it drops at the
  board's edges and the intensity threshold shrinks the board by millimetres per edge), the
  range is the board's when the board side returns more energy than the background, and
  mixed returns with comparable energies may land between board and wall (mixed pixels).
  During a carry every beam sees the board at its own firing time.
* Poses: each pose is drawn for one camera in turn (so rigs with cameras pointing apart get poses
  for every camera): the whole board inside that camera's image, a checker square of at least
  ``min_square_px`` pixels, at least ``min_rings`` LiDAR rings across it, 1.5-6 m from the LiDAR,
  turned and tilted, in-plane roll about +/-45 deg for a share ``roll45_prob`` of the poses.
* Timeline: the board is still for ``still_s`` at each pose and carried for ``carry_s`` to the
  next (smooth-step blend with a lift); LiDAR sweeps at the preset rate, every camera at its
  own rate and phase, its stamps on its own clock (``time_offset_s`` added to the capture time).

Entry points: :func:`simulate_board` (in-memory frames for tests and benchmarks),
:func:`sample_board_family` (a scenario drawn from a seed), :func:`load_board_scenario`
(YAML/dict), :class:`BoardWorld` (used by :mod:`lidar_cam_calib.sim.board_bag`).
"""
from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.geometry import (
    R_BODY_OPTICAL,
    R_from_rpy,
    inv_T,
    make_T,
    so3_exp,
    so3_log,
)
from lidar_cam_calib.sim.lidar import ALL_FIELDS, PRESETS, LidarPreset, get_preset
from lidar_cam_calib.sim.scenario import build_dataclass

# ---------------------------------------------------------------------------------------------
# board
# ---------------------------------------------------------------------------------------------


@dataclass
class BoardSpec:
    """Checkerboard with a retro-reflective border (paper 000: 10x7 squares of 55 mm centred in a
    1000 x 700 mm board; the border is the board area outside the checker pattern)."""

    squares: tuple = (10, 7)
    square_m: float = 0.055
    size_m: tuple = (1.0, 0.7)
    # rendering / reflectance (unit scale: 1 = full-scale LiDAR intensity, camera 0..1 radiance)
    border_lidar_unit: float = 1.04  # > 1: retro-reflective returns saturate the intensity scale
    checker_white_lidar_unit: float = 0.30
    checker_black_lidar_unit: float = 0.06
    border_gray: float = 0.62
    white_gray: float = 0.88
    black_gray: float = 0.07
    back_gray: float = 0.35

    def __post_init__(self) -> None:
        self.squares = tuple(int(v) for v in self.squares)
        self.size_m = tuple(float(v) for v in self.size_m)
        if len(self.squares) != 2 or min(self.squares) < 3:
            raise ValueError(f"board squares must be two integers >= 3, got {self.squares}")
        if len(self.size_m) != 2 or self.square_m <= 0:
            raise ValueError("board size_m needs two values and square_m must be > 0")
        cw, ch = self.checker_size_m
        if cw >= self.size_m[0] or ch >= self.size_m[1]:
            raise ValueError(f"checker pattern {cw:.3f} x {ch:.3f} m does not fit in the board "
                             f"{self.size_m[0]:.3f} x {self.size_m[1]:.3f} m")

    @property
    def inner_corners(self) -> tuple:
        return (self.squares[0] - 1, self.squares[1] - 1)

    @property
    def checker_size_m(self) -> tuple:
        return (self.squares[0] * self.square_m, self.squares[1] * self.square_m)

    @property
    def border_m(self) -> tuple:
        """Border width (x, y): board edge to checker pattern."""
        return ((self.size_m[0] - self.checker_size_m[0]) / 2, (self.size_m[1] - self.checker_size_m[1]) / 2)

    def inner_corners_board(self) -> np.ndarray:
        """(nx-1)*(ny-1) x 3 inner corners in the board frame, row-major with x fastest."""
        nx, ny = self.inner_corners
        d = self.square_m
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        x = (i.ravel() - (nx - 1) / 2.0) * d
        y = (j.ravel() - (ny - 1) / 2.0) * d
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    def outline_board(self) -> np.ndarray:
        """(4, 3) outer corners in the board frame: (-x,-y), (+x,-y), (+x,+y), (-x,+y)."""
        a, b = self.size_m[0] / 2, self.size_m[1] / 2
        return np.array([[-a, -b, 0.0], [a, -b, 0.0], [a, b, 0.0], [-a, b, 0.0]])

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["squares"] = list(self.squares)
        d["size_m"] = list(self.size_m)
        d["inner_corners"] = list(self.inner_corners)
        return d


# ---------------------------------------------------------------------------------------------
# scenario
# ---------------------------------------------------------------------------------------------
# Known camera bodies: (width, height, fx, fy, cx, cy, distortion_model, D)
CAMERA_TYPES: dict = {
    # paper 000 Table 2
    "mer132": (1292, 964, 1097.9, 1095.4, 652.383, 497.9676, "plumb_bob", [-0.0975, 0.0879, 0.0, 0.0, 0.0]),
    "zed2_left": (1920, 1080, 1057.47, 1056.79, 958.87, 545.144, "plumb_bob", [-0.0437, 0.0122, 0.0, 0.0, 0.0]),
    # others
    "wide720": (1280, 720, 640.0, 640.0, 636.5, 362.0, "plumb_bob", [-0.28, 0.075, 0.0004, -0.0003, -0.009]),
    "ind1440": (1440, 1080, 1650.0, 1650.0, 719.0, 541.0, "plumb_bob", [-0.12, 0.15, 0.0, 0.0, 0.0]),
    "fisheye1280": (1280, 960, 480.0, 480.0, 641.0, 478.5, "equidistant", [0.02, -0.006, 0.001, -0.0002]),
    "vga": (640, 480, 520.0, 520.0, 319.5, 239.5, "plumb_bob", [-0.08, 0.05, 0.0, 0.0, 0.0]),
}


@dataclass
class CameraSpec:
    """One camera of the rig. Mount: position of the optical centre in the LiDAR frame and the
    camera *body* orientation (x forward, y left, z up) as roll/pitch/yaw (deg, R = Rz Ry Rx)
    in the LiDAR frame; the optical frame is body @ R_BODY_OPTICAL. Intrinsics default to the
    ``type`` entry of CAMERA_TYPES; any of width..D set here overrides it."""

    name: str = "camera"
    type: str = "mer132"
    width: int = 0
    height: int = 0
    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    distortion_model: str = ""
    D: list = field(default_factory=list)
    encoding: str = "mono8"
    rate_hz: float = 12.0
    phase_s: float = 0.013
    time_offset_s: float = 0.0
    xyz_m: list = field(default_factory=lambda: [0.1, 0.0, -0.1])
    rpy_deg: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    blur_sigma_px: float = 0.7
    noise_sigma_dn: float = 2.0
    exposure: float = 1.0
    image_scale: float = 1.0  # render at this fraction of the resolution (times the scenario's)
    exposure_time_s: float = 0.01  # a board moving during the exposure is motion-blurred

    def model(self) -> CameraModel:
        if self.type not in CAMERA_TYPES and not (self.width and self.fx):
            raise ValueError(f"camera {self.name}: unknown type {self.type!r} (known: {', '.join(CAMERA_TYPES)}) "
                             "and no explicit width/height/fx/fy/cx/cy")
        w, h, fx, fy, cx, cy, dm, D = CAMERA_TYPES.get(self.type, (0, 0, 0, 0, 0, 0, "plumb_bob", []))
        w = self.width or w
        h = self.height or h
        fx, fy = self.fx or fx, self.fy or fy
        cx, cy = self.cx or cx, self.cy or cy
        dm = self.distortion_model or dm
        D = list(self.D) if self.D else list(D)
        return CameraModel.from_K(w, h, fx, fy, cx, cy, D=np.asarray(D, float), distortion_model=dm)

    def T_lidar_camera(self) -> np.ndarray:
        r, p, y = np.deg2rad(np.asarray(self.rpy_deg, dtype=float))
        return make_T(R_from_rpy(r, p, y) @ R_BODY_OPTICAL, np.asarray(self.xyz_m, dtype=float))


@dataclass
class LidarSpec:
    """The LiDAR: a preset from lidar.PRESETS plus overrides (None/negative = preset value)."""

    preset: str = "rs16"
    range_sigma_m: float = -1.0
    dropout_prob: float = -1.0
    ring_bias_sigma_m: float = 0.0
    intensity_sigma_unit: float = -1.0
    azimuth_range_deg: list = field(default_factory=list)  # [lo, hi] driver FOV crop; [] = 360
    drop_fields: list = field(default_factory=list)  # e.g. ["time"]: the driver publishes no time
    mixed_pixel_prob: float = 0.5
    # the bag records every k-th sweep (like a throttled `ros2 bag record`; each message is still
    # one full 1/rate_hz sweep). In-memory simulation is not affected.
    record_every: int = 1

    def make_preset(self) -> LidarPreset:
        p = get_preset(self.preset)
        ch: dict = {}
        if self.range_sigma_m >= 0:
            ch["range_sigma_m"] = float(self.range_sigma_m)
        if self.dropout_prob >= 0:
            ch["dropout_prob"] = float(self.dropout_prob)
        if self.intensity_sigma_unit >= 0:
            ch["intensity_sigma_unit"] = float(self.intensity_sigma_unit)
        bad = [f for f in self.drop_fields if f not in ("intensity", "ring", "time")]
        if bad:
            raise ValueError(f"lidar.drop_fields may name intensity, ring, time; got {bad}")
        if self.drop_fields:
            ch["fields"] = tuple(f for f in p.fields if f not in self.drop_fields)
        return p.replace(**ch) if ch else p


@dataclass
class SceneSpec:
    """Room around the rig (LiDAR frame). Walls at x = front_m, x = -back_m, y = left_m,
    y = -right_m; floor lidar_height_m below the LiDAR; ceiling_m above it (0 = open sky)."""

    lidar_height_m: float = 1.1
    front_m: float = 11.0
    back_m: float = 7.0
    left_m: float = 6.0
    right_m: float = 6.5
    ceiling_m: float = 2.6
    texture_seed: int = 7
    distractor: bool = False  # a 0.4 x 0.3 m retro-reflective sign on a wall
    floor_lidar_unit: float = 0.12
    wall_lidar_unit: float = 0.25


@dataclass
class PosesSpec:
    """Board poses (each seen whole by at least one camera and crossed by >= min_rings rings)."""

    n_poses: int = 20
    distance_m: list = field(default_factory=lambda: [1.5, 6.0])  # LiDAR to board centre
    yaw_deg: list = field(default_factory=lambda: [-40.0, 40.0])  # turn about the vertical
    tilt_deg: list = field(default_factory=lambda: [-25.0, 25.0])  # lean about the long axis
    roll_deg: list = field(default_factory=lambda: [-30.0, 30.0])  # in-plane
    roll45_prob: float = 0.5  # share of poses with in-plane roll about +/-45 deg (+/-10)
    min_rings: int = 4
    image_margin: float = 0.04  # board outline inside the image by this fraction of its size
    # the camera that must see the board sees a checker square at least this big (full-size
    # pixels, fronto-parallel): wide cameras get the board nearer, as a person would place it
    min_square_px: float = 12.0
    min_height_above_floor_m: float = 0.15


@dataclass
class TimelineSpec:
    start_s: float = 1.7e9
    still_s: list = field(default_factory=lambda: [1.5, 2.0])  # per pose, drawn
    carry_s: list = field(default_factory=lambda: [1.0, 2.0])
    lift_m: float = 0.08  # the board rises this much mid-carry
    # simulate_board (in memory) keeps only some sweeps: per pose this many still ones
    # (evenly spread over the still interval) and per carry this many moving ones.
    memory_still_frames: int = 2
    memory_carry_frames: int = 1
    compress: bool = True


@dataclass
class BoardScenario:
    name: str = "board_default"
    seed: int = 0
    board: BoardSpec = field(default_factory=BoardSpec)
    lidar: LidarSpec = field(default_factory=LidarSpec)
    cameras: list = field(default_factory=lambda: [
        CameraSpec(name="cam_mer", type="mer132", encoding="mono8", rate_hz=12.0, phase_s=0.013,
                   time_offset_s=0.004, xyz_m=[0.08, 0.12, -0.12], rpy_deg=[0.5, 2.0, 4.0]),
        CameraSpec(name="cam_zed", type="zed2_left", encoding="bgr8", rate_hz=15.0, phase_s=0.041,
                   time_offset_s=-0.011, xyz_m=[0.1, -0.1, -0.09], rpy_deg=[-0.8, 3.0, -25.0]),
    ])
    scene: SceneSpec = field(default_factory=SceneSpec)
    poses: PosesSpec = field(default_factory=PosesSpec)
    timeline: TimelineSpec = field(default_factory=TimelineSpec)
    image_scale: float = 1.0  # render every camera at this fraction of its resolution

    def __post_init__(self) -> None:
        self.cameras = [c if isinstance(c, CameraSpec) else build_dataclass(CameraSpec, c, f"cameras[{i}]")
                        for i, c in enumerate(self.cameras)]

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["board"] = {k: v for k, v in self.board.to_dict().items() if k != "inner_corners"}
        return _plain(d)


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def load_board_scenario(path_or_dict: str | Path | Mapping[str, Any] | BoardScenario | None) -> BoardScenario:
    """A :class:`BoardScenario` from a YAML path, a dict, or passed through; None = default.

    A YAML/dict with ``family_seed: N`` starts from :func:`sample_board_family` (N) and applies
    the other keys on top. Unknown keys raise ValueError naming them."""
    if path_or_dict is None:
        return default_board_scenario()
    if isinstance(path_or_dict, BoardScenario):
        return path_or_dict
    if isinstance(path_or_dict, (str, Path)):
        with open(path_or_dict, encoding="utf-8") as fh:
            data = yaml.safe_load(fh) or {}
    else:
        data = dict(path_or_dict)
    if "family_seed" in data:
        data = dict(data)
        base = sample_board_family(int(data.pop("family_seed"))).to_dict()
        for k, v in data.items():
            if isinstance(v, Mapping) and isinstance(base.get(k), dict):
                base[k] = {**base[k], **v}
            else:
                base[k] = v
        data = base
    sc = build_dataclass(BoardScenario, data)
    _validate(sc)
    return sc


def _validate(sc: BoardScenario) -> None:
    if sc.poses.n_poses < 1:
        raise ValueError("poses.n_poses must be >= 1")
    if not sc.cameras:
        raise ValueError("the scenario needs at least one camera")
    names = [c.name for c in sc.cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"camera names must be unique, got {names}")
    for c in sc.cameras:
        if c.encoding not in ("mono8", "bgr8"):
            raise ValueError(f"camera {c.name}: encoding must be mono8 or bgr8, got {c.encoding!r}")
        if c.rate_hz <= 0:
            raise ValueError(f"camera {c.name}: rate_hz must be > 0")
        if not 0 < c.image_scale <= 1:
            raise ValueError(f"camera {c.name}: image_scale must be in (0, 1]")
        c.model()
    get_preset(sc.lidar.preset)
    for nm in ("distance_m", "yaw_deg", "tilt_deg", "roll_deg"):
        v = getattr(sc.poses, nm)
        if len(v) != 2 or v[0] > v[1]:
            raise ValueError(f"poses.{nm} must be [min, max]")
    if sc.lidar.record_every < 1:
        raise ValueError("lidar.record_every must be >= 1")
    if not 0 < sc.image_scale <= 1:
        raise ValueError("image_scale must be in (0, 1]")


def default_board_scenario() -> BoardScenario:
    """Paper 000 set-up: RS-LiDAR-16, MER-132-43GC-P (mono) and ZED2 left (colour), 20 poses."""
    return BoardScenario()


# ---------------------------------------------------------------------------------------------
# the family
# ---------------------------------------------------------------------------------------------
def sample_board_family(seed: int, poses: int | None = None, lidar: str | None = None) -> BoardScenario:
    """A scenario drawn from ``seed``: LiDAR preset, 1-3 cameras (type, intrinsics perturbed,
    distortion, encoding, rate, clock offset, mounting: overlapping or not), board variant,
    number of poses, noise levels and the room."""
    rng = np.random.default_rng([int(seed), 0xB0A4D])
    preset = str(rng.choice(list(PRESETS)))  # drawn even when given: the rest of the draw stays the same
    if lidar is not None:
        preset = get_preset(lidar).name
    drop = []
    if rng.random() < 0.2:
        drop.append("time")
    if rng.random() < 0.1:
        drop.append("ring")
    lid = LidarSpec(preset=preset,
                    range_sigma_m=float(PRESETS[preset].range_sigma_m * rng.uniform(0.6, 1.4)),
                    dropout_prob=float(rng.uniform(0.0, 0.01)),
                    ring_bias_sigma_m=float(rng.uniform(0.0, 0.004)),
                    intensity_sigma_unit=float(rng.uniform(0.004, 0.015)),
                    drop_fields=drop, mixed_pixel_prob=float(rng.uniform(0.2, 0.8)))
    # board: mostly the paper's, sometimes a variant
    if rng.random() < 0.6:
        board = BoardSpec()
    else:
        sq = [(10, 7), (9, 6), (11, 8), (8, 6), (9, 7)][int(rng.integers(5))]
        d = round(float(rng.uniform(0.045, 0.065)), 4)
        bx, by = rng.uniform(0.12, 0.24), rng.uniform(0.10, 0.18)
        board = BoardSpec(squares=sq, square_m=d,
                          size_m=(round(sq[0] * d + 2 * bx, 3), round(sq[1] * d + 2 * by, 3)))
    n_cam = int(rng.choice([1, 2, 2, 3]))
    types = list(CAMERA_TYPES)
    cams = []
    yaw0 = float(rng.uniform(-10, 10))
    overlap = rng.random() < 0.5
    for k in range(n_cam):
        ct = "mer132" if k == 0 and rng.random() < 0.4 else str(rng.choice(types))
        w, h, fx, fy, cx, cy, dm, D = CAMERA_TYPES[ct]
        s = rng.uniform(0.95, 1.05)
        D = list(np.asarray(D, float) * rng.uniform(0.7, 1.3, len(D)))
        if k == 0:
            yaw = yaw0
        elif overlap:
            yaw = yaw0 + float(rng.choice([-1, 1]) * rng.uniform(15, 40))
        else:
            yaw = yaw0 + float(rng.choice([-1, 1]) * rng.uniform(70, 110)) if k == 1 else yaw0 + 180.0
        cams.append(CameraSpec(
            name=f"cam{k}", type=ct, width=w, height=h, fx=float(fx * s), fy=float(fy * s * rng.uniform(0.998, 1.002)),
            cx=float(cx + rng.uniform(-8, 8)), cy=float(cy + rng.uniform(-8, 8)), distortion_model=dm,
            D=[float(v) for v in D], encoding=str(rng.choice(["mono8", "bgr8"])),
            rate_hz=float(rng.uniform(10, 15)), phase_s=float(rng.uniform(0, 0.08)),
            time_offset_s=float(rng.uniform(-0.05, 0.05)),
            xyz_m=[float(v) for v in rng.uniform([-0.15, -0.25, -0.25], [0.2, 0.25, 0.1])],
            rpy_deg=[float(rng.uniform(-3, 3)), float(rng.uniform(-5, 12)), float(yaw + rng.uniform(-3, 3))],
            blur_sigma_px=float(rng.uniform(0.5, 1.3)), noise_sigma_dn=float(rng.uniform(1.0, 4.0)),
            exposure=float(rng.uniform(0.8, 1.15)), exposure_time_s=float(rng.uniform(0.003, 0.02))))
    scene = SceneSpec(lidar_height_m=float(rng.uniform(0.8, 1.6)), front_m=float(rng.uniform(9, 15)),
                      back_m=float(rng.uniform(6, 12)), left_m=float(rng.uniform(6, 10)),
                      right_m=float(rng.uniform(6, 10)),
                      ceiling_m=float(0.0 if rng.random() < 0.4 else rng.uniform(1.5, 3.5)),
                      texture_seed=int(rng.integers(1 << 30)), distractor=bool(rng.random() < 0.3),
                      floor_lidar_unit=float(rng.uniform(0.05, 0.25)),
                      wall_lidar_unit=float(rng.uniform(0.1, 0.45)))
    n_poses = int(poses) if poses is not None else int(rng.integers(12, 41))
    pz = PosesSpec(n_poses=n_poses, roll45_prob=float(rng.uniform(0.3, 0.7)))
    tl = TimelineSpec(still_s=[1.5, 2.0], carry_s=[1.0, 2.0])
    return BoardScenario(name=f"board_family_{int(seed)}", seed=int(seed), board=board, lidar=lid, cameras=cams,
                         scene=scene, poses=pz, timeline=tl)


# ---------------------------------------------------------------------------------------------
# run containers (the interface the method codes against)
# ---------------------------------------------------------------------------------------------
@dataclass
class BoardSimCamera:
    name: str
    model: CameraModel
    T_camera_lidar: np.ndarray
    frame_id: str
    encoding: str
    time_offset_s: float
    rate_hz: float = 12.0
    phase_s: float = 0.0
    image_topic: str = ""
    camera_info_topic: str = ""


@dataclass
class BoardSimFrame:
    stamp_s: float
    still: bool
    T_lidar_board: np.ndarray
    cloud: dict
    images: dict
    pose_index: int = -1  # index of the still pose (-1 while carried)
    board_in_view: dict = field(default_factory=dict)  # camera -> whole board inside the image


@dataclass
class BoardSimRun:
    lidar: LidarPreset
    board: BoardSpec
    cameras: dict
    frames: list
    truth: dict
    noise: dict
    lidar_frame: str = "lidar"
    poses: list = field(default_factory=list)  # T_lidar_board of every still pose
    scenario: BoardScenario | None = None


# ---------------------------------------------------------------------------------------------
# filtered patterns
# ---------------------------------------------------------------------------------------------
def _tri(x: np.ndarray, d: float) -> np.ndarray:
    """Integral of the square wave (+1 on [0, d), -1 on [d, 2d), period 2d) from 0 to x."""
    return d - np.abs(np.mod(x, 2 * d) - d)


def _filt_square(x: np.ndarray, w: np.ndarray, d: float) -> np.ndarray:
    return (_tri(x + 0.5 * w, d) - _tri(x - 0.5 * w, d)) / w


def _filt_box(x: np.ndarray, w: np.ndarray, a: float) -> np.ndarray:
    """Box-filtered indicator of |x| <= a (values in [0, 1])."""
    return (np.clip(x + 0.5 * w, -a, a) - np.clip(x - 0.5 * w, -a, a)) / w


def _texture(seed: int, size: int = 512) -> np.ndarray:
    """Tileable smooth noise in [0, 1] (float32, size x size), several octaves."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((size, size), np.float32)
    amp, tot = 1.0, 0.0
    for cells in (4, 8, 16, 32, 64, 128):
        g = rng.random((cells, cells)).astype(np.float32)
        g = np.tile(g, (3, 3))
        up = cv2.resize(g, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)[size:2 * size, size:2 * size]
        acc += amp * up
        tot += amp
        amp *= 0.6
    acc /= tot
    acc = (acc - acc.min()) / max(float(acc.max() - acc.min()), 1e-6)
    return acc


def _sample_wrap(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a tileable texture at texel coordinates (u along columns, v rows)."""
    n = tex.shape[0]
    u0, v0 = np.floor(u), np.floor(v)
    fu, fv = (u - u0).astype(np.float32), (v - v0).astype(np.float32)
    i0, j0 = v0.astype(np.int64) % n, u0.astype(np.int64) % n
    i1, j1 = (i0 + 1) % n, (j0 + 1) % n
    top = tex[i0, j0] * (1 - fu) + tex[i0, j1] * fu
    bot = tex[i1, j0] * (1 - fu) + tex[i1, j1] * fu
    return top * (1 - fv) + bot * fv


_RAY_CACHE: dict = {}


def pixel_rays_fast(m: CameraModel) -> np.ndarray:
    """(H*W, 3) undistorted rays (z = 1) of every pixel centre, as CameraModel.pixel_rays but
    faster: undistort a 4-px grid exactly, interpolate, then refine every pixel by fixed-point
    steps on the model's own distort() (so projection and rendering agree to ~1e-6 px).
    Cached per camera model."""
    key = (m.width, m.height, tuple(np.round(m.K.ravel(), 9)), tuple(np.round(m.D, 12)), m.distortion_model)
    if key in _RAY_CACHE:
        return _RAY_CACHE[key]
    H, W = m.height, m.width
    Kinv = np.linalg.inv(m.K)
    v, u = np.mgrid[0:H, 0:W]
    xd = np.stack([u.ravel(), v.ravel()], 1).astype(float) @ Kinv[:2, :2].T + Kinv[:2, 2]
    with np.errstate(all="ignore"):
        if m.is_distorted and m.distortion_model == "equidistant":
            x = _undistort_equidistant(m, xd)
        elif m.is_distorted:
            x = _undistort_grid(m, xd, u.ravel(), v.ravel())
        else:
            x = xd
    rays = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    if len(_RAY_CACHE) > 8:
        _RAY_CACHE.clear()
    _RAY_CACHE[key] = rays
    return rays


def _undistort_equidistant(m: CameraModel, xd: np.ndarray) -> np.ndarray:
    """Exact inverse of the equidistant model: Newton on theta_d = theta (1 + k1 theta^2 + ...),
    then r = tan(theta). Pixels beyond 90 deg off the axis get NaN (no pinhole ray)."""
    k = m._coeffs()
    thd = np.hypot(xd[:, 0], xd[:, 1])
    th = thd.copy()
    for _ in range(30):
        t2 = th * th
        f = th * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4) - thd
        df = 1 + 3 * k[0] * t2 + 5 * k[1] * t2**2 + 7 * k[2] * t2**3 + 9 * k[3] * t2**4
        th = th - f / df
    bad = ~(np.abs(f) < 1e-9) | (th >= np.pi / 2 - 1e-3) | (th < 0)
    scale = np.where(thd > 1e-12, np.tan(np.clip(th, 0, np.pi / 2 - 1e-3)) / np.maximum(thd, 1e-12), 1.0)
    x = xd * scale[:, None]
    x[bad] = np.nan
    return x


def _undistort_grid(m: CameraModel, xd: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Undistort a 4-px grid with the model's own iteration, interpolate, refine per pixel;
    pixels where the iteration does not converge (outside the invertible region) get NaN."""
    H, W = m.height, m.width
    step = 4
    gv = np.unique(np.r_[np.arange(0, H, step), H - 1])
    gu = np.unique(np.r_[np.arange(0, W, step), W - 1])
    GU, GV = np.meshgrid(gu, gv)
    g = m.pixels_to_rays(np.stack([GU.ravel(), GV.ravel()], 1).astype(float))[:, :2].reshape(len(gv), len(gu), 2)
    iu = np.clip(np.searchsorted(gu, u, side="right") - 1, 0, len(gu) - 2)
    iv = np.clip(np.searchsorted(gv, v, side="right") - 1, 0, len(gv) - 2)
    fu = ((u - gu[iu]) / (gu[iu + 1] - gu[iu]))[:, None]
    fv = ((v - gv[iv]) / (gv[iv + 1] - gv[iv]))[:, None]
    x = (g[iv, iu] * (1 - fu) + g[iv, iu + 1] * fu) * (1 - fv) \
        + (g[iv + 1, iu] * (1 - fu) + g[iv + 1, iu + 1] * fu) * fv
    for _ in range(3):
        x = x - (m.distort(x) - xd)
    res = np.linalg.norm(m.distort(x) - xd, axis=1)
    slow = np.flatnonzero(~(res < 1e-8))
    for _ in range(40):  # strongly distorted corners converge slowly
        if slow.size == 0:
            break
        x[slow] = x[slow] - (m.distort(x[slow]) - xd[slow])
        res = np.linalg.norm(m.distort(x[slow]) - xd[slow], axis=1)
        slow = slow[~(res < 1e-8)]
    x[slow] = np.nan
    return x


def _clip_z(poly: np.ndarray, z_min: float) -> np.ndarray:
    """The part of a convex polygon (N,3) with z >= z_min (Sutherland-Hodgman, one plane)."""
    out = []
    n = poly.shape[0]
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ina, inb = a[2] >= z_min, b[2] >= z_min
        if ina:
            out.append(a)
        if ina != inb:
            out.append(a + (b - a) * ((z_min - a[2]) / (b[2] - a[2])))
    return np.array(out).reshape(-1, 3)


def interp_T(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose between T0 (s = 0) and T1 (s = 1): geodesic rotation, linear translation."""
    R = T0[:3, :3] @ so3_exp(s * so3_log(T0[:3, :3].T @ T1[:3, :3]))
    return make_T(R, (1 - s) * T0[:3, 3] + s * T1[:3, 3])


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


# ---------------------------------------------------------------------------------------------
# the world
# ---------------------------------------------------------------------------------------------
class BoardWorld:
    """Static rig + room + the board's trajectory for one scenario and seed."""

    def __init__(self, scenario: BoardScenario | None = None, rng: np.random.Generator | None = None,
                 full_size: bool = True):
        sc = load_board_scenario(scenario)
        self.scenario = sc
        self.rng = rng if rng is not None else np.random.default_rng(sc.seed)
        self.board = sc.board
        self.preset = sc.lidar.make_preset()
        self.cameras: dict[str, BoardSimCamera] = {}
        self._cam_specs: dict[str, CameraSpec] = {}
        self._full_fx: dict[str, float] = {}
        self._rmax: dict[str, float] = {}
        for c in sc.cameras:
            scale = float(sc.image_scale) * float(c.image_scale) * (1.0 if full_size else 0.5)
            m = c.model()
            if scale != 1.0:
                m = m.scaled(scale)
            T_cl = inv_T(c.T_lidar_camera())
            self.cameras[c.name] = BoardSimCamera(
                name=c.name, model=m, T_camera_lidar=T_cl, frame_id=f"{c.name}_optical_frame",
                encoding=c.encoding, time_offset_s=float(c.time_offset_s), rate_hz=float(c.rate_hz),
                phase_s=float(c.phase_s), image_topic=f"/{c.name}/image_raw",
                camera_info_topic=f"/{c.name}/camera_info")
            self._cam_specs[c.name] = c
            self._full_fx[c.name] = float(c.model().fx)
        self.ring_bias_m = sc.lidar.ring_bias_sigma_m * self.rng.standard_normal(self.preset.n_rings)
        self._tex = _texture(sc.scene.texture_seed)
        self._planes = self._scene_planes()
        self._distractor = self._make_distractor()
        self._bg_cache: dict = {}
        self._lidar_cache = None
        self.poses = self.sample_poses(self.rng)
        self._build_timeline(self.rng)

    # -- scene ---------------------------------------------------------------------------------
    def _scene_planes(self) -> list:
        """(normal n, offset c, tangent u, tangent v, lidar unit, tint bgr, shade) with n.x = c,
        normals pointing into the room."""
        s = self.scene = self.scenario.scene
        tint_rng = np.random.default_rng(s.texture_seed + 1)
        pl = [
            (np.array([0, 0, 1.0]), -s.lidar_height_m, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
             s.floor_lidar_unit),
            (np.array([-1.0, 0, 0]), -s.front_m, np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), s.wall_lidar_unit),
            (np.array([1.0, 0, 0]), -s.back_m, np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), s.wall_lidar_unit * 0.9),
            (np.array([0, -1.0, 0]), -s.left_m, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), s.wall_lidar_unit * 1.1),
            (np.array([0, 1.0, 0]), -s.right_m, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), s.wall_lidar_unit * 0.8),
        ]
        if s.ceiling_m > 0:
            pl.append((np.array([0, 0, -1.0]), -s.ceiling_m, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 0.1))
        out = []
        for k, (n, c, u, v, unit) in enumerate(pl):
            tint = tint_rng.uniform(0.6, 1.0, 3)
            shade = (0.55, 0.75, 0.65, 0.7, 0.6, 0.85)[k]
            out.append((n, float(c), u, v, float(unit), tint, shade))
        return out

    def _make_distractor(self):
        if not self.scene.distractor:
            return None
        r = np.random.default_rng(self.scene.texture_seed + 2)
        k = int(r.integers(1, 5))  # a wall
        n, c, u, v = self._planes[k][:4]
        p0 = n * c  # the plane's point nearest the origin (n . x = c, |n| = 1)
        along = float(r.uniform(-3.0, 3.0))
        height = float(r.uniform(-0.3, 0.8))
        centre = p0 + along * u + height * v
        return (k, centre, u, v, 0.2, 0.15)

    def _background_hits(self, dirs: np.ndarray):
        """Nearest room hit along unit/any rays from the origin: (range (N,), plane (N,),
        tex coords (N,2) metres)."""
        n_r = dirs.shape[0]
        best = np.full(n_r, np.inf)
        plane = np.full(n_r, -1, np.int16)
        for k, (n, c, *_rest) in enumerate(self._planes):
            den = dirs @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = c / den
            ok = (den < -1e-9) & (t > 0) & (t < best)
            best[ok] = t[ok]
            plane[ok] = k
        uv = np.zeros((n_r, 2))
        for k, (_n, _c, u, v, *_r) in enumerate(self._planes):
            m = plane == k
            if m.any():
                p = dirs[m] * best[m, None]
                uv[m, 0], uv[m, 1] = p @ u, p @ v
        return best, plane, uv

    def _distractor_mask(self, dirs: np.ndarray, rng_m: np.ndarray, plane: np.ndarray,
                         origin: np.ndarray | None = None) -> np.ndarray:
        if self._distractor is None:
            return np.zeros(dirs.shape[0], bool)
        k, centre, u, v, hu, hv = self._distractor
        m = plane == k
        out = np.zeros(dirs.shape[0], bool)
        if m.any():
            o = np.zeros(3) if origin is None else origin
            p = o + dirs[m] * rng_m[m, None] - centre
            out[m] = (np.abs(p @ u) <= hu) & (np.abs(p @ v) <= hv)
        return out

    # -- poses ---------------------------------------------------------------------------------
    def _ring_count(self, T_lb: np.ndarray) -> int:
        """Rings whose elevation crosses the board (sampled over its area)."""
        g = np.linspace(-0.5, 0.5, 9)
        gx, gy = np.meshgrid(g * self.board.size_m[0], g * self.board.size_m[1])
        pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1) @ T_lb[:3, :3].T + T_lb[:3, 3]
        el = np.rad2deg(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
        e = np.asarray(self.preset.elevations_deg)
        return int(np.sum((e > el.min() + 0.05) & (e < el.max() - 0.05)))

    def board_fully_in_view(self, cam: BoardSimCamera, T_lb: np.ndarray, margin: float = 0.0) -> bool:
        T_cb = cam.T_camera_lidar @ T_lb
        a, b = self.board.size_m[0] / 2, self.board.size_m[1] / 2
        s = np.linspace(-1, 1, 11)
        edge = np.concatenate([np.stack([s * a, -b + 0 * s], 1), np.stack([a + 0 * s, s * b], 1),
                               np.stack([s * a, b + 0 * s], 1), np.stack([-a + 0 * s, s * b], 1)])
        pts = np.concatenate([edge, np.zeros((edge.shape[0], 1))], 1) @ T_cb[:3, :3].T + T_cb[:3, 3]
        if np.any(pts[:, 2] < 0.3):
            return False
        if float(T_cb[:3, 2] @ T_cb[:3, 3]) >= 0:  # seen from behind
            return False
        m = cam.model
        xn = pts[:, :2] / pts[:, 2:3]
        # stay inside the well-behaved part of the distortion (monotonic radius)
        if cam.name not in self._rmax:
            r = pixel_rays_fast(m)
            self._rmax[cam.name] = float(np.nanmax(np.hypot(r[:, 0], r[:, 1])))
        if np.max(np.hypot(xn[:, 0], xn[:, 1])) > self._rmax[cam.name] * 1.05:
            return False
        uv, ok = m.project(pts)
        if not np.all(ok):
            return False
        mu, mv = margin * m.width, margin * m.height
        return bool(np.all((uv[:, 0] >= mu) & (uv[:, 0] <= m.width - 1 - mu)
                           & (uv[:, 1] >= mv) & (uv[:, 1] <= m.height - 1 - mv)))

    def sample_poses(self, rng: np.random.Generator) -> list:
        """Still board poses T_lidar_board, taking the cameras in turn as the one that must see
        the whole board (multi-camera rigs pointing apart each get poses)."""
        pz = self.scenario.poses
        names = list(self.cameras)
        out = []
        for i in range(pz.n_poses):
            cam = self.cameras[names[i % len(names)]]
            T = None
            for attempt in range(400):
                relax = attempt >= 200
                T = self._draw_pose(rng, cam, relax)
                if T is None:
                    continue
                if self._ring_count(T) < (2 if relax else pz.min_rings):
                    continue
                if self.board_fully_in_view(cam, T, 0.0 if relax else pz.image_margin):
                    break
            else:
                raise ValueError(f"could not place the board in view of camera {cam.name} and the LiDAR "
                                 f"(distance {pz.distance_m} m): check the camera mounting and intrinsics")
            out.append(T)
        return out

    def _draw_pose(self, rng: np.random.Generator, cam: BoardSimCamera, relax: bool):
        pz = self.scenario.poses
        m = cam.model
        T_lc = inv_T(cam.T_camera_lidar)
        # a direction inside the camera's image (central part)
        f = 0.8 if relax else 0.6
        u = rng.uniform(0.5 - f / 2, 0.5 + f / 2) * m.width
        v = rng.uniform(0.5 - f / 2, 0.5 + f / 2) * m.height
        with np.errstate(all="ignore"):
            ray_c = m.pixels_to_rays(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(ray_c)):
            return None
        ray_c /= np.linalg.norm(ray_c)
        ray_l = T_lc[:3, :3] @ ray_c
        lo, hi = pz.distance_m
        if pz.min_square_px > 0:
            hi = min(hi, max(lo, self._full_fx[cam.name] * self.board.square_m / pz.min_square_px))
        d_l = rng.uniform(lo, hi)
        # choose the range along the camera ray so that the LiDAR distance is d_l
        o = T_lc[:3, 3]
        bq = float(o @ ray_l)
        disc = bq * bq - (o @ o - d_l * d_l)
        if disc <= 0:
            return None
        s = -bq + np.sqrt(disc)
        centre = o + s * ray_l
        if centre[2] - (-self.scene.lidar_height_m) < pz.min_height_above_floor_m + 0.62 * max(self.board.size_m):
            return None
        # base orientation: board faces the rig midpoint, long side horizontal
        to_rig = 0.5 * o - centre
        z_b = to_rig / np.linalg.norm(to_rig)
        x_b = np.cross(np.array([0, 0, 1.0]), z_b)
        if np.linalg.norm(x_b) < 1e-3:
            return None
        x_b /= np.linalg.norm(x_b)
        y_b = np.cross(z_b, x_b)
        R0 = np.stack([x_b, y_b, z_b], 1)
        yaw = np.deg2rad(rng.uniform(*pz.yaw_deg))
        tilt = np.deg2rad(rng.uniform(*pz.tilt_deg))
        if rng.random() < pz.roll45_prob:
            roll = np.deg2rad(rng.choice([-1, 1]) * rng.uniform(35, 55))
        else:
            roll = np.deg2rad(rng.uniform(*pz.roll_deg))
        # yaw about the world vertical, tilt about the board's x, roll about the board's z
        R = so3_exp(np.array([0, 0, 1.0]) * yaw) @ R0 @ so3_exp(np.array([1.0, 0, 0]) * tilt) \
            @ so3_exp(np.array([0, 0, 1.0]) * roll)
        T = make_T(R, centre)
        # not through the floor
        corners = self.board.outline_board() @ R.T + centre
        if corners[:, 2].min() < -self.scene.lidar_height_m + pz.min_height_above_floor_m:
            return None
        return T

    # -- timeline ------------------------------------------------------------------------------
    def _build_timeline(self, rng: np.random.Generator) -> None:
        tl = self.scenario.timeline
        t = 0.0  # relative to start_s (avoids float loss at 1.7e9)
        self.still_intervals = []
        self.carries = []
        for i in range(len(self.poses)):
            st = float(rng.uniform(*tl.still_s))
            self.still_intervals.append((t, t + st))
            t += st
            if i + 1 < len(self.poses):
                ca = float(rng.uniform(*tl.carry_s))
                self.carries.append((t, t + ca))
                t += ca
        self.duration_s = t
        self.start_s = float(tl.start_s)

    def board_pose_at(self, t_rel: float) -> tuple[np.ndarray, int]:
        """(T_lidar_board, still pose index or -1 while carried) at time t_rel after start."""
        for i, (_a, b) in enumerate(self.still_intervals):
            if t_rel <= b:
                return self.poses[i], i
            if i < len(self.carries):
                c0, c1 = self.carries[i]
                if t_rel < c1:
                    s = _smoothstep((t_rel - c0) / (c1 - c0))
                    T = interp_T(self.poses[i], self.poses[i + 1], s)
                    T[2, 3] += self.scenario.timeline.lift_m * np.sin(np.pi * s)
                    return T, -1
        return self.poses[-1], len(self.poses) - 1

    def board_poses_exposed(self, name: str, t_capture_rel: float) -> list:
        """Board poses over camera ``name``'s exposure centred on t_capture_rel (one pose when the
        board stands still, five sub-exposure poses while it is carried)."""
        e = float(self._cam_specs[name].exposure_time_s)
        T, idx = self.board_pose_at(t_capture_rel)
        if e <= 0 or (idx >= 0 and self.still_over(t_capture_rel - e / 2, t_capture_rel + e / 2) == idx):
            return [T]
        return [self.board_pose_at(t_capture_rel + e * f)[0] for f in np.linspace(-0.5, 0.5, 5)]

    def still_over(self, t0_rel: float, t1_rel: float) -> int:
        """Index of the still interval containing [t0, t1], or -1."""
        for i, (a, b) in enumerate(self.still_intervals):
            if t0_rel >= a - 1e-9 and t1_rel <= b + 1e-9:
                return i
        return -1

    def sweep_starts(self) -> np.ndarray:
        p = self.preset.period_s
        n = int(np.floor((self.duration_s - p) / p + 1e-9)) + 1
        return np.arange(max(n, 0)) * p

    def camera_captures(self, name: str) -> np.ndarray:
        """True capture times (relative) of camera ``name``; its stamps add time_offset_s."""
        c = self.cameras[name]
        n = int(np.floor((self.duration_s - c.phase_s) * c.rate_hz + 1e-9)) + 1
        return c.phase_s + np.arange(max(n, 0)) / c.rate_hz

    # -- LiDAR ---------------------------------------------------------------------------------
    def _lidar_static(self):
        if self._lidar_cache is None:
            crop = tuple(self.scenario.lidar.azimuth_range_deg) or None
            dirs, ring, az, t = self.preset.ray_directions(crop)
            rng_bg, plane, uv = self._background_hits(dirs)
            tex = self._tex
            ts = tex.shape[0]
            iu = (np.floor(uv[:, 0] / 0.02).astype(np.int64)) % ts
            iv = (np.floor(uv[:, 1] / 0.02).astype(np.int64)) % ts
            base = np.array([p[4] for p in self._planes] + [0.0])[plane]
            unit = base * (0.7 + 0.6 * tex[iv, iu])
            # grazing incidence returns less
            nrm = np.array([p[0] for p in self._planes] + [np.zeros(3)])[plane]
            cosi = np.abs(np.sum(nrm * dirs, axis=1))
            unit = unit * (0.3 + 0.7 * cosi)
            unit[self._distractor_mask(dirs, rng_bg, plane)] = 0.99
            rng_bg[plane < 0] = np.inf
            el = np.arcsin(np.clip(dirs[:, 2], -1, 1))
            self._lidar_cache = {"dirs": dirs, "ring": ring, "az": az, "t": t, "el": el, "rng_bg": rng_bg,
                                 "unit_bg": unit}
        return self._lidar_cache

    def _footprint(self):
        """Sub-ray offsets (K,2) in half-divergence units and Gaussian weights (1/e^2 at the edge)."""
        gh, gv = np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 3))
        off = np.stack([gh.ravel(), gv.ravel()], 1)
        off = off[np.hypot(off[:, 0], off[:, 1]) <= 1.0 + 1e-9]
        w = np.exp(-2.0 * np.sum(off**2, 1))
        return off, w / w.sum()

    def lidar_sweep(self, t0_rel: float, rng: np.random.Generator,
                    T_lidar_board: np.ndarray | None = None) -> tuple[dict, dict]:
        """One sweep starting at t0_rel: (cloud dict on the preset's fields, info dict).

        ``info['label']`` per point: 0 background, 1 border, 2 checker, 3 mixed ghost between the
        board and what is behind it; ``info['T_lidar_board']`` the pose at the sweep start.
        With ``T_lidar_board`` the board stands still there (t0_rel is then unused)."""
        L = self._lidar_static()
        p = self.preset
        dirs, t_pt = L["dirs"], L["t"]
        n = dirs.shape[0]
        rng_true = L["rng_bg"].copy()
        unit = L["unit_bg"].copy()
        label = np.zeros(n, np.int8)  # 0 background, 1 border, 2 checker, 3 mixed ghost
        if T_lidar_board is not None:
            T0, idx0, moving = np.asarray(T_lidar_board, dtype=float), -1, False
        else:
            T0, idx0 = self.board_pose_at(t0_rel)
            _T1, idx1 = self.board_pose_at(t0_rel + p.period_s)
            moving = not (idx0 >= 0 and idx0 == idx1)
        if moving:
            nb = 20
            bins = np.minimum((t_pt / p.period_s * nb).astype(int), nb - 1)
            groups = [(np.flatnonzero(bins == b), self.board_pose_at(t0_rel + (b + 0.5) * p.period_s / nb)[0])
                      for b in range(nb)]
        else:
            groups = [(np.arange(n), T0)]
        off, wts = self._footprint()
        bw, bh = self.board.size_m[0] / 2, self.board.size_m[1] / 2
        cw, ch = self.board.checker_size_m[0] / 2, self.board.checker_size_m[1] / 2
        dsq = self.board.square_m
        hd, vd = p.divergence_h_rad / 2, p.divergence_v_rad / 2
        for idx, T in groups:
            if idx.size == 0:
                continue
            R, c = T[:3, :3], T[:3, 3]
            nrm = R[:, 2]
            d = dirs[idx]
            den = d @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (nrm @ c) / den
            b = (d * s[:, None] - c) @ R
            foot = s * max(hd, vd) / np.maximum(np.abs(den), 0.05) + 0.01
            cand = (s > 0) & np.isfinite(s) & (np.abs(b[:, 0]) < bw + foot) & (np.abs(b[:, 1]) < bh + foot)
            cand &= s < rng_true[idx]
            ci = idx[cand]
            if ci.size == 0:
                continue
            dc = dirs[ci]
            az = np.arctan2(dc[:, 1], dc[:, 0])
            el = np.arcsin(np.clip(dc[:, 2], -1, 1))
            eh = np.stack([-np.sin(az), np.cos(az), 0 * az], 1)
            ev = np.stack([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)], 1)
            sub = dc[:, None, :] + off[None, :, 0:1] * hd * eh[:, None, :] + off[None, :, 1:2] * vd * ev[:, None, :]
            sub /= np.linalg.norm(sub, axis=2, keepdims=True)
            sden = sub @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                ss = (nrm @ c) / sden
            sb = (sub * ss[..., None] - c) @ R
            on = (ss > 0) & (np.abs(sb[..., 0]) <= bw) & (np.abs(sb[..., 1]) <= bh)
            inch = on & (np.abs(sb[..., 0]) <= cw) & (np.abs(sb[..., 1]) <= ch)
            black = ((np.floor((sb[..., 0] + cw) / dsq) + np.floor((sb[..., 1] + ch) / dsq)) % 2) == 0
            cos_inc = np.abs(den[cand])
            if float(nrm @ c) < 0:  # the LiDAR sees the patterned face
                u_border = self.board.border_lidar_unit * (0.985 + 0.015 * cos_inc)  # retro: weak angle dependence
                u_chk = np.where(black, self.board.checker_black_lidar_unit, self.board.checker_white_lidar_unit)
                u_chk = u_chk * (0.4 + 0.6 * cos_inc[:, None])
            else:  # the plain back of the board
                u_border = np.full(ci.size, 0.2) * cos_inc
                u_chk = np.full(black.shape, 0.2) * cos_inc[:, None]
            w_border = np.sum(wts * (on & ~inch), axis=1)
            w_chk_u = np.sum(wts * inch * u_chk, axis=1)
            w_chk = np.sum(wts * inch, axis=1)
            w_on = w_border + w_chk
            w_bg = 1.0 - w_on
            r_bg = rng_true[ci]
            u_bg = unit[ci]
            u_bg = np.where(np.isfinite(r_bg), u_bg, 0.0)
            # footprint-averaged intensity of what the beam saw (unit scale)
            e_board = w_border * u_border + w_chk_u
            r_board = np.sum(wts * on * np.where(on, ss, 0.0), axis=1) / np.maximum(w_on, 1e-12)
            far = np.where(np.isfinite(r_bg), (r_board / np.where(np.isfinite(r_bg), r_bg, 1.0)) ** 2, 0.0)
            e_bg = w_bg * u_bg * far
            board_wins = (w_on > 0) & (e_board >= e_bg)
            mixed_i = e_board + w_bg * u_bg  # intensity of the blend
            rr = np.where(board_wins, r_board, r_bg)
            ui = np.where(board_wins, mixed_i, u_bg)
            lab = np.where(board_wins, np.where(w_border >= w_chk, 1, 2), 0).astype(np.int8)
            # mixed pixels: comparable energies from board and a surface well behind it
            ratio = e_bg / np.maximum(e_board, 1e-12)
            ghost = (w_on > 0.05) & (w_bg > 0.05) & (ratio > 0.3) & (ratio < 3.0) & np.isfinite(r_bg) \
                & ((r_bg - r_board) > 0.05) & (rng.random(ci.size) < self.scenario.lidar.mixed_pixel_prob)
            if ghost.any():
                wsum = e_board[ghost] + e_bg[ghost]
                rr[ghost] = (e_board[ghost] * r_board[ghost] + e_bg[ghost] * r_bg[ghost]) / wsum
                lab[ghost] = 3
            no_ret = (w_on > 0) & ~board_wins & ~np.isfinite(r_bg)
            rr[no_ret] = np.inf
            rng_true[ci] = rr
            unit[ci] = ui
            label[ci] = lab
        cloud = p.finish_sweep(dirs, L["ring"], t_pt, rng_true, unit, rng, ring_bias_m=self.ring_bias_m)
        kept = cloud.pop("_index")
        info = {"label": label[kept], "T_lidar_board": T0, "moving": moving, "pose_index": idx0 if not moving else -1}
        return cloud, info

    # -- cameras -------------------------------------------------------------------------------
    def _background(self, name: str):
        """Per-camera static background radiance (H,W,3 float32) and normalised ray grid."""
        if name in self._bg_cache:
            return self._bg_cache[name]
        cam = self.cameras[name]
        m = cam.model
        rays_c = pixel_rays_fast(m)  # (H*W, 3), z = 1
        T_lc = inv_T(cam.T_camera_lidar)
        d_l = rays_c @ T_lc[:3, :3].T
        d_l /= np.linalg.norm(d_l, axis=1, keepdims=True)
        o = T_lc[:3, 3]
        H, W = m.height, m.width
        n_r = d_l.shape[0]
        best = np.full(n_r, np.inf)
        plane = np.full(n_r, -1, np.int16)
        for k, (nn, c, *_r) in enumerate(self._planes):
            den = d_l @ nn
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (c - o @ nn) / den
            ok = (den < -1e-9) & (t > 0) & (t < best)
            best[ok] = t[ok]
            plane[ok] = k
        img = np.full((n_r, 3), 0.75, np.float32)  # open sky
        tex = self._tex
        tex.shape[0]
        for k, (_n, _c, u, v, _unit, tint, shade) in enumerate(self._planes):
            msk = plane == k
            if not msk.any():
                continue
            pnt = o + d_l[msk] * best[msk, None]
            tu = ((pnt @ u) / 0.01).astype(np.float32)
            tv = ((pnt @ v) / 0.01).astype(np.float32)
            val = _sample_wrap(tex, tu, tv)
            lum = shade * (0.45 + 0.55 * val)
            img[msk] = (lum[:, None] * tint[None, :]).astype(np.float32)
        if self._distractor is not None:
            dm = self._distractor_mask(d_l, best, plane, origin=o)
            img[dm] = np.array([0.2, 0.8, 0.9], np.float32)
        img = img.reshape(H, W, 3)
        spec = self._cam_specs[name]
        if self.cameras[name].encoding == "mono8":
            img = (img @ np.array([0.114, 0.587, 0.299], np.float32))[..., None]
        img = np.ascontiguousarray(img, dtype=np.float32)
        blurred = self._blur(img, spec.blur_sigma_px)
        xn = rays_c[:, :2].reshape(H, W, 2).astype(np.float32)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows/columns of a fisheye
            ranges = (np.nanmin(xn[..., 0], 0), np.nanmax(xn[..., 0], 0),
                      np.nanmin(xn[..., 1], 1), np.nanmax(xn[..., 1], 1))
        ranges = tuple(np.nan_to_num(r, nan=np.inf if k % 2 == 0 else -np.inf) for k, r in enumerate(ranges))
        self._bg_cache[name] = (img, blurred, xn, ranges)
        return self._bg_cache[name]

    @staticmethod
    def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
        if sigma <= 0:
            return img.copy()
        out = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
        return out.reshape(img.shape)

    def _board_box(self, name: str, corners_cam: np.ndarray):
        """Pixel box (v0, v1, u0, u1) that contains the board, or None."""
        m = self.cameras[name].model
        _img, _blur, _xn, (cx_lo, cx_hi, ry_lo, ry_hi) = self._background(name)
        H, W = m.height, m.width
        poly = _clip_z(corners_cam, 0.05)
        if poly.shape[0] >= 3:
            q = poly[:, :2] / poly[:, 2:3]
            lo, hi = q.min(0), q.max(0)
            cols = np.flatnonzero((cx_hi >= lo[0]) & (cx_lo <= hi[0]))
            rows = np.flatnonzero((ry_hi >= lo[1]) & (ry_lo <= hi[1]))
            if rows.size == 0 or cols.size == 0:
                return None
            return (max(rows[0] - 3, 0), min(rows[-1] + 4, H), max(cols[0] - 3, 0), min(cols[-1] + 4, W))
        return None

    def _board_face(self, xn: np.ndarray, R: np.ndarray, t: np.ndarray):
        """(alpha, radiance) of the board over a patch of normalised ray coordinates (h, w, 2)."""
        r = np.concatenate([xn.astype(np.float64), np.ones(xn.shape[:2] + (1,))], axis=2)
        nrm = R[:, 2]
        den = r @ nrm
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (nrm @ t) / den
        valid = np.isfinite(s) & (s > 0)
        s = np.where(valid, s, 0.0)
        bxy = (r * s[..., None] - t) @ R[:, :2]
        bx = np.where(valid, bxy[..., 0], 1e3).astype(np.float32)
        by = np.where(valid, bxy[..., 1], 1e3).astype(np.float32)
        # pixel footprint widths in board coordinates (root of summed squares: the same
        # variance as the pixel's parallelogram)
        gxu, gxv = np.gradient(bx, axis=1), np.gradient(bx, axis=0)
        gyu, gyv = np.gradient(by, axis=1), np.gradient(by, axis=0)
        wx = np.clip(np.sqrt(gxu**2 + gxv**2), 1e-6, 0.5)
        wy = np.clip(np.sqrt(gyu**2 + gyv**2), 1e-6, 0.5)
        bs = self.board
        bw, bh = bs.size_m[0] / 2, bs.size_m[1] / 2
        cw, ch = bs.checker_size_m[0] / 2, bs.checker_size_m[1] / 2
        d = bs.square_m
        alpha = _filt_box(bx, wx, bw) * _filt_box(by, wy, bh) * valid
        if float(nrm @ t) >= 0:  # the camera sees the back of the board
            face = np.full(bx.shape, bs.back_gray)
        else:
            inch = _filt_box(bx, wx, cw) * _filt_box(by, wy, ch)
            chk = _filt_square(bx + cw, wx, d) * _filt_square(by + ch, wy, d)  # +1 on black squares
            chk_val = 0.5 * (bs.white_gray + bs.black_gray) - 0.5 * (bs.white_gray - bs.black_gray) * chk
            face = bs.border_gray + inch * (chk_val - bs.border_gray)
        # simple shading: brighter when facing the camera
        face = face * (0.75 + 0.25 * float(abs(nrm @ (t / np.linalg.norm(t)))))
        return alpha.astype(np.float32), face.astype(np.float32)

    def render(self, name: str, T_lidar_board, rng: np.random.Generator) -> np.ndarray:
        """Image of camera ``name`` with the board at T_lidar_board (uint8, mono8 HxW or bgr8 HxWx3).

        ``T_lidar_board`` may be a list of poses over the exposure (motion blur: the composites
        are averaged). Only the board's pixel box (plus the blur margin) is composited and
        re-blurred; the rest is the cached blurred background. Fresh read noise on every call."""
        cam = self.cameras[name]
        spec = self._cam_specs[name]
        m = cam.model
        bg, bg_blur, xn, _ranges = self._background(name)
        H, W = m.height, m.width
        out = bg_blur.copy()
        poses = [np.asarray(T_lidar_board, float)] if np.ndim(T_lidar_board) == 2 else \
            [np.asarray(T, float) for T in T_lidar_board]
        Rts, boxes = [], []
        for T in poses:
            T_cb = cam.T_camera_lidar @ T
            R, t = T_cb[:3, :3], T_cb[:3, 3]
            bx = self._board_box(name, self.board.outline_board() @ R.T + t)
            if bx is not None:
                Rts.append((R, t))
                boxes.append(bx)
        if boxes:
            v0, v1 = min(b[0] for b in boxes), max(b[1] for b in boxes)
            u0, u1 = min(b[2] for b in boxes), max(b[3] for b in boxes)
            mg = int(np.ceil(4 * spec.blur_sigma_px)) + 1
            p0, p1, q0, q1 = max(v0 - mg, 0), min(v1 + mg, H), max(u0 - mg, 0), min(u1 + mg, W)
            base = bg[p0:p1, q0:q1]
            patch = np.zeros_like(base)
            for R, t in Rts:
                alpha, face = self._board_face(xn[p0:p1, q0:q1], R, t)
                a3 = alpha[..., None]
                patch += (1 - a3) * base + a3 * face[..., None]
            patch = (patch + base * (len(poses) - len(Rts))) / len(poses)
            patch = self._blur(np.ascontiguousarray(patch, dtype=np.float32), spec.blur_sigma_px)
            out[v0:v1, u0:u1] = patch[v0 - p0:v1 - p0, u0 - q0:u1 - q0]
        img = out[..., 0] if cam.encoding == "mono8" else out
        img = img * np.float32(255.0 * spec.exposure)
        if spec.noise_sigma_dn > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(spec.noise_sigma_dn)
        np.rint(img, out=img)
        np.clip(img, 0, 255, out=img)
        return img.astype(np.uint8)

    # -- truth ---------------------------------------------------------------------------------
    def truth(self) -> dict:
        return {n: c.T_camera_lidar.copy() for n, c in self.cameras.items()}

    def noise(self) -> dict:
        p = self.preset
        cams = {n: {"pixel_noise_sigma": float(s.noise_sigma_dn), "blur_sigma_px": float(s.blur_sigma_px),
                    "time_offset_s": float(s.time_offset_s), "rate_hz": float(s.rate_hz), "phase_s": float(s.phase_s),
                    "exposure_time_s": float(s.exposure_time_s)}
                for n, s in self._cam_specs.items()}
        return {
            "range_sigma_m": float(p.range_sigma_m),
            "dropout_prob": float(p.dropout_prob),
            "ring_bias_m": [float(v) for v in self.ring_bias_m],
            "intensity_sigma_unit": float(p.intensity_sigma_unit),
            "intensity_scale": p.intensity_scale,
            "intensity_threshold": float(p.intensity_threshold),
            "divergence_h_rad": float(p.divergence_h_rad),
            "divergence_v_rad": float(p.divergence_v_rad),
            "mixed_pixel_prob": float(self.scenario.lidar.mixed_pixel_prob),
            "pixel_noise_sigma": max(c["pixel_noise_sigma"] for c in cams.values()),
            "blur_sigma_px": max(c["blur_sigma_px"] for c in cams.values()),
            "cameras": cams,
        }


def _frame_images(world: BoardWorld, t_sweep_rel: float, rng: np.random.Generator):
    """For one sweep: per camera the capture nearest (by stamp) to the sweep middle, rendered.
    Returns (images {name: (stamp_abs, img)}, captures {name: t_capture_rel})."""
    images, caps = {}, {}
    mid = t_sweep_rel + 0.5 * world.preset.period_s
    for name, cam in world.cameras.items():
        tc = world.camera_captures(name)
        if tc.size == 0:
            continue
        k = int(np.argmin(np.abs(tc + cam.time_offset_s - mid)))
        Ts = world.board_poses_exposed(name, float(tc[k]))
        images[name] = (world.start_s + float(tc[k]) + cam.time_offset_s, world.render(name, Ts, rng))
        caps[name] = float(tc[k])
    return images, caps


def simulate_board(scenario: BoardScenario | None = None, rng: np.random.Generator | None = None,
                   full_size: bool = True, frames: str = "sampled") -> BoardSimRun:
    """Simulate a session in memory.

    ``frames='sampled'`` keeps per pose ``timeline.memory_still_frames`` still sweeps (spread
    over the still interval) and per carry ``timeline.memory_carry_frames`` moving ones;
    ``'all'`` keeps every sweep. Each frame carries one image per camera (the capture whose
    stamp is nearest the sweep middle). ``full_size=False`` renders at half resolution.
    """
    sc = load_board_scenario(scenario)
    rng = rng if rng is not None else np.random.default_rng(sc.seed)
    world = BoardWorld(sc, rng, full_size=full_size)
    starts = world.sweep_starts()
    per = world.preset.period_s
    if frames == "all":
        chosen = list(starts)
    elif frames == "sampled":
        chosen = []
        tl = sc.timeline
        for i, (a, b) in enumerate(world.still_intervals):
            cand = [t for t in starts if t >= a - 1e-9 and t + per <= b + 1e-9]
            if cand and tl.memory_still_frames > 0:
                pick = np.linspace(0, len(cand) - 1, min(tl.memory_still_frames, len(cand)) + 2)[1:-1]
                chosen += [cand[round(x)] for x in pick]
            if i < len(world.carries) and tl.memory_carry_frames > 0:
                c0, c1 = world.carries[i]
                cand = [t for t in starts if t > c0 and t + per < c1]
                if cand:
                    pick = np.linspace(0, len(cand) - 1, min(tl.memory_carry_frames, len(cand)) + 2)[1:-1]
                    chosen += [cand[round(x)] for x in pick]
        chosen = sorted(set(chosen))
    else:
        raise ValueError("frames must be 'sampled' or 'all'")
    out = []
    for t0 in chosen:
        cloud, info = world.lidar_sweep(float(t0), rng)
        images, caps = _frame_images(world, float(t0), rng)
        idx = world.still_over(float(t0), float(t0) + per)
        half = {n: 0.5 * world._cam_specs[n].exposure_time_s for n in caps}
        still = idx >= 0 and all(world.still_over(tc - half[n], tc + half[n]) == idx for n, tc in caps.items())
        T0 = info["T_lidar_board"]
        view = {n: world.board_fully_in_view(c, world.board_pose_at(caps[n])[0]) for n, c in world.cameras.items()
                if n in caps}
        out.append(BoardSimFrame(stamp_s=world.start_s + float(t0), still=bool(still), T_lidar_board=T0,
                                 cloud=cloud, images=images, pose_index=idx if still else -1, board_in_view=view))
    return BoardSimRun(lidar=world.preset, board=world.board, cameras=world.cameras, frames=out,
                       truth=world.truth(), noise=world.noise(), poses=list(world.poses), scenario=sc)


__all__ = ["ALL_FIELDS", "CAMERA_TYPES", "BoardScenario", "BoardSimCamera", "BoardSimFrame", "BoardSimRun",
           "BoardSpec", "BoardWorld", "CameraSpec", "LidarSpec", "PosesSpec", "SceneSpec", "TimelineSpec",
           "default_board_scenario", "interp_T", "load_board_scenario", "sample_board_family", "simulate_board"]
