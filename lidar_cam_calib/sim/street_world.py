"""Urban street driven by a car: spinning LiDAR + camera simulator for the ``targetless`` method.

The world is built from analytic primitives (ROS-free, numpy only, cv2 for image warps):

* ground plane ``z = 0`` (asphalt with lane markings, paved sidewalks, gravel behind them),
* oriented boxes (building blocks, parked and moving cars, benches, kiosks, sign plates, lamp arms),
* vertical capped cylinders (street-light poles, sign posts, tree trunks, bins, bollards, pedestrians),
* vertical ellipsoids (tree crowns, pedestrians' heads).

The street centreline is an arc of constant curvature (``layout.curvature_per_m``, 0 = straight)
starting at the world origin along +x; street coordinates are ``s`` (arc length along the
centreline) and ``d`` (lateral offset, positive to the left). World frame: x, y horizontal, z up.
Traffic is right-handed: the ego car drives towards +s in a lane at ``d < 0``.

Sensors:

* LiDAR: a :class:`lidar_cam_calib.sim.lidar.LidarPreset` ray pattern; every ray is cast from the
  ego pose *at its own firing time* (rolling sweep), so a moving car bends the cloud. The cloud is
  expressed in the LiDAR frame at the time each point was measured (not motion-compensated),
  exactly as a driver publishes it. Moving objects are placed at their pose at the middle of each
  1/72 of the sweep (<= 1.4 ms, i.e. <= 2 cm at 50 km/h).
* Camera: global shutter at the true exposure time, pinhole + ROS distortion model; rendered by
  per-primitive z-buffering on an ideal pinhole image which is then warped into the distorted
  image. Textures are procedural functions of surface coordinates (multi-scale value noise,
  bricks and windows on facades, road markings, bark, foliage), mip-faded by the pixel footprint
  so they stay stable from frame to frame (SIFT finds thousands of features per image).

Clocks: the *LiDAR clock* is the true time. Sweep ``j`` starts at ``start_stamp_s + j / rate``
(its stamp; per-point ``time`` is relative to it). Image ``k`` is exposed at true time
``start_stamp_s + camera_phase_s + k / camera.rate_hz`` and stamped on the camera clock, i.e. with
``time_offset_s`` added (``time_offset_s`` = camera clock minus LiDAR clock; no hardware trigger).

Entry points: :func:`default_street_scenario`, :func:`load_street_scenario`,
:func:`sample_street_family`, :func:`simulate_drive` (everything in memory) and
:func:`iter_drive` (the same frames streamed in stamp order, used by the bag writer).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.errors import ConfigError
from lidar_cam_calib.core.geometry import R_BODY_OPTICAL, R_from_rpy, inv_T, make_T

# ----------------------------------------------------------------------------------------------
# scenario
# ----------------------------------------------------------------------------------------------


@dataclass
class StreetLayout:
    """Street geometry and static object densities (the layout itself is drawn from ``seed``)."""

    curvature_per_m: float = 0.0         # 1 / radius of the centreline arc (0: straight street)
    road_width_m: float = 11.0           # kerb to kerb
    lane_width_m: float = 3.3
    sidewalk_width_m: float = 3.5
    setback_m: list = field(default_factory=lambda: [0.0, 2.5])       # facade behind the sidewalk
    building_length_m: list = field(default_factory=lambda: [8.0, 28.0])
    building_height_m: list = field(default_factory=lambda: [7.0, 24.0])
    building_gap_prob: float = 0.15
    light_spacing_m: float = 24.0        # street-light poles per side (0: none)
    tree_spacing_m: float = 14.0         # trees per side (0: none)
    tree_prob: float = 0.7               # chance a tree slot holds a tree
    signs_per_100m: float = 5.0
    furniture_per_100m: float = 8.0
    parked_cars_per_100m: float = 6.0


@dataclass
class StreetTraffic:
    """Moving cars (both directions) and pedestrians on the sidewalks."""

    cars_per_100m: float = 2.0
    car_speed_kmh: list = field(default_factory=lambda: [15.0, 45.0])
    pedestrians_per_100m: float = 5.0
    pedestrian_speed_mps: list = field(default_factory=lambda: [0.7, 1.6])


@dataclass
class StreetLidar:
    """Which spinning LiDAR and how its measurements are degraded (-1: the preset's value)."""

    preset: str = "hdl64"
    column_stride: int = 1               # keep every n-th firing column (smaller demo bags)
    range_sigma_m: float = -1.0
    dropout_prob: float = -1.0
    crown_pass_prob: float = 0.35        # LiDAR rays passing through a tree crown's foliage
    crown_depth_m: float = 0.5           # returns scatter this deep into a crown
    mixed_edge_returns: bool = True      # beams straddling a depth edge return in between
    # the reflectance texture a LiDAR footprint sees and a camera pixel averages away (asphalt grain,
    # leaves, weathering): each return's reflectance times exp(N(0, s^2) - s^2 / 2). 0: uniform surfaces.
    # Measured on KITTI's HDL-64E (2011_09_26): 12 % of neighbouring road returns on a ring differ by more
    # than a quarter of the sweep's 95th intensity percentile, which iid texture gives at s ~ 0.3
    intensity_texture: float = 0.0
    paint_reflectivity: float = 0.55     # LiDAR reflectance of road paint (new, beaded ~0.6; worn ~0.25)


@dataclass
class StreetCamera:
    """Camera intrinsics (OpenCV/ROS conventions) and image formation."""

    width_px: int = 1288
    height_px: int = 964
    fx_px: float = 920.0
    fy_px: float = 920.0
    cx_px: float = 643.5
    cy_px: float = 481.5
    distortion_model: str = "plumb_bob"
    D: list = field(default_factory=lambda: [-0.12, 0.05, 0.0005, -0.0003, 0.0])
    rate_hz: float = 10.0
    noise_sigma: float = 2.0             # grey levels
    blur_sigma_px: float = 0.6
    mono: bool = False                   # mono8 instead of bgr8


@dataclass
class StreetMount:
    """Sensor poses on the car. Car frame: x forward, y left, z up, origin on the ground.

    rpy in degrees, R = Rz(yaw) Ry(pitch) Rx(roll); the camera's rpy rotates its *body* frame
    (x = viewing direction), pitch > 0 looks down; yaw may be anything (side/rear cameras)."""

    lidar_xyz_m: list = field(default_factory=lambda: [0.2, 0.0, 1.85])
    lidar_rpy_deg: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    camera_xyz_m: list = field(default_factory=lambda: [0.6, 0.1, 1.6])
    camera_rpy_deg: list = field(default_factory=lambda: [0.0, 4.0, 0.0])


@dataclass
class StreetMotion:
    """Ego speed profile and lane keeping."""

    speed_kmh: float = 18.0
    speed_amplitude_kmh: float = 4.0     # sinusoidal speed variation
    speed_period_s: float = 9.0
    lane_offset_m: float = -1.65         # centre of the ego lane (d < 0: right-hand traffic)
    weave_amplitude_m: float = 0.4
    weave_wavelength_m: float = 80.0
    body_motion_scale: float = 1.0       # suspension pitch/roll/heave (accel, cornering, bumps); 0: planar


@dataclass
class StreetTiming:
    duration_s: float = 8.0
    start_stamp_s: float = 1700000000.0
    time_offset_s: float = 0.025         # camera clock minus LiDAR clock
    camera_phase_s: float = 0.037        # first exposure after the first sweep start (true time)


@dataclass
class StreetScenario:
    """One simulated drive: street family parameters, sensors, motion, clocks and the seed."""

    name: str = "targetless_default"
    seed: int = 0
    sun_azimuth_deg: float = 35.0
    sun_elevation_deg: float = 45.0
    layout: StreetLayout = field(default_factory=StreetLayout)
    traffic: StreetTraffic = field(default_factory=StreetTraffic)
    lidar: StreetLidar = field(default_factory=StreetLidar)
    camera: StreetCamera = field(default_factory=StreetCamera)
    mount: StreetMount = field(default_factory=StreetMount)
    motion: StreetMotion = field(default_factory=StreetMotion)
    timing: StreetTiming = field(default_factory=StreetTiming)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def speed_set(self) -> str:
        """Paper 001 Table 1: 'slow' for 5-30 km/h, 'fast' above 30 km/h (by the mean speed)."""
        return "fast" if self.motion.speed_kmh > 30.0 else "slow"


def _validate(sc: StreetScenario) -> None:
    from lidar_cam_calib.sim.lidar import PRESETS

    if sc.lidar.preset not in PRESETS:
        raise ConfigError(f"lidar.preset {sc.lidar.preset!r} is unknown; known: {', '.join(PRESETS)}")
    if sc.lidar.column_stride < 1:
        raise ConfigError(f"lidar.column_stride must be >= 1, got {sc.lidar.column_stride}")
    if not (0.0 <= sc.lidar.intensity_texture <= 2.0):
        raise ConfigError(f"lidar.intensity_texture must be in [0, 2], got {sc.lidar.intensity_texture}")
    if not (0.0 <= sc.lidar.paint_reflectivity <= 1.0):
        raise ConfigError(f"lidar.paint_reflectivity must be in [0, 1], got {sc.lidar.paint_reflectivity}")
    c = sc.camera
    if c.width_px < 16 or c.height_px < 16 or c.fx_px <= 0 or c.fy_px <= 0:
        raise ConfigError(f"camera needs width/height >= 16 px and positive focal lengths, got "
                          f"{c.width_px}x{c.height_px}, fx={c.fx_px}, fy={c.fy_px}")
    if c.rate_hz <= 0:
        raise ConfigError(f"camera.rate_hz must be > 0, got {c.rate_hz}")
    CameraModel.from_K(c.width_px, c.height_px, c.fx_px, c.fy_px, c.cx_px, c.cy_px, c.D,
                       c.distortion_model)
    if sc.timing.duration_s <= 0:
        raise ConfigError(f"timing.duration_s must be > 0, got {sc.timing.duration_s}")
    if sc.motion.speed_kmh < 0 or sc.motion.speed_amplitude_kmh < 0:
        raise ConfigError("motion.speed_kmh and motion.speed_amplitude_kmh must be >= 0")
    if sc.motion.speed_period_s <= 0 or sc.motion.weave_wavelength_m <= 0:
        raise ConfigError("motion.speed_period_s and motion.weave_wavelength_m must be > 0")
    L = sc.layout
    if L.road_width_m < 2 * L.lane_width_m or L.sidewalk_width_m < 1.5:
        raise ConfigError("layout.road_width_m must hold two lanes and sidewalk_width_m be >= 1.5 m")
    if abs(L.curvature_per_m) > 1.0 / 60.0:
        raise ConfigError(f"layout.curvature_per_m {L.curvature_per_m} is too sharp (|k| <= 1/60 m)")
    for name in ("setback_m", "building_length_m", "building_height_m"):
        v = getattr(L, name)
        if len(v) != 2 or v[0] > v[1] or v[0] < 0:
            raise ConfigError(f"layout.{name} must be [min, max] with 0 <= min <= max, got {v}")
    if len(L.building_length_m) == 2 and L.building_length_m[0] < 2.0:
        raise ConfigError("layout.building_length_m minimum must be >= 2 m")


def load_street_scenario(path_or_dict: str | Path | Mapping[str, Any] | StreetScenario | None
                         ) -> StreetScenario:
    """A :class:`StreetScenario` from a YAML path, a (partial) dict, or passed through.

    Missing keys keep their defaults; unknown keys raise ConfigError naming them."""
    from .scenario import build_dataclass

    if path_or_dict is None:
        sc = default_street_scenario()
    elif isinstance(path_or_dict, StreetScenario):
        sc = path_or_dict
    else:
        if isinstance(path_or_dict, (str, Path)):
            try:
                with open(path_or_dict, encoding="utf-8") as fh:
                    data = yaml.safe_load(fh) or {}
            except OSError as exc:
                raise ConfigError(f"cannot read street scenario {path_or_dict}: {exc}") from exc
        else:
            data = dict(path_or_dict)
        try:
            sc = build_dataclass(StreetScenario, data)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
    _validate(sc)
    return sc


def default_street_scenario() -> StreetScenario:
    """Paper-like: HDL-64E, 1288x964 camera looking forward, 18 km/h (slow set), 8 s."""
    return StreetScenario()


def _lens_unfolded(c, margin: float = 1.05, min_slope: float = 0.3) -> bool:
    """True when the radial distortion of camera ``c`` maps the undistorted radius monotonically (slope
    above ``min_slope``) out to ``margin`` times the image corner's distorted radius: every pixel then has
    one ray, as with a real lens (a wide field with a strong negative k1 and a small k2 folds over)."""
    k1, k2 = float(c.D[0]), float(c.D[1])
    xs = max(c.cx_px, c.width_px - 1 - c.cx_px) / c.fx_px
    ys = max(c.cy_px, c.height_px - 1 - c.cy_px) / c.fy_px
    rd = margin * float(np.hypot(xs, ys))
    r = np.linspace(0.0, 4.0, 8001)
    d = r * (1 + k1 * r ** 2 + k2 * r ** 4)
    slope = 1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4
    reach = np.nonzero(d >= rd)[0]
    return reach.size > 0 and bool(np.all(slope[:reach[0] + 1] > min_slope))


def sample_street_family(seed: int, speed: str = "slow") -> StreetScenario:
    """One member of the scenario family, drawn from ``seed``.

    Draws the street (curvature, widths, building sizes, landmark and traffic densities), the
    LiDAR preset, camera intrinsics and distortion, the mounting (camera yaw anywhere around the
    car in 40 % of the draws), the speed profile (``speed``: 'slow' 5-30 km/h, 'fast' 30-80
    km/h), the clock offset and the sun. The layout itself is then drawn from the same seed."""
    if speed not in ("slow", "fast"):
        raise ConfigError(f"speed must be 'slow' or 'fast', got {speed!r}")
    rng = np.random.default_rng([int(seed), 9001, 0 if speed == "slow" else 1])
    sc = StreetScenario(name=f"targetless_family_{speed}_{int(seed)}", seed=int(seed))
    u = rng.uniform
    L = sc.layout
    L.curvature_per_m = float(0.0 if rng.random() < 0.35 else u(-1 / 150, 1 / 150))
    L.lane_width_m = float(u(3.0, 3.6))
    L.road_width_m = float(2 * L.lane_width_m + (u(4.4, 7.0) if rng.random() < 0.7 else u(0.6, 3.0)))
    L.sidewalk_width_m = float(u(2.8, 5.0))
    L.setback_m = [0.0, float(u(0.5, 5.0))]
    lo = float(u(6.0, 12.0))
    L.building_length_m = [lo, float(lo + u(8.0, 25.0))]
    hlo = float(u(5.0, 10.0))
    L.building_height_m = [hlo, float(hlo + u(4.0, 22.0))]
    L.building_gap_prob = float(u(0.05, 0.35))
    L.light_spacing_m = float(u(18.0, 40.0))
    L.tree_spacing_m = float(0.0 if rng.random() < 0.15 else u(9.0, 25.0))
    L.tree_prob = float(u(0.4, 0.95))
    L.signs_per_100m = float(u(1.0, 10.0))
    L.furniture_per_100m = float(u(2.0, 15.0))
    L.parked_cars_per_100m = float(u(0.0, 12.0))
    T = sc.traffic
    T.cars_per_100m = float(u(0.0, 4.0))
    T.pedestrians_per_100m = float(u(0.0, 10.0))
    lid = sc.lidar
    lid.preset = str(rng.choice(["hdl64", "hdl64", "vlp32", "vlp16", "os1_64"]))
    c = sc.camera
    scale = float(u(0.9, 1.1))
    hfov = np.radians(u(55.0, 85.0))
    c.fx_px = float(0.5 * c.width_px / np.tan(hfov / 2))
    c.fy_px = float(c.fx_px * u(0.995, 1.005))
    c.cx_px = float((c.width_px - 1) / 2 + u(-0.03, 0.03) * c.width_px)
    c.cy_px = float((c.height_px - 1) / 2 + u(-0.03, 0.03) * c.height_px)
    c.D = [float(u(-0.2, 0.02)) * scale, float(u(0.0, 0.06)), float(u(-1e-3, 1e-3)),
           float(u(-1e-3, 1e-3)), 0.0]
    for _ in range(30):  # a real lens: weaken a barrel distortion that would fold over inside the image
        if _lens_unfolded(c):
            break
        c.D[0] *= 0.85
    c.rate_hz = float(rng.choice([10.0, 10.0, 15.0, 20.0]))
    c.noise_sigma = float(u(1.0, 3.5))
    m = sc.mount
    m.lidar_xyz_m = [float(u(-0.5, 0.8)), float(u(-0.3, 0.3)), float(u(1.7, 2.1))]
    m.lidar_rpy_deg = [float(u(-2, 2)), float(u(-2, 2)), float(u(-5, 5))]
    yaw = float(u(-180.0, 180.0)) if rng.random() < 0.4 else float(u(-20.0, 20.0))
    m.camera_xyz_m = [float(m.lidar_xyz_m[0] + u(-1.0, 1.0)), float(u(-0.8, 0.8)), float(u(1.3, 1.9))]
    m.camera_rpy_deg = [float(u(-3, 3)), float(u(-4, 10)), yaw]
    mo = sc.motion
    if speed == "slow":
        mo.speed_kmh = float(u(8.0, 27.0))
        amp_max = min(mo.speed_kmh - 5.0, 30.0 - mo.speed_kmh)
    else:
        mo.speed_kmh = float(u(35.0, 75.0))
        amp_max = min(mo.speed_kmh - 31.0, 80.0 - mo.speed_kmh)
    mo.speed_amplitude_kmh = float(u(0.0, max(amp_max, 0.0)))
    mo.speed_period_s = float(u(5.0, 15.0))
    mo.lane_offset_m = float(-L.lane_width_m / 2 + u(-0.2, 0.2))
    mo.weave_amplitude_m = float(u(0.0, 0.4))
    mo.weave_wavelength_m = float(u(40.0, 150.0))
    mo.body_motion_scale = float(u(0.3, 1.5))
    tm = sc.timing
    tm.time_offset_s = float(u(-0.1, 0.1))
    tm.camera_phase_s = float(u(0.0, 1.0 / c.rate_hz))
    sc.sun_azimuth_deg = float(u(-180, 180))
    sc.sun_elevation_deg = float(u(25, 70))
    # drawn from a stream of their own, so that adding them left every other draw of a seed as it was
    r2 = np.random.default_rng([int(seed), 9002, 0 if speed == "slow" else 1])
    lid.intensity_texture = float(r2.uniform(0.0, 0.4))
    lid.paint_reflectivity = float(r2.uniform(0.25, 0.6))
    _validate(sc)
    return sc


# ----------------------------------------------------------------------------------------------
# street geometry and ego trajectory
# ----------------------------------------------------------------------------------------------
class StreetFrame:
    """Street coordinates (s along the centreline arc, d to the left) <-> world x, y."""

    def __init__(self, curvature_per_m: float):
        self.k = float(curvature_per_m)
        self.straight = abs(self.k) < 1e-7

    def heading(self, s):
        return self.k * np.asarray(s, dtype=float)

    def to_world(self, s, d):
        s = np.asarray(s, dtype=float)
        d = np.asarray(d, dtype=float)
        if self.straight:
            return s + 0.0 * d, d + 0.0 * s
        th = self.k * s
        r = 1.0 / self.k - d
        return r * np.sin(th), 1.0 / self.k - r * np.cos(th)

    def from_world(self, x, y):
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if self.straight:
            return x.copy(), y.copy()
        sg = 1.0 if self.k > 0 else -1.0
        qx, qy = x, y - 1.0 / self.k
        th = np.arctan2(sg * qx, -sg * qy)
        rho = np.hypot(qx, qy)
        return th / self.k, 1.0 / self.k - sg * rho


def _R_rpy(roll, pitch, yaw):
    """Rz(yaw) Ry(pitch) Rx(roll) for arrays of angles: shape (..., 3, 3)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.empty(np.shape(roll) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


class EgoTrajectory:
    """Ego-car pose vs time (dense 2 ms grid, linear interpolation).

    The car follows its lane (plus a slow weave) with the speed profile; its body pitches with
    the longitudinal acceleration (~0.35 deg per m/s^2, nose up when speeding up), rolls with the
    lateral one (~0.45 deg per m/s^2) and both pitch, roll and heave over road bumps (~0.2 deg,
    ~1 cm), all scaled by ``motion.body_motion_scale``.

    ``T_world_lidar(t)`` takes LiDAR-clock stamps (absolute seconds) like the sweeps; it returns
    a 4x4 for a scalar and (N,4,4) for an array."""

    def __init__(self, sc: StreetScenario, street: StreetFrame, s0_m: float, T_car_lidar: np.ndarray,
                 rng: np.random.Generator):
        mo = sc.motion
        self.start_s = float(sc.timing.start_stamp_s)
        self.T_car_lidar = np.asarray(T_car_lidar, dtype=float)
        dur = float(sc.timing.duration_s) + 0.5
        dt = 0.002
        t = np.arange(0.0, dur + dt, dt)
        ph = rng.uniform(0, 2 * np.pi, 2)
        v = (mo.speed_kmh + mo.speed_amplitude_kmh * np.sin(2 * np.pi * t / mo.speed_period_s + ph[0])) / 3.6
        v = np.maximum(v, 0.0)
        s = np.empty_like(t)
        s[0] = s0_m
        k = street.k
        amp, lam = mo.weave_amplitude_m, mo.weave_wavelength_m
        for i in range(1, t.size):  # integrate ds/dt = v / |dp/ds| (offset lane + weave)
            sp = s[i - 1]
            d = mo.lane_offset_m + amp * np.sin(2 * np.pi * sp / lam + ph[1])
            dd = amp * 2 * np.pi / lam * np.cos(2 * np.pi * sp / lam + ph[1])
            s[i] = sp + dt * v[i - 1] / np.hypot(1.0 - k * d, dd)
        d = mo.lane_offset_m + amp * np.sin(2 * np.pi * s / lam + ph[1])
        x, y = street.to_world(s, d)
        dd_ds = amp * 2 * np.pi / lam * np.cos(2 * np.pi * s / lam + ph[1])
        yaw = street.heading(s) + np.arctan2(dd_ds, 1.0 - k * d)
        yaw = np.unwrap(yaw)
        bm = float(mo.body_motion_scale)
        path = np.concatenate([[0.0], np.cumsum(v[:-1] * dt)])
        acc = np.gradient(v, dt)
        lat = v * np.gradient(yaw, dt)
        bph = rng.uniform(0, 2 * np.pi, 4)
        bl = rng.uniform(6.0, 20.0, 2)
        pitch = bm * (-0.006 * acc + 0.0025 * (np.sin(2 * np.pi * path / bl[0] + bph[0])
                                               + 0.5 * np.sin(2 * np.pi * path / (0.37 * bl[0]) + bph[1])))
        roll = bm * (0.008 * lat + 0.0015 * np.sin(2 * np.pi * path / bl[1] + bph[2]))
        z = bm * 0.01 * np.sin(2 * np.pi * path / bl[0] + bph[3])
        self.t, self.x, self.y, self.yaw, self.s, self.d, self.v = t, x, y, yaw, s, d, v
        self.z, self.roll, self.pitch = z, roll, pitch

    def car_pose_rel(self, t_rel):
        """(x, y, z, roll, pitch, yaw) arrays at relative times (s after the first sweep start)."""
        tr = np.asarray(t_rel, dtype=float)
        return tuple(np.interp(tr, self.t, a) for a in (self.x, self.y, self.z, self.roll, self.pitch, self.yaw))

    def T_world_car(self, t_abs):
        t_abs = np.asarray(t_abs, dtype=float)
        x, y, z, roll, pitch, yaw = self.car_pose_rel(t_abs - self.start_s)
        T = np.zeros(np.shape(x) + (4, 4))
        T[..., :3, :3] = _R_rpy(roll, pitch, yaw)
        T[..., 3, 3] = 1.0
        T[..., 0, 3], T[..., 1, 3], T[..., 2, 3] = x, y, z
        return T

    def T_world_lidar(self, t_abs):
        return self.T_world_car(t_abs) @ self.T_car_lidar

    __call__ = T_world_lidar

    def speed_mps(self, t_abs):
        return np.interp(np.asarray(t_abs, dtype=float) - self.start_s, self.t, self.v)


# ----------------------------------------------------------------------------------------------
# primitives
# ----------------------------------------------------------------------------------------------
GROUND, BOX, CYL, ELL = 0, 1, 2, 3
# materials
M_ROAD, M_FACADE, M_ROOF, M_POLE, M_BARK, M_FOLIAGE, M_CAR, M_GLASS, M_SIGN, M_WOOD, M_CLOTH, \
    M_SKIN, M_KIOSK, M_BIN = range(14)
_REFLECTIVITY = np.array([0.12, 0.32, 0.25, 0.4, 0.22, 0.3, 0.35, 0.06, 0.95, 0.3, 0.25, 0.3, 0.3, 0.3])
_EPS = 1e-6
_KERB_HALF_M = 0.12  # kerb stones: a band this far either side of the road's edge


@dataclass
class _Prims:
    """Struct-of-arrays for one primitive type; ``agent`` >= 0 means parameters are in that agent's
    frame (instantiated per time), -1 means world frame."""

    params: np.ndarray      # BOX: cx cy cz yaw hx hy hz | CYL: x y z0 z1 r | ELL: cx cy cz rxy rz
    pid: np.ndarray         # global primitive id per row
    agent: np.ndarray       # agent index or -1


class StreetWorld:
    """The static layout and the traffic of one drive, drawn from ``rng``."""

    def __init__(self, sc: StreetScenario, rng: np.random.Generator, s_range_m: tuple, ego_s0: float = 0.0):
        self.sc = sc
        self.ego_s0 = float(ego_s0)
        self.street = StreetFrame(sc.layout.curvature_per_m)
        self.rng = rng
        self._rows: dict = {BOX: [], CYL: [], ELL: []}
        self.ptype: list = [GROUND]
        self.material: list = [M_ROAD]
        self.color: list = [(0.3, 0.3, 0.3)]
        self.seed: list = [0]
        self.kind: list = ["ground"]
        self.landmarks: list = []
        self.agents: list = []
        self.s_lo, self.s_hi = float(s_range_m[0]), float(s_range_m[1])
        # lanes per direction: two when a second lane and a parking strip fit
        self.n_lanes = 2 if sc.layout.road_width_m / 2 >= 2 * sc.layout.lane_width_m + 2.2 else 1
        self._build()
        self._finalise()

    # -- building ------------------------------------------------------------------------------
    def _add(self, ptype: int, params, material: int, kind: str, color=(0.5, 0.5, 0.5),
             agent: int = -1) -> int:
        pid = len(self.ptype)
        self._rows[ptype].append((list(map(float, params)), pid, agent))
        self.ptype.append(ptype)
        self.material.append(material)
        self.color.append(tuple(float(c) for c in color))
        self.seed.append(int(self.rng.integers(0, 2**20)))
        self.kind.append(kind)
        return pid

    def _sd_pose(self, s, d):
        x, y = self.street.to_world(s, d)
        return float(x), float(y), float(self.street.heading(s))

    def _landmark(self, typ: str, s: float, d: float, radius: float, height: float, pids: list,
                  **extra) -> None:
        x, y, _ = self._sd_pose(s, d)
        self.landmarks.append(dict(type=typ, id=len(self.landmarks), position=[x, y, 0.0],
                                   radius=float(radius), height=float(height), s_m=float(s), d_m=float(d),
                                   pids=[int(p) for p in pids], **extra))

    def _build(self) -> None:
        _sc, rng, L = self.sc, self.rng, self.sc.layout
        u = rng.uniform
        half = L.road_width_m / 2
        lo, hi = self.s_lo, self.s_hi
        for side in (-1.0, 1.0):
            # buildings
            s = lo - u(0, L.building_length_m[1])
            while s < hi:
                length = u(*L.building_length_m)
                if rng.random() < L.building_gap_prob:
                    s += u(3.0, 12.0)
                    continue
                depth = u(8.0, 16.0)
                setback = u(*L.setback_m)
                d = side * (half + L.sidewalk_width_m + setback + depth / 2)
                x, y, yaw = self._sd_pose(s + length / 2, d)
                h = u(*L.building_height_m)
                col = np.clip(np.array([0.55, 0.6, 0.68]) + u(-0.2, 0.2, 3) + u(-0.1, 0.1), 0.15, 0.95)
                self._add(BOX, [x, y, h / 2, yaw, length / 2 - 0.05, depth / 2, h / 2], M_FACADE,
                          "building", col)
                s += length
            # street lights (pole + arm towards the road)
            if L.light_spacing_m > 0:
                s = lo + u(0, L.light_spacing_m) + (L.light_spacing_m / 2 if side > 0 else 0)
                while s < hi:
                    d = side * (half + 0.45)
                    x, y, yaw = self._sd_pose(s, d)
                    r, h = u(0.07, 0.14), u(5.0, 8.5)
                    p = self._add(CYL, [x, y, 0.0, h, r], M_POLE, "pole", (0.45, 0.47, 0.5))
                    ax, ay, _ = self._sd_pose(s, d - side * 0.9)
                    a = self._add(BOX, [ax, ay, h - 0.1, yaw, 0.08, 0.9, 0.06], M_POLE, "pole_arm",
                                  (0.4, 0.42, 0.45))
                    self._landmark("pole", s, d, r, h, [p, a])
                    s += L.light_spacing_m * u(0.85, 1.15)
            # trees
            if L.tree_spacing_m > 0:
                s = lo + u(0, L.tree_spacing_m)
                while s < hi:
                    if rng.random() < L.tree_prob:
                        d = side * (half + min(1.2, L.sidewalk_width_m * 0.35))
                        d += side * u(-0.1, 0.1)
                        x, y, _ = self._sd_pose(s, d)
                        # crown bottom >= 2.18 m: above any roof-mounted sensor passing below
                        r, h = u(0.12, 0.3), u(2.4, 3.6)
                        rxy, rz = u(1.2, 2.6), u(1.0, 2.2)
                        t = self._add(CYL, [x, y, 0.0, h + 0.3 * rz, r], M_BARK, "trunk",
                                      (0.25, 0.33, 0.4) * np.array(u(0.7, 1.2)))
                        green = np.array([0.18, 0.45, 0.25]) * u(0.6, 1.3) + u(-0.05, 0.05, 3)
                        c = self._add(ELL, [x, y, h + 0.9 * rz, rxy, rz], M_FOLIAGE, "crown", green)
                        self._landmark("tree", s, d, r, h, [t, c], crown_radius=float(rxy),
                                       crown_height=float(rz))
                    s += L.tree_spacing_m * u(0.8, 1.2)
        def n(per100: float) -> int:
            return int(rng.poisson(per100 * (hi - lo) / 100.0))

        # sign posts (plate facing the oncoming traffic of that side)
        for _ in range(n(L.signs_per_100m)):
            side = rng.choice([-1.0, 1.0])
            s, d = u(lo, hi), side * (half + 0.3)
            x, y, yaw = self._sd_pose(s, d)
            r, h = u(0.03, 0.05), u(2.2, 3.0)
            p = self._add(CYL, [x, y, 0.0, h, r], M_POLE, "sign_post", (0.55, 0.55, 0.57))
            w = u(0.25, 0.4)
            off = 0.05 if side < 0 else -0.05
            px, py, _ = self._sd_pose(s + off, d)
            col = [(0.15, 0.15, 0.8), (0.7, 0.35, 0.1), (0.9, 0.9, 0.9), (0.2, 0.6, 0.2)][rng.integers(4)]
            q = self._add(BOX, [px, py, h - w, yaw, 0.02, w, w], M_SIGN, "sign_plate", col)
            self._landmark("sign", s, d, r, h, [p, q], plate_size_m=float(2 * w))
        # street furniture on the sidewalk's kerb zone
        for _ in range(n(L.furniture_per_100m)):
            side = rng.choice([-1.0, 1.0])
            s = u(lo, hi)
            kind = rng.choice(["bin", "bollard", "bench", "kiosk", "hydrant"], p=[0.3, 0.25, 0.2, 0.1, 0.15])
            if kind in ("bin", "bollard", "hydrant"):
                r, h = {"bin": (0.3, 1.0), "bollard": (0.09, 0.9), "hydrant": (0.15, 0.75)}[kind]
                d = side * (half + 0.35 + u(0, 0.6))
                x, y, _ = self._sd_pose(s, d)
                col = {"bin": (0.2, 0.45, 0.25), "bollard": (0.3, 0.3, 0.3), "hydrant": (0.1, 0.1, 0.75)}[kind]
                p = self._add(CYL, [x, y, 0.0, h, r], M_BIN, kind, col)
                self._landmark(str(kind), s, d, r, h, [p])
            else:
                lx, ly, lz = (0.9, 0.3, 0.45) if kind == "bench" else (1.5, 1.0, 1.3)
                d = side * (half + L.sidewalk_width_m - ly - 0.1)
                x, y, yaw = self._sd_pose(s, d)
                col = (0.2, 0.35, 0.55) if kind == "bench" else tuple(u(0.2, 0.8, 3))
                p = self._add(BOX, [x, y, lz, yaw, lx, ly, lz], M_WOOD if kind == "bench" else M_KIOSK,
                              str(kind), col)
                self._landmark(str(kind), s, d, max(lx, ly), 2 * lz, [p])
        # parked cars along the kerb (static), only where a parking strip (>= 2 m) is left
        occupied: list = []
        strip = half - self.n_lanes * L.lane_width_m
        for _ in range(n(L.parked_cars_per_100m) if strip >= 2.0 else 0):
            side = rng.choice([-1.0, 1.0])
            s = u(lo, hi)
            if any(abs(s - s2) < 5.5 and side == sd2 for s2, sd2 in occupied):
                continue
            occupied.append((s, side))
            d = side * (half - min(1.1, strip / 2))
            pids = self._car_parts(agent=-1, s=s, d=d, heading_offset=0.0 if side < 0 else np.pi)
            self._landmark("parked_car", s, d, 2.2, 1.5, pids)
        self._traffic(occupied)

    def _car_parts(self, agent: int, s: float = 0.0, d: float = 0.0, heading_offset: float = 0.0) -> list:
        """A car as a body box and a cabin box (glass), in the world or in an agent frame."""
        u = self.rng.uniform
        length, width = u(3.9, 4.8), u(1.7, 1.95)
        hb, hc = u(0.65, 0.85), u(0.5, 0.65)
        col = tuple(np.clip(self.rng.choice([[0.8, 0.8, 0.8], [0.1, 0.1, 0.12], [0.15, 0.2, 0.7],
                                             [0.6, 0.6, 0.62], [0.1, 0.15, 0.6], [0.2, 0.5, 0.2]])
                            + u(-0.05, 0.05, 3), 0, 1))
        if agent < 0:
            x, y, yaw = self._sd_pose(s, d)
            yaw += heading_offset
        else:
            x = y = yaw = 0.0
        c, sn = np.cos(yaw), np.sin(yaw)
        kind = "car" if agent >= 0 else "parked_car"
        b = self._add(BOX, [x, y, 0.25 + hb / 2, yaw, length / 2, width / 2, hb / 2], M_CAR, kind, col,
                      agent=agent)
        off = -0.25
        g = self._add(BOX, [x + c * off, y + sn * off, 0.25 + hb + hc / 2, yaw, length * 0.28, width / 2 - 0.08,
                            hc / 2], M_GLASS, kind, (0.12, 0.1, 0.08), agent=agent)
        return [b, g]

    def _traffic(self, occupied: list) -> None:
        sc, rng, L, T = self.sc, self.rng, self.sc.layout, self.sc.traffic
        u = rng.uniform
        half = L.road_width_m / 2
        lo, hi = self.s_lo, self.s_hi
        n_cars = rng.poisson(T.cars_per_100m * (hi - lo) / 100.0)
        for _ in range(n_cars):
            same = rng.random() < 0.4
            v = u(*T.car_speed_kmh) / 3.6
            if same:  # same direction, adjacent lane if the road is wide, else a leading car
                if self.n_lanes >= 2:
                    d = -L.lane_width_m * 1.5
                    s0 = u(lo, hi)
                else:
                    d = -L.lane_width_m / 2
                    s0 = u(self.ego_s0 + 20.0, hi)
                    v = max(v, sc.motion.speed_kmh / 3.6 + sc.motion.speed_amplitude_kmh / 3.6 + 2.0)
                vs, yaw_off = v, 0.0
            else:
                d, s0, vs, yaw_off = L.lane_width_m / 2 + u(-0.2, 0.2), u(lo, hi), -v, np.pi
            a = len(self.agents)
            pids = self._car_parts(agent=a)
            self.agents.append({"type": "car", "s0": float(s0), "d0": float(d), "vs": float(vs), "vd": 0.0,
                                    "yaw_offset": float(yaw_off), "pids": pids})
        n_ped = rng.poisson(T.pedestrians_per_100m * (hi - lo) / 100.0)
        for _ in range(n_ped):
            side = rng.choice([-1.0, 1.0])
            d = side * (half + 1.6 + u(0, max(L.sidewalk_width_m - 2.0, 0.1)))
            v = u(*T.pedestrian_speed_mps) * rng.choice([-1.0, 1.0])
            a = len(self.agents)
            r, h = u(0.18, 0.25), u(1.35, 1.6)
            col = tuple(u(0.1, 0.8, 3))
            body = self._add(CYL, [0.0, 0.0, 0.0, h, r], M_CLOTH, "pedestrian", col, agent=a)
            head = self._add(ELL, [0.0, 0.0, h + 0.13, 0.1, 0.13], M_SKIN, "pedestrian",
                             (0.45, 0.55, 0.75), agent=a)
            self.agents.append({"type": "pedestrian", "s0": float(u(lo, hi)), "d0": float(d), "vs": float(v), "vd": 0.0,
                                    "yaw_offset": 0.0 if v > 0 else np.pi, "pids": [body, head]})

    def _finalise(self) -> None:
        self.prims = {}
        width = {BOX: 7, CYL: 5, ELL: 5}
        for t, rows in self._rows.items():
            if rows:
                params = np.array([r[0] for r in rows], dtype=float)
                pid = np.array([r[1] for r in rows], dtype=np.int64)
                agent = np.array([r[2] for r in rows], dtype=np.int64)
            else:
                params = np.zeros((0, width[t]))
                pid = agent = np.zeros(0, dtype=np.int64)
            self.prims[t] = _Prims(params, pid, agent)
        n = len(self.ptype)
        self.ptype_arr = np.array(self.ptype, dtype=np.int64)
        self.material_arr = np.array(self.material, dtype=np.int64)
        self.color_arr = np.array(self.color, dtype=np.float32)
        self.seed_arr = np.array(self.seed, dtype=np.int64)
        self.row_of_pid = np.full(n, -1, dtype=np.int64)
        for p in self.prims.values():
            self.row_of_pid[p.pid] = np.arange(p.pid.size)
        self.dynamic_arr = np.zeros(n, dtype=bool)
        for a in self.agents:
            self.dynamic_arr[a["pids"]] = True

    # -- time-dependent instantiation ----------------------------------------------------------
    def agent_poses(self, t_rel: float) -> np.ndarray:
        """(n_agents, 3) x, y, yaw of every agent at relative time ``t_rel``."""
        if not self.agents:
            return np.zeros((0, 3))
        s = np.array([a["s0"] + a["vs"] * t_rel for a in self.agents])
        d = np.array([a["d0"] + a["vd"] * t_rel for a in self.agents])
        x, y = self.street.to_world(s, d)
        yaw = self.street.heading(s) + np.array([a["yaw_offset"] for a in self.agents])
        return np.stack([x, y, yaw], axis=1)

    def instantiate(self, t_rel: float) -> dict:
        """Per-type world-frame parameter arrays at relative time ``t_rel`` (agents placed)."""
        out = {}
        poses = self.agent_poses(t_rel)
        for t, p in self.prims.items():
            par = p.params.copy()
            dyn = p.agent >= 0
            if dyn.any():
                ag = poses[p.agent[dyn]]
                c, s = np.cos(ag[:, 2]), np.sin(ag[:, 2])
                lx, ly = par[dyn, 0].copy(), par[dyn, 1].copy()
                par[dyn, 0] = ag[:, 0] + c * lx - s * ly
                par[dyn, 1] = ag[:, 1] + s * lx + c * ly
                if t == BOX:
                    par[dyn, 3] += ag[:, 2]
            out[t] = par
        return out

    # -- queries --------------------------------------------------------------------------------
    @staticmethod
    def bounding_circles(inst: dict) -> dict:
        """Per type: (cx, cy, r_xy) arrays of each primitive's vertical bounding cylinder."""
        b = inst[BOX]
        return {BOX: (b[:, 0], b[:, 1], np.hypot(b[:, 4], b[:, 5])),
                CYL: (inst[CYL][:, 0], inst[CYL][:, 1], inst[CYL][:, 4]),
                ELL: (inst[ELL][:, 0], inst[ELL][:, 1], inst[ELL][:, 3])}

    def distance_to_surfaces(self, pts_world: np.ndarray, t_rel: float = 0.0, pids=None) -> np.ndarray:
        """Unsigned distance of each point to the nearest surface (ground included), for checks.

        ``pids``: restrict to these primitive ids (the ground is id 0)."""
        p = np.asarray(pts_world, dtype=float).reshape(-1, 3)
        inst = self.instantiate(t_rel)
        keep = None if pids is None else {int(i) for i in np.atleast_1d(pids)}
        best = np.abs(p[:, 2]) if (keep is None or 0 in keep) else np.full(len(p), np.inf)
        for t, par in inst.items():
            sel = np.arange(par.shape[0])
            if keep is not None:
                sel = np.array([i for i in sel if int(self.prims[t].pid[i]) in keep], dtype=int)
            for i in sel:
                q = par[i]
                if t == BOX:
                    c, s = np.cos(q[3]), np.sin(q[3])
                    dx, dy, dz = p[:, 0] - q[0], p[:, 1] - q[1], p[:, 2] - q[2]
                    lx, ly = c * dx + s * dy, -s * dx + c * dy
                    e = np.abs(np.stack([lx, ly, dz], 1)) - q[4:7]
                    out = np.linalg.norm(np.maximum(e, 0), axis=1)
                    dist = np.where(out > 0, out, -np.max(e, axis=1))
                elif t == CYL:
                    rr = np.hypot(p[:, 0] - q[0], p[:, 1] - q[1]) - q[4]
                    dzc = np.maximum(p[:, 2] - q[3], q[2] - p[:, 2])
                    e = np.stack([rr, dzc], 1)
                    out = np.linalg.norm(np.maximum(e, 0), axis=1)
                    dist = np.where(out > 0, out, -np.max(e, axis=1))
                else:  # first-order distance to the ellipsoid: F / |grad F|
                    radii = np.array([q[3], q[3], q[4]])
                    F = np.sum(((p - q[:3]) / radii) ** 2, axis=1) - 1.0
                    grad = 2.0 * (p - q[:3]) / radii ** 2
                    dist = F / np.maximum(np.linalg.norm(grad, axis=1), 1e-9)
                best = np.minimum(best, np.abs(dist))
        return best


# ----------------------------------------------------------------------------------------------
# ray casting (rays (n,3) origins o, directions d; returns t (n,m), inf = miss)
# ----------------------------------------------------------------------------------------------
def _hit_boxes(o, d, P):
    if P.shape[0] == 0:
        return np.full((o.shape[0], 0), np.inf)
    c, s = np.cos(P[:, 3]), np.sin(P[:, 3])
    ox = o[:, 0:1] - P[:, 0]
    oy = o[:, 1:2] - P[:, 1]
    oz = o[:, 2:3] - P[:, 2]
    lox, loy = c * ox + s * oy, -s * ox + c * oy
    ldx, ldy = c * d[:, 0:1] + s * d[:, 1:2], -s * d[:, 0:1] + c * d[:, 1:2]
    ldz = d[:, 2:3]
    tmin = np.full(lox.shape, -np.inf)
    tmax = np.full(lox.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo_, ld, h in ((lox, ldx, P[:, 4]), (loy, ldy, P[:, 5]), (oz, ldz, P[:, 6])):
            inv = 1.0 / np.where(np.abs(ld) < 1e-12, 1e-12, ld)
            t1, t2 = (-h - lo_) * inv, (h - lo_) * inv
            tmin = np.maximum(tmin, np.minimum(t1, t2))
            tmax = np.minimum(tmax, np.maximum(t1, t2))
    hit = (tmax >= tmin) & (tmin > _EPS)
    return np.where(hit, tmin, np.inf)


def _hit_cylinders(o, d, P):
    if P.shape[0] == 0:
        return np.full((o.shape[0], 0), np.inf)
    ox = o[:, 0:1] - P[:, 0]
    oy = o[:, 1:2] - P[:, 1]
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    cc = ox * ox + oy * oy - P[:, 4] ** 2
    disc = b * b - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / np.where(a < 1e-12, 1e-12, a)
        z = o[:, 2:3] + t * dz
        side = (disc >= 0) & (t > _EPS) & (z >= P[:, 2]) & (z <= P[:, 3])
        tc = (P[:, 3] - o[:, 2:3]) / np.where(np.abs(dz) < 1e-12, 1e-12, dz)
        cx, cy = ox + tc * dx, oy + tc * dy
        cap = (tc > _EPS) & (cx * cx + cy * cy <= P[:, 4] ** 2) & (o[:, 2:3] > P[:, 3])
    return np.minimum(np.where(side, t, np.inf), np.where(cap, tc, np.inf))


def _hit_ellipsoids(o, d, P):
    if P.shape[0] == 0:
        return np.full((o.shape[0], 0), np.inf)
    sz = P[:, 3] / P[:, 4]
    ox, oy, oz = o[:, 0:1] - P[:, 0], o[:, 1:2] - P[:, 1], (o[:, 2:3] - P[:, 2]) * sz
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3] * sz
    a = dx * dx + dy * dy + dz * dz
    b = ox * dx + oy * dy + oz * dz
    cc = ox * ox + oy * oy + oz * oz - P[:, 3] ** 2
    disc = b * b - a * cc
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > _EPS), t, np.inf)


