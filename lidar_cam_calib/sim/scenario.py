"""Scenario description for the ``lrf`` simulator (2D laser scanner + depth camera on an AGV).

A :class:`Scenario` is a tree of small dataclasses; every sensor-model, noise, board-geometry,
mount, pose-generation, timeline and seed parameter lives here and can be set from YAML.
Unknown keys raise ``ValueError`` naming them (with their dotted path), so typos do not pass
silently. A YAML file only needs the keys it changes; everything else keeps the defaults below
(which follow paper 003: Pepperl+Fuchs R2000 laser, ZED2i-like stereo depth camera).

Units are in the names (``_m``, ``_deg``, ``_s``, ``_hz``, ``_px``). Angles in YAML are degrees.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Union, get_type_hints

import yaml


@dataclass
class BoardConfig:
    """Folded calibration board (paper 003, Fig. 3), all in the board frame.

    Board frame: origin at the bottom-centre of the base rectangle PBDQ, x to the right as seen
    by a viewer in front of the board, y up along the board, z out of the front face (towards the
    viewer). The base rectangle spans x in [-width/2, width/2], y in [0, height], z = 0.
    ``A``, ``B`` and ``D`` lie anywhere on the base (``a_xy_m``, ``b_xy_m``, ``d_xy_m``; empty
    ``b_xy_m`` / ``d_xy_m`` = the top-left / top-right corners), B left of D; the apex ``C``
    (``c_xyz_m``) sticks out of the base by ``c_xyz_m[2]``, above or below A.
    """

    width_m: float = 1.0
    height_m: float = 1.0
    a_xy_m: list = field(default_factory=lambda: [0.0, 0.0])
    b_xy_m: list = field(default_factory=list)
    d_xy_m: list = field(default_factory=list)
    c_xyz_m: list = field(default_factory=lambda: [0.0, 1.0, 0.6])
    # Optional rear stand panel (a second rectangle behind the board, leaning back); 0 disables.
    stand_depth_m: float = 0.0


@dataclass
class RoomConfig:
    """Axis-aligned room in the world frame (world: x, y horizontal, z up, floor at z = 0)."""

    size_m: list = field(default_factory=lambda: [8.0, 6.0, 3.0])
    center_xy_m: list = field(default_factory=lambda: [4.0, 0.0])


@dataclass
class LaserConfig:
    """2D laser range finder (defaults: Pepperl+Fuchs R2000).

    Beam k has angle ``angle_min_deg + k * resolution_deg`` measured counter-clockwise about the
    laser z axis from the laser x axis (ROS LaserScan convention). ``range_sigma_m`` defaults to
    12.5 mm, i.e. the datasheet's +/-25 mm read as 2 sigma.
    """

    angle_min_deg: float = -180.0
    fov_deg: float = 360.0
    resolution_deg: float = 0.042
    range_min_m: float = 0.1
    range_max_m: float = 30.0
    range_sigma_m: float = 0.0125
    dropout_fraction: float = 0.0
    frame_id: str = "laser"


@dataclass
class CameraConfig:
    """Stereo depth camera (ZED2i-like), left camera = depth/colour reference.

    Depth noise sigma = k * z^2 with k = sigma_disparity_px / (fx_stereo * baseline_m), where
    fx_stereo is the focal length at the resolution the stereo matching runs at
    (``stereo_width_px``), not at the published depth resolution: a camera that
    publishes a downscaled depth image is not noisier for it. With the defaults,
    sigma is 3.1 mm at 1 m and 28 mm at 3 m (ZED2i spec: < 1 % up to 3 m).
    ``invalid_value``: 'nan' or 0 for pixels without depth. ``fx_px`` > 0 sets the focal
    length directly (else from ``hfov_deg``); ``depth_sigma_k`` > 0 sets sigma_z = k z^2
    directly (a structured-light / ToF camera instead of the stereo model);
    ``depth_encoding`` '16UC1' rounds the simulated depth to whole millimetres.
    """

    width_px: int = 640
    height_px: int = 360
    hfov_deg: float = 100.0
    fx_px: float = 0.0
    depth_sigma_k: float = 0.0
    depth_encoding: str = "32FC1"
    distortion_model: str = ""
    D: list = field(default_factory=list)
    depth_min_m: float = 0.3
    depth_max_m: float = 20.0
    sigma_disparity_px: float = 0.1
    stereo_width_px: int = 640
    baseline_m: float = 0.12
    dropout_fraction: float = 0.0
    invalid_value: Any = "nan"
    render_color: bool = True
    right_camera: bool = True
    frame_id: str = "camera_depth_optical_frame"
    right_frame_id: str = "camera_right_depth_optical_frame"


@dataclass
class MountConfig:
    """Sensor mounts on the AGV base (x forward, y left, z up); rpy in degrees (ROS fixed axis).

    The camera's rpy is applied to a body-aligned frame; the optical rotation
    (z forward, x right, y down) is appended by the simulator.
    Defaults (paper Table 3): camera 128 mm in front of, 60 mm left of and 10 mm below the laser.
    """

    laser_xyz_m: list = field(default_factory=lambda: [0.10, 0.0, 0.65])
    laser_rpy_deg: list = field(default_factory=lambda: [0.5, -0.3, 0.2])
    camera_xyz_m: list = field(default_factory=lambda: [0.228, 0.060, 0.640])
    camera_rpy_deg: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    agv_frame_id: str = "base_link"
    world_frame_id: str = "map"


@dataclass
class PosesConfig:
    """Observation poses: the AGV stops at ``n_poses`` poses in front of the board.

    Relative to the board's nominal pose: distance along the board normal, lateral offset along
    the board's x axis, AGV yaw relative to "looking straight at the board". Samples are
    stratified (Latin hypercube) so a few poses already span the ranges. When ``replace_board``
    is true the board is re-placed (base height, tilt about its x axis, yaw) at every pose.
    Every pose must let both sensors see all three faces (resampled otherwise).
    """

    n_poses: int = 20
    distance_m: list = field(default_factory=lambda: [1.2, 3.0])
    lateral_m: list = field(default_factory=lambda: [-0.8, 0.8])
    yaw_deg: list = field(default_factory=lambda: [-30.0, 30.0])
    board_position_m: list = field(default_factory=lambda: [6.5, 0.0])
    board_yaw_deg: float = 0.0
    board_base_height_m: float = 0.05
    board_tilt_deg: float = 0.0
    replace_board: bool = True
    board_base_height_range_m: list = field(default_factory=lambda: [0.0, 0.15])
    board_tilt_range_deg: list = field(default_factory=lambda: [-10.0, 10.0])
    board_yaw_range_deg: list = field(default_factory=lambda: [-15.0, 15.0])
    min_laser_points_per_face: int = 10
    min_pixels_per_face: int = 200
    max_attempts: int = 500


@dataclass
class TimelineConfig:
    """Bag timeline: stand still ``static_s`` at each pose, then drive ``drive_s`` to the next.

    Scans at ``scan_hz`` and depth (+ right depth, colour, camera_info) at ``depth_hz``, all
    re-noised per frame; while driving, the AGV (and a re-placed board) pose is interpolated.
    ``start_s`` is the first stamp (seconds since the epoch)."""

    start_s: float = 1700000000.0
    static_s: float = 1.5
    drive_s: float = 1.0
    scan_hz: float = 10.0
    depth_hz: float = 5.0
    write_color: bool = True
    write_right: bool = True
    depth_offset_s: float = 0.013  # depth frames are stamped this long after a scan slot
    stamp_jitter_s: float = 0.0  # uniform +/- jitter on every stamp (clock noise)
    compress: bool = True  # zstd MCAP chunk compression (rosbags CompressionMode.STORAGE)


@dataclass
class Scenario:
    """Complete description of one simulated ``lrf`` calibration session."""

    name: str = "lrf_default"
    seed: int = 0
    board: BoardConfig = field(default_factory=BoardConfig)
    room: RoomConfig = field(default_factory=RoomConfig)
    laser: LaserConfig = field(default_factory=LaserConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mount: MountConfig = field(default_factory=MountConfig)
    poses: PosesConfig = field(default_factory=PosesConfig)
    timeline: TimelineConfig = field(default_factory=TimelineConfig)

    def to_dict(self) -> dict:
        """Plain nested dict (YAML-safe)."""
        return dataclasses.asdict(self)


def build_dataclass(cls, data: Mapping[str, Any], path: str = ""):
    """Instantiate dataclass ``cls`` from ``data`` (defaults for missing keys), nested
    dataclasses recursively; ``path`` names the section in messages. Every simulator's scenario
    loader uses it. Raises ValueError naming unknown keys and wrongly typed values."""
    if not isinstance(data, Mapping):
        raise ValueError(f"scenario section '{path or '<root>'}' must be a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = f" in section '{path}'" if path else ""
        raise ValueError(f"unknown scenario key(s){where}: "
                         + ", ".join(f"{path + '.' if path else ''}{k}" for k in unknown))
    hints = get_type_hints(cls)
    kwargs = {}
    for key, value in data.items():
        typ = hints[key]
        sub = f"{path}.{key}" if path else key
        if dataclasses.is_dataclass(typ):
            kwargs[key] = build_dataclass(typ, value or {}, sub)
        elif typ is float:
            kwargs[key] = float(value)
        elif typ is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(f"scenario key '{sub}' must be an integer, got {value}")
            kwargs[key] = int(value)
        elif typ is bool:
            if not isinstance(value, bool):
                raise ValueError(f"scenario key '{sub}' must be true/false, got {value!r}")
            kwargs[key] = value
        elif typ in (list, tuple):
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"scenario key '{sub}' must be a list, got {value!r}")
            kwargs[key] = typ(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def load_scenario(path_or_dict: Union[str, Path, Mapping[str, Any], Scenario, None]) -> Scenario:
    """Load a :class:`Scenario` from a YAML file path, a dict, or pass a Scenario through.

    ``None`` gives :func:`default_scenario`. Raises ``ValueError`` on unknown keys.
    """
    if path_or_dict is None:
        return default_scenario()
    if isinstance(path_or_dict, Scenario):
        return path_or_dict
    if isinstance(path_or_dict, (str, Path)):
        with open(path_or_dict, "r", encoding="utf-8") as fh:
            data = yaml.safe_load(fh) or {}
    else:
        data = dict(path_or_dict)
    sc = build_dataclass(Scenario, data)
    _validate(sc)
    return sc


def _validate(sc: Scenario) -> None:
    if sc.poses.n_poses < 1:
        raise ValueError("poses.n_poses must be >= 1")
    if len(sc.board.a_xy_m) != 2 or len(sc.board.c_xyz_m) != 3:
        raise ValueError("board.a_xy_m needs 2 values and board.c_xyz_m 3 values")
    for k in ("b_xy_m", "d_xy_m"):
        if len(getattr(sc.board, k)) not in (0, 2):
            raise ValueError(f"board.{k} needs 2 values (or none: the top corner)")
    if sc.camera.depth_encoding not in ("32FC1", "16UC1"):
        raise ValueError("camera.depth_encoding must be '32FC1' or '16UC1'")
    if sc.board.c_xyz_m[2] <= 0:
        raise ValueError("board.c_xyz_m[2] (apex protrusion) must be > 0")
    if sc.laser.resolution_deg <= 0 or sc.laser.fov_deg <= 0:
        raise ValueError("laser.resolution_deg and laser.fov_deg must be > 0")
    for name in ("distance_m", "lateral_m", "yaw_deg", "board_base_height_range_m",
                 "board_tilt_range_deg", "board_yaw_range_deg"):
        v = getattr(sc.poses, name)
        if len(v) != 2 or v[0] > v[1]:
            raise ValueError(f"poses.{name} must be [min, max]")
    iv = sc.camera.invalid_value
    if not (str(iv).lower() == "nan" or (not isinstance(iv, bool) and iv == 0)):
        raise ValueError("camera.invalid_value must be 'nan' or 0")


def default_scenario() -> Scenario:
    """Paper-like defaults: R2000 noise, ZED2i-like camera, 20 observation poses."""
    return Scenario()