_HIT = {BOX: _hit_boxes, CYL: _hit_cylinders, ELL: _hit_ellipsoids}


def _surface(world: StreetWorld, inst: dict, pts: np.ndarray, pid: np.ndarray):
    """Normals (k,3), surface coordinates uv (k,2) and face index (k,) of hit points on ``pid``."""
    k = pts.shape[0]
    nrm = np.zeros((k, 3), dtype=pts.dtype)
    uv = np.zeros((k, 2), dtype=pts.dtype)
    face = np.zeros(k, dtype=np.int64)
    typ = world.ptype_arr[pid]
    g = typ == GROUND
    nrm[g] = (0, 0, 1)
    uv[g] = pts[g, :2]
    m = typ == BOX
    if m.any():
        P = inst[BOX][world.row_of_pid[pid[m]]].astype(pts.dtype)
        c, s = np.cos(P[:, 3]), np.sin(P[:, 3])
        dx, dy, dz = pts[m, 0] - P[:, 0], pts[m, 1] - P[:, 1], pts[m, 2] - P[:, 2]
        q = np.stack([c * dx + s * dy, -s * dx + c * dy, dz], 1)
        rel = np.abs(q) / P[:, 4:7] - 1.0
        ax = np.argmax(rel, axis=1)
        sg = np.sign(q[np.arange(q.shape[0]), ax])
        nl = np.zeros_like(q)
        nl[np.arange(q.shape[0]), ax] = sg
        nrm[m] = np.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1], nl[:, 2]], 1)
        uu = np.where(ax == 0, q[:, 1] * -sg, np.where(ax == 1, q[:, 0] * sg, q[:, 0]))
        vv = np.where(ax == 2, q[:, 1], q[:, 2] + P[:, 6])  # height above the box bottom
        uv[m] = np.stack([uu, vv], 1)
        face[m] = ax * 2 + (sg > 0)
    m = typ == CYL
    if m.any():
        P = inst[CYL][world.row_of_pid[pid[m]]].astype(pts.dtype)
        dx, dy = pts[m, 0] - P[:, 0], pts[m, 1] - P[:, 1]
        top = pts[m, 2] > P[:, 3] - 1e-6
        n = np.stack([dx, dy, np.zeros_like(dx)], 1) / np.maximum(P[:, 4:5], 1e-9)
        n[top] = (0, 0, 1)
        nrm[m] = n
        uv[m] = np.stack([np.arctan2(dy, dx) * P[:, 4], pts[m, 2]], 1)
        face[m] = top
    m = typ == ELL
    if m.any():
        P = inst[ELL][world.row_of_pid[pid[m]]].astype(pts.dtype)
        q = pts[m] - P[:, :3]
        n = q / np.stack([P[:, 3] ** 2, P[:, 3] ** 2, P[:, 4] ** 2], 1)
        nrm[m] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        uv[m] = np.stack([np.arctan2(q[:, 1], q[:, 0]) * P[:, 3], q[:, 2]], 1)
    return nrm, uv, face


# ----------------------------------------------------------------------------------------------
# procedural textures
# ----------------------------------------------------------------------------------------------
_NOISE = np.random.default_rng(20201).random(256 * 256).astype(np.float32)


def _vnoise(u, v):
    """Smooth value noise on a 256-periodic lattice, values in [0, 1] (float32)."""
    xf, yf = np.floor(u), np.floor(v)
    fx, fy = u - xf, v - yf
    xi = xf.astype(np.int32) & 255
    yi = (yf.astype(np.int32) & 255) << 8
    x1 = (xi + 1) & 255
    y1 = (yi + 256) & 65535
    sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    a, b = np.take(_NOISE, yi + xi), np.take(_NOISE, yi + x1)
    c, d = np.take(_NOISE, y1 + xi), np.take(_NOISE, y1 + x1)
    ab = a + (b - a) * sx
    return ab + (c + (d - c) * sx - ab) * sy


def _fbm(u, v, freq, octaves, foot, seed, gain=0.55):
    """Multi-octave noise in [0, 1] whose octaves finer than ~2 pixels fade to their mean."""
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    foot = np.asarray(foot, dtype=np.float32)
    total = np.zeros(u.shape, dtype=np.float32)
    norm = 0.0
    amp = 1.0
    off = ((np.asarray(seed) % 997) * 7.31).astype(np.float32)
    for o in range(octaves):
        f = np.float32(freq * (2.03 ** o))
        w = np.clip(1.0 / (f * foot) - 1.5, 0.0, 1.0).astype(np.float32)  # wavelength / footprint
        live = np.flatnonzero(w > 0)
        if live.size == u.size:
            n = _vnoise(u * f + off + np.float32(17.1 * o), v * f - off * np.float32(0.7) + np.float32(31.7 * o))
            total += amp * (w * (n - 0.5))
        elif live.size:
            ol = off[live] if off.ndim else off
            n = _vnoise(u[live] * f + ol + np.float32(17.1 * o),
                        v[live] * f - ol * np.float32(0.7) + np.float32(31.7 * o))
            total[live] += amp * (w[live] * (n - 0.5))
        norm += amp
        amp *= gain
    return total / np.float32(norm) + np.float32(0.5)


def _fade(period, foot):
    """1 when a pattern of this period spans >= 4 pixels, 0 below 2 pixels."""
    return np.clip(period / np.maximum(foot, 1e-9) / 2.0 - 1.0, 0.0, 1.0).astype(np.float32)


def _road_paint(s, d, L: StreetLayout):
    """Paint mask on the road: dashed centre line, lane lines, solid edge lines, crossings."""
    half = L.road_width_m / 2
    paint = np.zeros(np.shape(s), dtype=np.float32)
    dash = (np.mod(s, 9.0) < 3.0)
    paint = np.maximum(paint, ((np.abs(d) < 0.08) & dash).astype(np.float32))
    lanes = int(half // L.lane_width_m)
    for k in range(1, lanes):
        paint = np.maximum(paint, ((np.abs(np.abs(d) - k * L.lane_width_m) < 0.07) & (np.mod(s, 12.0) < 4.0)))
    paint = np.maximum(paint, (np.abs(np.abs(d) - (half - 0.3)) < 0.08).astype(np.float32))
    zebra = (np.mod(s, 150.0) < 4.0) & (np.mod(d, 1.0) < 0.5) & (np.abs(d) < half - 0.5)
    return np.maximum(paint, zebra.astype(np.float32)) * (np.abs(d) < half)


def _albedo(world: StreetWorld, pid, uv, face, pts, foot):
    """Colour (k,3) BGR in [0, 1] of hit points (procedural, by material)."""
    k = pid.shape[0]
    col = np.zeros((k, 3), dtype=np.float32)
    mat = world.material_arr[pid]
    base = world.color_arr[pid]
    seed = world.seed_arr[pid]
    L = world.sc.layout
    half = L.road_width_m / 2

    m = mat == M_ROAD
    if m.any():
        x, y, f = pts[m, 0], pts[m, 1], foot[m]
        s, d = world.street.from_world(x, y)
        s, d = s.astype(np.float32), d.astype(np.float32)
        n = _fbm(x, y, 0.7, 4, f, 3) + 0.9 * (_fbm(x, y, 6.0, 3, f, 5, gain=0.8) - 0.5)
        ad = np.abs(d)
        g = 0.22 + 0.25 * (n - 0.5)  # asphalt
        walk = np.flatnonzero((ad >= half) & (ad < half + L.sidewalk_width_m))
        if walk.size:  # sidewalk: 0.4 m paving slabs with dark joints
            sw_, dw_ = s[walk], d[walk]
            joint = np.minimum(np.abs(np.mod(sw_, 0.4) - 0.2), np.abs(np.mod(dw_, 0.4) - 0.2))
            slab = 1.0 - (joint > 0.18) * _fade(0.4, f[walk]) * 0.35
            g[walk] = (0.5 + 0.35 * (n[walk] - 0.5)) * slab
        g[np.abs(ad - half) < _KERB_HALF_M] = 0.65  # kerb stones
        beyond = ad >= half + L.sidewalk_width_m
        g[beyond] = 0.35 + 0.4 * (n[beyond] - 0.5)
        road = np.flatnonzero(ad < half)
        if road.size:
            paint = _road_paint(s[road], d[road], L) * _fade(0.3, f[road])
            g[road] = g[road] * (1 - paint) + 0.85 * paint
        c = np.repeat(g[:, None], 3, axis=1)
        c[beyond] *= np.array([0.75, 0.95, 1.0], np.float32)
        col[m] = c
    m = mat == M_FACADE
    if m.any():
        u, v, f, sd = uv[m, 0], uv[m, 1], foot[m], seed[m]
        n = _fbm(u, v, 0.35, 7, f, sd)
        c = base[m] * (0.75 + 0.5 * n)[:, None]
        # bricks on half the buildings
        brick = (sd % 2) == 0
        row = np.floor(v / 0.075)
        bu = np.mod(u / 0.25 + 0.5 * np.mod(row, 2), 1.0)
        mortar = ((np.mod(v, 0.075) < 0.012) | (bu < 0.05)).astype(np.float32) * _fade(0.075, f)
        c[brick] *= (1 - 0.3 * mortar[brick])[:, None]
        # windows: floors of 3.2 m, bays of 2.6-3.6 m (per building), ground floor shop windows
        bay = 2.6 + (sd % 7) * 0.15
        fu = np.mod(u, bay) / bay
        fv = np.mod(v, 3.2) / 3.2
        floor = np.floor(v / 3.2)
        win = (fu > 0.25) & (fu < 0.75) & (fv > 0.3) & (fv < 0.8) & (floor >= 1)
        shop = (floor < 1) & (fu > 0.1) & (fu < 0.9) & (fv > 0.15) & (fv < 0.8) & ((np.floor(u / bay) % 3) != 1)
        frame = ((fu > 0.22) & (fu < 0.78) & (fv > 0.27) & (fv < 0.83) & (floor >= 1)) & ~win
        top = face[m] == 5
        wv = (win | shop) & ~top
        if wv.any():
            glass = 0.12 + 0.35 * _fbm(u[wv] * 0.3, v[wv] * 0.3 + floor[wv] * 3.3, 0.8, 3, f[wv], sd[wv] + 5)
            c[wv] = glass[:, None] * np.array([1.1, 1.0, 0.85], np.float32)
        c[frame & ~top] = 0.85
        c[top] = (0.3 + 0.3 * n[top])[:, None]
        col[m] = c
    for mm, freq, contrast in ((M_POLE, 2.0, 0.4), (M_CAR, 1.5, 0.25), (M_WOOD, 3.0, 0.5),
                               (M_KIOSK, 1.0, 0.5), (M_BIN, 2.0, 0.4), (M_CLOTH, 3.0, 0.5),
                               (M_SKIN, 6.0, 0.3), (M_GLASS, 1.0, 0.6), (M_ROOF, 1.0, 0.4)):
        m = mat == mm
        if m.any():
            n = _fbm(uv[m, 0], uv[m, 1], freq, 6, foot[m], seed[m])
            c = base[m] * (1.0 - contrast / 2 + contrast * n)[:, None]
            if mm == M_KIOSK:  # poster panels
                p = _fbm(uv[m, 0], uv[m, 1], 3.0, 5, foot[m], seed[m] + 11)
                c = np.where((np.mod(uv[m, 0], 1.2) < 0.9)[:, None], np.stack([p, 1 - p, p * 0.5], 1), c)
            if mm == M_CAR:  # dark bumper band, light number plate at front/back
                v = uv[m, 1]
                c = np.where((v < 0.18)[:, None], 0.08, c)
                plate = (face[m] < 2) & (np.abs(uv[m, 0]) < 0.26) & (v > 0.22) & (v < 0.34)
                c = np.where(plate[:, None], 0.9, c)
            if mm == M_POLE:  # stickers and bands
                st = _fbm(uv[m, 0], uv[m, 1], 1.5, 3, foot[m], seed[m] + 3) > 0.62
                c = np.where(st[:, None], np.array([[0.9, 0.85, 0.7]], np.float32), c)
            col[m] = c
    m = mat == M_BARK
    if m.any():
        n = _fbm(uv[m, 0] * 3.0, uv[m, 1] * 0.7, 4.0, 6, foot[m], seed[m])
        col[m] = base[m] * (0.5 + 0.9 * n)[:, None]
    m = mat == M_FOLIAGE
    if m.any():
        n = _fbm(uv[m, 0], uv[m, 1], 2.5, 7, foot[m], seed[m], gain=0.7)
        col[m] = base[m] * (0.35 + 1.3 * n)[:, None]
    m = mat == M_SIGN
    if m.any():
        P = world.prims[BOX].params[world.row_of_pid[pid[m]]]
        w = P[:, 5]
        border = (np.abs(uv[m, 0]) > 0.8 * w) | (np.abs(uv[m, 1] - w) > 0.8 * w)
        sym = _fbm(uv[m, 0], uv[m, 1], 8.0, 2, foot[m], seed[m]) > 0.55
        c = np.where(border[:, None], 0.95, base[m])
        c = np.where((sym & ~border)[:, None], 0.05, c)
        c = np.where((face[m] >= 2)[:, None] | (face[m] == (seed[m] % 2))[:, None], 0.5, c)
        col[m] = c
    return np.clip(col, 0.0, 1.0)


def _lidar_reflectivity(world: StreetWorld, pid, pts):
    """Unit reflectance of hit points (paint on the road is brighter, signs retro-reflect)."""
    r = _REFLECTIVITY[world.material_arr[pid]].astype(float)
    g = world.material_arr[pid] == M_ROAD
    if g.any():
        s, d = world.street.from_world(pts[g, 0], pts[g, 1])
        L = world.sc.layout
        paint = _road_paint(s, d, L)
        ad = np.abs(d)
        # the same surfaces the camera renders (_albedo): asphalt, paint, the kerb stones' 0.24 m band of
        # bright concrete along the road's edge, then the sidewalk's slabs
        r[g] = np.where(paint > 0.5, world.sc.lidar.paint_reflectivity,
                        np.where(np.abs(ad - L.road_width_m / 2) < _KERB_HALF_M, 0.3,
                                 np.where(ad < L.road_width_m / 2, 0.1, 0.2)))
    return r


# ----------------------------------------------------------------------------------------------
# sensors
# ----------------------------------------------------------------------------------------------
@dataclass
class StreetSweep:
    """One LiDAR sweep; ``stamp_s`` = sweep start on the LiDAR clock."""

    stamp_s: float
    cloud: dict              # 'x','y','z' float32 LiDAR frame at each point's time; 'intensity',
    #                          'ring', 'time' (s after stamp_s) when the preset publishes them
    dynamic: np.ndarray      # bool (N,) point on a moving object (truth)
    label: np.ndarray | None = None   # int32 (N,) primitive id (0 = ground), with_labels only


@dataclass
class StreetImage:
    """One camera image; ``stamp_s`` on the camera clock = ``exposure_s`` + ``time_offset_s``."""

    stamp_s: float           # camera clock
    image: np.ndarray        # HxWx3 uint8 bgr8 (or HxW mono8)
    dynamic_mask: np.ndarray  # bool HxW pixel on a moving object (truth)
    exposure_s: float = 0.0  # true (LiDAR-clock) exposure time
    label: np.ndarray | None = None   # int32 HxW primitive id (-1 sky), with_labels only


@dataclass
class DriveSimRun:
    """A simulated drive with its truth.

    ``landmarks``: static objects, dicts with ``type`` ('pole', 'tree', 'sign', 'bin', 'bollard',
    'hydrant', 'bench', 'kiosk', 'parked_car'), ``id``, ``position`` [x, y, 0] (world, base
    centre), ``radius`` (trunk / pole / post radius, half footprint for boxes), ``height`` (of
    the column: pole, post, trunk up to the crown), ``s_m``/``d_m`` street coordinates, ``pids``
    (primitive ids, as in the ``label`` arrays) and per type ``crown_radius``/``crown_height``
    (trees) or ``plate_size_m`` (signs). ``T_world_lidar`` is the ego LiDAR pose at any LiDAR-clock
    time (``EgoTrajectory``; its ``T_world_car`` and ``speed_mps`` are there too)."""

    camera: CameraModel
    T_camera_lidar: np.ndarray
    lidar: Any                                    # LidarPreset
    sweeps: list
    images: list
    T_world_lidar: Callable[[float], np.ndarray]  # LiDAR-clock stamp -> 4x4 (array -> (N,4,4))
    time_offset_s: float
    speed_set: str
    landmarks: list
    frames: dict
    scenario: StreetScenario | None = None
    world: StreetWorld | None = None
    T_car_lidar: np.ndarray | None = None
    T_car_camera: np.ndarray | None = None
    mean_speed_kmh: float = 0.0


class DriveSimulator:
    """Renders sweeps and images of one drive (see module docstring)."""

    N_SECTORS = 72

    def __init__(self, scenario=None, rng: np.random.Generator | None = None, image_scale: float = 1.0,
                 preset=None, duration_s: float | None = None):
        from lidar_cam_calib.sim.lidar import PRESETS

        sc = load_street_scenario(scenario)
        if duration_s is not None:
            if duration_s <= 0:
                raise ConfigError(f"duration_s must be > 0, got {duration_s}")
            sc = dataclasses.replace(sc, timing=dataclasses.replace(sc.timing, duration_s=float(duration_s)))
        if not (0.05 <= float(image_scale) <= 2.0):
            raise ConfigError(f"image_scale must be in [0.05, 2], got {image_scale}")
        self.sc = sc
        self.rng = rng if rng is not None else np.random.default_rng(sc.seed)
        # the reflectance texture's own stream (the other draws of a drive do not depend on it)
        self._texture_rng = np.random.default_rng([int(sc.seed), 9003])
        self.preset = preset if preset is not None else PRESETS[sc.lidar.preset]
        c = sc.camera
        cam = CameraModel.from_K(c.width_px, c.height_px, c.fx_px, c.fy_px, c.cx_px, c.cy_px,
                                 list(c.D), c.distortion_model)
        self.camera = cam.scaled(float(image_scale)) if image_scale != 1.0 else cam
        m = sc.mount
        self.T_car_lidar = make_T(R_from_rpy(*np.radians(m.lidar_rpy_deg)), m.lidar_xyz_m)
        self.T_car_camera = make_T(R_from_rpy(*np.radians(m.camera_rpy_deg)) @ R_BODY_OPTICAL, m.camera_xyz_m)
        self.T_camera_lidar = inv_T(self.T_car_camera) @ self.T_car_lidar
        # layout covers the drive plus the sensor range behind and ahead
        vmax = (sc.motion.speed_kmh + sc.motion.speed_amplitude_kmh) / 3.6
        s0 = 0.0
        reach = min(float(getattr(self.preset, "range_max_m", 100.0)), 110.0) + 10.0
        street = StreetFrame(sc.layout.curvature_per_m)
        self.traj = EgoTrajectory(sc, street, s0, self.T_car_lidar, self.rng)
        s_end = float(self.traj.s[-1]) + vmax * 0.5
        self.world = StreetWorld(sc, self.rng, (s0 - reach, s_end + reach), ego_s0=s0)
        self._rays = None
        self._remap = None

    # -- LiDAR ----------------------------------------------------------------------------------
    def _lidar_rays(self):
        if self._rays is None:
            dirs, ring, az, t = self.preset.ray_directions()
            stride = int(self.sc.lidar.column_stride)
            if stride > 1:
                period = float(self.preset.period_s)
                ncol = int(getattr(self.preset, "n_columns", 0) or round(len(t) / max(self.preset.n_rings, 1)))
                col = np.floor(np.asarray(t) / period * ncol + 1e-6).astype(np.int64)
                keep = (col % stride) == 0
                dirs, ring, az, t = dirs[keep], ring[keep], az[keep], t[keep]
            self._rays = (np.asarray(dirs, float), np.asarray(ring), np.asarray(az, float), np.asarray(t, float))
            # next beam of the same ring (the neighbour across a possible depth edge), -1 at the end
            ring_a, t_a = np.asarray(ring), np.asarray(t, float)
            order = np.lexsort((t_a, ring_a))
            nxt = np.full(t_a.size, -1, dtype=np.int64)
            same = ring_a[order[1:]] == ring_a[order[:-1]]
            nxt[order[:-1][same]] = order[1:][same]
            self._ring_next = nxt
        return self._rays

    def _mix_edges(self, best: np.ndarray, pid: np.ndarray, rng: np.random.Generator) -> None:
        """Mixed returns at depth edges, in place: a beam whose footprint (horizontal divergence)
        straddles the edge of a nearer object returns a range in between, with probability
        (divergence / 2) / azimuth step, attributed to the nearer object."""
        nxt = self._ring_next
        i = np.flatnonzero(nxt >= 0)
        j = nxt[i]
        ri, rj = best[i], best[j]
        ok = np.isfinite(ri) & np.isfinite(rj)
        i, j, ri, rj = i[ok], j[ok], ri[ok], rj[ok]
        edge = np.abs(ri - rj) > np.maximum(0.3, 0.03 * np.minimum(ri, rj))
        i, j, ri, rj = i[edge], j[edge], ri[edge], rj[edge]
        if i.size == 0:
            return
        daz = np.radians(float(self.preset.azimuth_step_deg) * int(self.sc.lidar.column_stride))
        p = min(0.5 * float(getattr(self.preset, "divergence_h_rad", 3e-3)) / daz, 0.9)
        near = np.where(ri < rj, i, j)
        far = np.where(ri < rj, j, i)
        mix = rng.random(i.size) < p
        near, far = near[mix], far[mix]
        w = rng.random(far.size)
        best[far] = best[near] + w * (best[far] - best[near])
        pid[far] = pid[near]

    def sweep(self, j: int, with_labels: bool = False) -> StreetSweep:
        """Sweep ``j`` (starts at relative time j / rate)."""
        sc, world = self.sc, self.world
        dirs, ring, _, t_in = self._lidar_rays()
        period = float(self.preset.period_s)
        t0 = j * period
        tr = t0 + t_in
        x, y, z, roll, pitch, yaw = self.traj.car_pose_rel(tr)
        R_cl, p_cl = self.T_car_lidar[:3, :3], self.T_car_lidar[:3, 3]
        Rw = _R_rpy(roll, pitch, yaw)
        dw = np.einsum("nij,nj->ni", Rw, dirs @ R_cl.T)
        ow = np.stack([x, y, z], 1) + Rw @ p_cl
        n = dirs.shape[0]
        best = np.full(n, np.inf)
        pid = np.zeros(n, dtype=np.int64)
        down = dw[:, 2] < -1e-9
        best[down] = -ow[down, 2] / dw[down, 2]
        az_w = np.arctan2(dw[:, 1], dw[:, 0])
        rmax = float(getattr(self.preset, "range_max_m", 120.0)) + 5.0
        order = np.argsort(tr, kind="stable")
        chunks = np.array_split(order, self.N_SECTORS)
        pass_p = float(sc.lidar.crown_pass_prob)
        rng = self.rng
        for idx in chunks:
            if idx.size == 0:
                continue
            tm = float(np.median(tr[idx]))
            inst = world.instantiate(tm)
            circles = StreetWorld.bounding_circles(inst)
            o_mid = ow[idx].mean(axis=0)
            spread = float(np.max(np.linalg.norm(ow[idx] - o_mid, axis=1))) + 0.3
            ref = np.angle(np.mean(np.exp(1j * az_w[idx])))
            rel = np.angle(np.exp(1j * (az_w[idx] - ref)))
            lo, hi = float(rel.min()), float(rel.max())
            o, d = ow[idx], dw[idx]
            tb = best[idx]
            pb = pid[idx]
            for typ in (BOX, CYL, ELL):
                cx, cy, r = circles[typ]
                if cx.size == 0:
                    continue
                vx, vy = cx - o_mid[0], cy - o_mid[1]
                dist = np.hypot(vx, vy)
                half = np.arcsin(np.clip((r + spread) / np.maximum(dist, 1e-9), 0, 1))
                phi = np.angle(np.exp(1j * (np.arctan2(vy, vx) - ref)))
                sel = ((dist < r + spread + 0.5) | ((phi + half >= lo) & (phi - half <= hi))) & (dist - r < rmax)
                rows = np.flatnonzero(sel)
                if rows.size == 0:
                    continue
                T = _HIT[typ](o, d, inst[typ][rows])
                if typ == ELL and pass_p > 0:
                    crown = world.material_arr[world.prims[ELL].pid[rows]] == M_FOLIAGE
                    if crown.any():
                        through = rng.random((T.shape[0], int(crown.sum()))) < pass_p
                        Tc = T[:, crown]
                        Tc[through] = np.inf
                        Tc += rng.uniform(0, sc.lidar.crown_depth_m, Tc.shape)
                        T[:, crown] = Tc
                k = np.argmin(T, axis=1)
                tk = T[np.arange(T.shape[0]), k]
                better = tk < tb
                tb = np.where(better, tk, tb)
                pb = np.where(better, world.prims[typ].pid[rows][k], pb)
            best[idx] = tb
            pid[idx] = pb
        if sc.lidar.mixed_edge_returns:
            self._mix_edges(best, pid, rng)
        hit = np.isfinite(best)
        pts = ow + best[:, None] * dw
        refl = np.zeros(n)
        if hit.any():
            hi_idx = np.flatnonzero(hit)
            inst_mid = world.instantiate(t0 + period / 2)
            nrm, _, _ = _surface(world, inst_mid, pts[hi_idx], pid[hi_idx])
            cosi = np.abs(np.sum(nrm * dw[hi_idx], axis=1))
            refl[hi_idx] = _lidar_reflectivity(world, pid[hi_idx], pts[hi_idx]) * (0.35 + 0.65 * cosi)
            s_tex = float(sc.lidar.intensity_texture)
            if s_tex > 0:
                refl[hi_idx] *= np.exp(self._texture_rng.normal(-0.5 * s_tex ** 2, s_tex, hi_idx.size))
        rng_m = np.where(hit, best, np.nan)
        kw = {}
        if sc.lidar.range_sigma_m >= 0:
            kw["range_sigma_m"] = float(sc.lidar.range_sigma_m)
        if sc.lidar.dropout_prob >= 0:
            kw["dropout_prob"] = float(sc.lidar.dropout_prob)
        cloud = self.preset.finish_sweep(dirs, ring, t_in, rng_m, refl, rng, **kw)
        keep = cloud.pop("_index")
        stamp = sc.timing.start_stamp_s + t0
        return StreetSweep(stamp_s=float(stamp), cloud=cloud, dynamic=world.dynamic_arr[pid[keep]],
                           label=pid[keep].astype(np.int32) if with_labels else None)

    # -- camera ---------------------------------------------------------------------------------
    def _virtual(self):
        """Ideal pinhole image covering the distorted image, and the remap into it."""
        if self._remap is None:
            cam = self.camera
            if not cam.is_distorted:
                self._remap = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, None, None)
            else:
                # undistort a coarse grid (every 8 px) and interpolate: the map is smooth
                from scipy.ndimage import map_coordinates

                step = 8
                gu = np.append(np.arange(0, cam.width, step), cam.width - 1).astype(float)
                gv = np.append(np.arange(0, cam.height, step), cam.height - 1).astype(float)
                GU, GV = np.meshgrid(gu, gv)
                r = cam.pixels_to_rays(np.stack([GU.ravel(), GV.ravel()], 1))
                vv, uu = np.mgrid[0:cam.height, 0:cam.width].astype(float)
                ci = np.interp(uu[0], gu, np.arange(gu.size))
                ri = np.interp(vv[:, 0], gv, np.arange(gv.size))
                coords = np.stack(np.meshgrid(ri, ci, indexing="ij"))
                xv = cam.fx * map_coordinates(r[:, 0].reshape(GU.shape), coords, order=1).ravel()
                yv = cam.fy * map_coordinates(r[:, 1].reshape(GU.shape), coords, order=1).ravel()
                u0, u1 = np.floor(xv.min()) - 2, np.ceil(xv.max()) + 2
                v0, v1 = np.floor(yv.min()) - 2, np.ceil(yv.max()) + 2
                W, H = int(u1 - u0 + 1), int(v1 - v0 + 1)
                if W * H > 4 * cam.width * cam.height:
                    raise ConfigError("camera distortion is too strong to render (the undistorted view "
                                      "is more than 4x the image); reduce |k1|")
                cxv, cyv = -u0, -v0
                mx = (xv + cxv).reshape(cam.height, cam.width).astype(np.float32)
                my = (yv + cyv).reshape(cam.height, cam.width).astype(np.float32)
                self._remap = (W, H, cam.fx, cam.fy, cxv, cyv, mx, my)
        return self._remap

    def image(self, k: int, with_labels: bool = False) -> StreetImage:
        """Image ``k`` (exposed at relative time camera_phase_s + k / rate)."""
        import cv2

        sc, world = self.sc, self.world
        tau = sc.timing.camera_phase_s + k / sc.camera.rate_hz
        W, H, fx, fy, cx, cy, mx, my = self._virtual()
        Twc = self.traj.T_world_car(sc.timing.start_stamp_s + tau) @ self.T_car_camera
        Rwc, o = Twc[:3, :3], Twc[:3, 3]
        uu = (np.arange(W) - cx) / fx
        vv = (np.arange(H) - cy) / fy
        # world ray of every pixel (z-depth parametrisation: t = depth along the optical axis)
        R32 = Rwc.astype(np.float32)
        dw = (R32[:, 0][None, None, :] * uu.astype(np.float32)[None, :, None]
              + R32[:, 1][None, None, :] * vv.astype(np.float32)[:, None, None] + R32[:, 2][None, None, :])
        zbuf = np.full((H, W), np.inf)
        pbuf = np.full((H, W), -1, dtype=np.int64)
        down = dw[..., 2] < -1e-9
        zbuf[down] = -o[2] / dw[..., 2][down]
        pbuf[down] = 0
        inst = world.instantiate(tau)
        rects = self._rects(inst, Rwc, o, W, H, fx, fy, cx, cy)
        o1 = o[None, :]
        for typ, rows, r4 in rects:
            P = inst[typ]
            pids = world.prims[typ].pid
            for row, (u0, u1, v0, v1) in zip(rows, r4):
                d = dw[v0:v1, u0:u1].reshape(-1, 3)
                t = _HIT[typ](o1, d, P[row:row + 1])[:, 0].reshape(v1 - v0, u1 - u0)
                zb = zbuf[v0:v1, u0:u1]
                better = t < zb
                if better.any():
                    zb[better] = t[better]
                    pbuf[v0:v1, u0:u1][better] = pids[row]
        # shading
        img = np.empty((H, W, 3), dtype=np.float32)
        flat_p = pbuf.reshape(-1)
        hit = flat_p >= 0
        hidx = np.flatnonzero(hit)
        dflat = dw.reshape(-1, 3)
        zflat = zbuf.reshape(-1)
        dsel = dflat[hidx]
        zsel = zflat[hidx].astype(np.float32)
        pts = o.astype(np.float32)[None, :] + zsel[:, None] * dsel
        pid = flat_p[hidx]
        nrm, uv, face = _surface(world, inst, pts, pid)
        dlen = np.sqrt(np.einsum("ij,ij->i", dsel, dsel))
        dn = dsel / dlen[:, None]
        cosi = np.abs(np.einsum("ij,ij->i", nrm, dn))
        foot = zsel / np.float32(fx) / np.maximum(cosi, np.float32(0.15))
        alb = _albedo(world, pid, uv, face, pts, foot)
        sa, se = np.radians(sc.sun_azimuth_deg), np.radians(sc.sun_elevation_deg)
        sun = np.array([np.cos(se) * np.cos(sa), np.cos(se) * np.sin(sa), np.sin(se)])
        ns = nrm @ sun.astype(np.float32)
        ns = np.where(np.einsum("ij,ij->i", nrm, dn) > 0, -ns, ns)  # normals towards the viewer
        shade = (0.45 + 0.6 * np.clip(ns, 0, 1)).astype(np.float32)
        dist = zsel * dlen
        fog = np.exp(-dist / 600.0).astype(np.float32)[:, None]
        sky_c = np.array([0.92, 0.82, 0.72], np.float32)
        flat_img = img.reshape(-1, 3)
        flat_img[hidx] = (alb * shade[:, None]) * fog + sky_c * (1 - fog)
        sidx = np.flatnonzero(~hit)
        if sidx.size:
            el = dflat[sidx, 2] / np.linalg.norm(dflat[sidx], axis=1)
            g = np.clip(el, 0, 1)[:, None].astype(np.float32)
            flat_img[sidx] = sky_c * (1 - g) + np.array([0.85, 0.6, 0.4], np.float32) * g
        dyn = np.zeros(H * W, dtype=bool)
        dyn[hidx] = world.dynamic_arr[pid]
        dyn = dyn.reshape(H, W)
        if mx is not None:
            img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            dyn = cv2.remap(dyn.astype(np.uint8), mx, my, cv2.INTER_NEAREST) > 0
            if with_labels:
                pbuf = cv2.remap(pbuf.astype(np.float32), mx, my, cv2.INTER_NEAREST).astype(np.int64)
        c = sc.camera
        if c.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), c.blur_sigma_px)
        gain = float(self.rng.uniform(0.95, 1.05))
        out = img * np.float32(255.0 * gain) + np.float32(0.5)
        if c.noise_sigma > 0:
            out += np.float32(c.noise_sigma) * self.rng.standard_normal(img.shape, dtype=np.float32)
        out = np.clip(out, 0, 255).astype(np.uint8)
        if c.mono:
            out = cv2.cvtColor(out, cv2.COLOR_BGR2GRAY)
        stamp = sc.timing.start_stamp_s + tau + sc.timing.time_offset_s
        return StreetImage(stamp_s=float(stamp), image=out, dynamic_mask=dyn,
                           exposure_s=float(sc.timing.start_stamp_s + tau),
                           label=pbuf.astype(np.int32) if with_labels else None)

    @staticmethod
    def _rects(inst, Rwc, o, W, H, fx, fy, cx, cy, near=0.05):
        """Per type: rows and pixel rectangles (u0, u1, v0, v1) of primitives in view (exact hull of
        the near-clipped bounding box, so partly-behind primitives are not over-covered)."""
        out = []
        sgn = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.sum(sgn[a] != sgn[b]) == 1]
        ea, eb = np.array([e[0] for e in edges]), np.array([e[1] for e in edges])
        for typ in (BOX, CYL, ELL):
            P = inst[typ]
            if P.shape[0] == 0:
                continue
            if typ == BOX:
                c, s = np.cos(P[:, 3]), np.sin(P[:, 3])
                lx, ly, lz = sgn[None, :, 0] * P[:, 4:5], sgn[None, :, 1] * P[:, 5:6], sgn[None, :, 2] * P[:, 6:7]
                C = np.stack([P[:, 0:1] + c[:, None] * lx - s[:, None] * ly,
                              P[:, 1:2] + s[:, None] * lx + c[:, None] * ly, P[:, 2:3] + lz], 2)
            elif typ == CYL:
                C = np.stack([P[:, 0:1] + sgn[None, :, 0] * P[:, 4:5], P[:, 1:2] + sgn[None, :, 1] * P[:, 4:5],
                              np.where(sgn[None, :, 2] < 0, P[:, 2:3], P[:, 3:4])], 2)
            else:
                C = np.stack([P[:, 0:1] + sgn[None, :, 0] * P[:, 3:4], P[:, 1:2] + sgn[None, :, 1] * P[:, 3:4],
                              P[:, 2:3] + sgn[None, :, 2] * P[:, 4:5]], 2)
            Q = (C - o) @ Rwc  # camera frame (m, 8, 3)
            z = Q[..., 2]
            za, zb = z[:, ea], z[:, eb]
            cross = (za - near) * (zb - near) < 0
            with np.errstate(divide="ignore", invalid="ignore"):
                f = np.where(cross, (near - za) / (zb - za), 0.0)
            X = Q[:, ea] + f[..., None] * (Q[:, eb] - Q[:, ea])
            pts = np.concatenate([Q, X], axis=1)
            valid = np.concatenate([z >= near, cross], axis=1)
            zz = np.where(valid, np.maximum(pts[..., 2], near), 1.0)
            u = np.where(valid, fx * pts[..., 0] / zz + cx, np.nan)
            v = np.where(valid, fy * pts[..., 1] / zz + cy, np.nan)
            anyv = valid.any(axis=1)
            if not anyv.any():
                continue
            rows = np.flatnonzero(anyv)
            with np.errstate(invalid="ignore"):
                u0 = np.clip(np.floor(np.nanmin(u[rows], axis=1)) - 1, 0, W).astype(int)
                u1 = np.clip(np.ceil(np.nanmax(u[rows], axis=1)) + 2, 0, W).astype(int)
                v0 = np.clip(np.floor(np.nanmin(v[rows], axis=1)) - 1, 0, H).astype(int)
                v1 = np.clip(np.ceil(np.nanmax(v[rows], axis=1)) + 2, 0, H).astype(int)
            ok = (u1 > u0) & (v1 > v0)
            out.append((typ, rows[ok], np.stack([u0, u1, v0, v1], 1)[ok]))
        return out

    # -- timeline -------------------------------------------------------------------------------
    def n_sweeps(self) -> int:
        return int(np.floor(self.sc.timing.duration_s * float(self.preset.rate_hz) + 1e-9))

    def n_images(self) -> int:
        tm = self.sc.timing
        return max(int(np.floor((tm.duration_s - tm.camera_phase_s) * self.sc.camera.rate_hz + 1e-9)) + 1, 0) \
            if tm.camera_phase_s <= tm.duration_s else 0

    def events(self) -> list:
        """[(stamp_s, kind, index)] in stamp order (kind 'sweep' | 'image'; images on the camera clock)."""
        tm = self.sc.timing
        ev = [(tm.start_stamp_s + j / float(self.preset.rate_hz), "sweep", j) for j in range(self.n_sweeps())]
        ev += [(tm.start_stamp_s + tm.camera_phase_s + k / self.sc.camera.rate_hz + tm.time_offset_s, "image", k)
               for k in range(self.n_images())]
        ev.sort(key=lambda e: (e[0], e[1]))
        return ev

    def run_header(self) -> DriveSimRun:
        sc = self.sc
        return DriveSimRun(
            camera=self.camera, T_camera_lidar=self.T_camera_lidar.copy(), lidar=self.preset, sweeps=[], images=[],
            T_world_lidar=self.traj, time_offset_s=float(sc.timing.time_offset_s), speed_set=sc.speed_set,
            landmarks=[dict(lm) for lm in self.world.landmarks],
            frames={"lidar_frame": "lidar", "camera_frame": "camera_optical_frame", "world_frame": "world"},
            scenario=sc, world=self.world, T_car_lidar=self.T_car_lidar.copy(),
            T_car_camera=self.T_car_camera.copy(), mean_speed_kmh=float(np.mean(self.traj.v) * 3.6))


def iter_drive(scenario=None, rng=None, duration_s: float | None = None, image_scale: float = 1.0,
               preset=None, with_labels: bool = False) -> Iterator:
    """First yields the :class:`DriveSimRun` header (empty sweeps/images), then
    ``(stamp_s, 'sweep' | 'image', StreetSweep | StreetImage)`` in stamp order."""
    sim = DriveSimulator(scenario, rng, image_scale=image_scale, preset=preset, duration_s=duration_s)
    yield sim.run_header()
    for stamp, kind, i in sim.events():
        yield stamp, kind, (sim.sweep(i, with_labels) if kind == "sweep" else sim.image(i, with_labels))


def simulate_drive(scenario=None, rng=None, duration_s: float | None = None, image_scale: float = 1.0,
                   preset=None, with_labels: bool = False) -> DriveSimRun:
    """Simulate a whole drive in memory (see :func:`iter_drive` to stream a long one).

    ``scenario``: StreetScenario, dict or YAML path (None: default); ``rng``: drives the layout,
    the speed/weave phases and all noise (default ``np.random.default_rng(scenario.seed)``);
    ``duration_s`` overrides ``timing.duration_s``; ``image_scale`` scales the camera resolution
    (intrinsics scaled accordingly); ``preset`` overrides the LiDAR preset object;
    ``with_labels`` adds per-point / per-pixel primitive ids (memory hungry at full size)."""
    it = iter_drive(scenario, rng, duration_s, image_scale, preset, with_labels)
    run = next(it)
    for _, kind, item in it:
        (run.sweeps if kind == "sweep" else run.images).append(item)
    return run


__all__ = ["DriveSimRun", "DriveSimulator", "EgoTrajectory", "StreetCamera", "StreetFrame", "StreetImage",
           "StreetLayout", "StreetLidar", "StreetMotion", "StreetMount", "StreetScenario", "StreetSweep",
           "StreetTiming", "StreetTraffic", "StreetWorld", "default_street_scenario", "iter_drive",
           "load_street_scenario", "sample_street_family", "simulate_drive"]
