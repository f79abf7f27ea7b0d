"""Spinning multi-beam LiDAR presets and the ray generator (ROS-free).

A :class:`LidarPreset` describes one sensor model: per-ring elevation table, azimuth step,
rotation rate and direction, per-laser firing delays, range noise, dropouts, beam
divergence (for the mixed-return model at object edges), the intensity scale the driver
publishes, and which PointCloud2 fields the driver fills (real drivers differ: some publish
no ``time``, Ouster numbers rings from the top beam down).

LiDAR frame: x forward, y left, z up. ``azimuth`` is the angle about +z measured from +x
towards +y (so +90 deg is left); ``elevation`` is positive upwards. A sweep starts at
``start_azimuth_deg`` and turns by ``spin`` (-1: clockwise seen from above, as Velodyne,
RoboSense and Ouster sensors turn). Per-point ``time`` is seconds after the sweep start.

``PRESETS`` keys: ``rs16`` (RoboSense RS-LiDAR-16, paper 000 Table 1), ``vlp16``, ``vlp32``
(VLP-32C), ``hdl64`` (HDL-64E S2), ``os1_64`` (Ouster OS1-64 gen 1 like).

Intensity: simulators compute a *unit reflectance-like value* in [0, 1] per return, where a
retro-reflective sheet seen head-on gives ~0.99 and diffuse surfaces 0.02-0.45, and
:meth:`LidarPreset.to_intensity_scale` maps it onto the preset's scale ("uint8": 0-255 whole
numbers, "unit": 0-1, "uint16": 0-65535 whole numbers). ``intensity_threshold`` is the value on
that scale above which a return counts as retro-reflective (250 on the 0-255 scale, as in
paper 000; 0.98 of full scale on the others).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

INTENSITY_SCALES = {"uint8": 255.0, "unit": 1.0, "uint16": 65535.0}
ALL_FIELDS = ("x", "y", "z", "intensity", "ring", "time")


@dataclass(frozen=True)
class LidarPreset:
    """One spinning LiDAR model. Rings are numbered by ``ring_order`` of the elevation table.

    ``elevations_deg`` is listed in ascending elevation; ring ``r`` is the r-th entry when
    ``ring_order == 'ascending'`` (Velodyne, RoboSense drivers) and the r-th from the top when
    ``'descending'`` (Ouster drivers: ring 0 is the highest beam). ``fire_order`` (per entry of
    ``elevations_deg``) gives the slot in which that laser fires inside one column; its time
    offset is ``fire_order * laser_fire_dt_s``. ``azimuth_offsets_deg`` (per entry, optional)
    are fixed horizontal beam offsets (Ouster's staggered beam azimuths).

    Noise and divergence defaults follow the datasheets; ``range_sigma_m`` reads a datasheet
    "+/-3 cm" as 2 sigma (15 mm). Divergences are full angles in radians.
    """

    name: str
    model: str
    elevations_deg: tuple
    azimuth_step_deg: float
    rate_hz: float = 10.0
    spin: int = -1
    start_azimuth_deg: float = 180.0
    fire_order: tuple = ()
    laser_fire_dt_s: float = 0.0
    azimuth_offsets_deg: tuple = ()
    ring_order: str = "ascending"
    range_min_m: float = 0.4
    range_max_m: float = 100.0
    range_sigma_m: float = 0.015
    range_resolution_m: float = 0.0
    dropout_prob: float = 0.003
    divergence_h_rad: float = 3.0e-3
    divergence_v_rad: float = 1.5e-3
    intensity_scale: str = "uint8"
    intensity_sigma_unit: float = 0.01
    fields: tuple = ALL_FIELDS

    def __post_init__(self) -> None:
        if self.intensity_scale not in INTENSITY_SCALES:
            raise ValueError(f"intensity_scale must be one of {sorted(INTENSITY_SCALES)}, "
                             f"got {self.intensity_scale!r}")
        if self.ring_order not in ("ascending", "descending"):
            raise ValueError("ring_order must be 'ascending' or 'descending'")
        if self.azimuth_step_deg <= 0 or self.rate_hz <= 0:
            raise ValueError("azimuth_step_deg and rate_hz must be > 0")
        if len(self.elevations_deg) < 1:
            raise ValueError("a LiDAR needs at least one beam")
        if list(self.elevations_deg) != sorted(self.elevations_deg):
            raise ValueError("elevations_deg must be listed in ascending order")
        for nm in ("fire_order", "azimuth_offsets_deg"):
            v = getattr(self, nm)
            if len(v) not in (0, len(self.elevations_deg)):
                raise ValueError(f"{nm} needs one value per beam ({len(self.elevations_deg)}), got {len(v)}")
        bad = [f for f in self.fields if f not in ALL_FIELDS]
        if bad or not {"x", "y", "z"} <= set(self.fields):
            raise ValueError(f"fields must contain x, y, z and only {ALL_FIELDS}; got {self.fields}")

    # -- derived -----------------------------------------------------------------------------
    @property
    def n_rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def n_columns(self) -> int:
        return round(360.0 / self.azimuth_step_deg)

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def intensity_max(self) -> float:
        return INTENSITY_SCALES[self.intensity_scale]

    @property
    def intensity_threshold(self) -> float:
        """Retro-reflector threshold on the preset's scale (250 on 0-255 as in paper 000)."""
        if self.intensity_scale == "uint8":
            return 250.0
        if self.intensity_scale == "uint16":
            return float(round(0.98 * self.intensity_max))
        return 0.98

    def has(self, name: str) -> bool:
        return name in self.fields

    def ring_elevations_deg(self) -> np.ndarray:
        """(n_rings,) elevation of ring 0, 1, ... in the driver's ring numbering."""
        e = np.asarray(self.elevations_deg, dtype=float)
        return e if self.ring_order == "ascending" else e[::-1].copy()

    def replace(self, **changes) -> LidarPreset:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    # -- rays ---------------------------------------------------------------------------------
    def ray_directions(self, azimuth_range_deg: tuple | None = None):
        """All beams of one sweep, in firing order (column by column).

        Returns ``(dirs (N,3) unit vectors in the LiDAR frame, ring (N,) uint16,
        azimuth_rad (N,) in (-pi, pi], time_s (N,) after the sweep start)``.
        ``azimuth_range_deg=(lo, hi)`` keeps only beams whose azimuth lies in [lo, hi]
        (degrees, the driver's field-of-view crop; lo > hi wraps through 180).
        """
        nb, nc = self.n_rings, self.n_columns
        elev = np.deg2rad(np.asarray(self.elevations_deg, dtype=float))
        ring_of_beam = np.arange(nb) if self.ring_order == "ascending" else np.arange(nb)[::-1]
        fire = np.asarray(self.fire_order, dtype=float) if self.fire_order else np.zeros(nb)
        az_off = np.deg2rad(np.asarray(self.azimuth_offsets_deg, dtype=float)) \
            if self.azimuth_offsets_deg else np.zeros(nb)
        col = np.arange(nc, dtype=float)
        col_az = np.deg2rad(self.start_azimuth_deg) + self.spin * col * np.deg2rad(self.azimuth_step_deg)
        col_t = col * (self.period_s / nc)
        # (nc, nb) grids, column-major firing order
        az = col_az[:, None] + az_off[None, :]
        t = col_t[:, None] + fire[None, :] * self.laser_fire_dt_s
        el = np.broadcast_to(elev[None, :], az.shape)
        ring = np.broadcast_to(ring_of_beam[None, :], az.shape)
        az = np.angle(np.exp(1j * az)).ravel()
        el = el.ravel()
        ce = np.cos(el)
        dirs = np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=1)
        ring = ring.ravel().astype(np.uint16)
        t = t.ravel()
        if azimuth_range_deg is not None:
            keep = azimuth_mask(az, azimuth_range_deg)
            dirs, ring, az, t = dirs[keep], ring[keep], az[keep], t[keep]
        return dirs, ring, az, t

    # -- measurement model ---------------------------------------------------------------------
    def to_intensity_scale(self, unit: np.ndarray) -> np.ndarray:
        """Unit reflectance-like values [0, 1] -> the preset's intensity scale (float32)."""
        v = np.clip(np.asarray(unit, dtype=float), 0.0, 1.0) * self.intensity_max
        if self.intensity_scale != "unit":
            v = np.round(v)
        return v.astype(np.float32)

    def finish_sweep(self, dirs: np.ndarray, ring: np.ndarray, time_s: np.ndarray,
                     range_m: np.ndarray, unit_intensity: np.ndarray,
                     rng: np.random.Generator, range_sigma_m: float | None = None,
                     dropout_prob: float | None = None, ring_bias_m: np.ndarray | None = None,
                     intensity_sigma_unit: float | None = None, fields: tuple | None = None) -> dict:
        """Turn true ranges (NaN/inf = no hit) into a driver-like cloud dict.

        Adds Gaussian range noise (``range_sigma_m``, default the preset's), an optional fixed
        per-ring range bias (``ring_bias_m[ring]``), quantises to ``range_resolution_m``,
        drops returns outside [range_min, range_max] and a random ``dropout_prob`` fraction,
        adds intensity noise and maps intensity to the preset's scale. Returns
        ``{'x','y','z'[, 'intensity', 'ring', 'time']}`` (float32 / uint16 / float32 s) with the
        keys in ``fields`` (default the preset's) and, under ``'_index'``, the indices of the
        kept rays (for simulator bookkeeping; not a PointCloud2 field).
        """
        sig = self.range_sigma_m if range_sigma_m is None else float(range_sigma_m)
        pdrop = self.dropout_prob if dropout_prob is None else float(dropout_prob)
        isig = self.intensity_sigma_unit if intensity_sigma_unit is None else float(intensity_sigma_unit)
        r = np.asarray(range_m, dtype=float)
        n = r.shape[0]
        rn = r + sig * rng.standard_normal(n)
        if ring_bias_m is not None:
            rn = rn + np.asarray(ring_bias_m, dtype=float)[np.asarray(ring, dtype=int)]
        if self.range_resolution_m > 0:
            rn = np.round(rn / self.range_resolution_m) * self.range_resolution_m
        ok = np.isfinite(r) & (rn >= self.range_min_m) & (rn <= self.range_max_m)
        if pdrop > 0:
            ok &= rng.random(n) >= pdrop
        idx = np.flatnonzero(ok)
        p = dirs[idx] * rn[idx, None]
        out = {"x": p[:, 0].astype(np.float32), "y": p[:, 1].astype(np.float32),
               "z": p[:, 2].astype(np.float32)}
        flds = self.fields if fields is None else fields
        if "intensity" in flds:
            ui = np.asarray(unit_intensity, dtype=float)[idx]
            ui = ui + isig * rng.standard_normal(idx.size)
            out["intensity"] = self.to_intensity_scale(ui)
        if "ring" in flds:
            out["ring"] = np.asarray(ring)[idx].astype(np.uint16)
        if "time" in flds:
            out["time"] = np.asarray(time_s)[idx].astype(np.float32)
        out["_index"] = idx
        return out


def azimuth_mask(azimuth_rad: np.ndarray, azimuth_range_deg: tuple) -> np.ndarray:
    """Beams whose azimuth lies in [lo, hi] degrees (lo > hi wraps through +/-180)."""
    lo, hi = (float(a) for a in azimuth_range_deg)
    a = np.rad2deg(np.asarray(azimuth_rad, dtype=float))
    lo = (lo + 180.0) % 360.0 - 180.0
    hi = (hi + 180.0) % 360.0 - 180.0
    if lo <= hi:
        return (a >= lo) & (a <= hi)
    return (a >= lo) | (a <= hi)


def _hdl64_elevations() -> tuple:
    upper = np.linspace(2.0, -8.33, 32)     # upper block: ~1/3 deg spacing
    lower = np.linspace(-8.83, -24.33, 32)  # lower block: ~1/2 deg spacing
    return tuple(float(round(v, 4)) for v in sorted(np.concatenate([upper, lower])))


_VLP16_FIRE_ELEV = (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)
_VLP32_ELEV = (-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667,
               -3.333, -3.0, -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0,
               0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0)


def _fire_order_from(fire_elev: tuple, elev_sorted: tuple) -> tuple:
    """Slot in which each (sorted) beam fires, given the elevations in firing order."""
    pos = {float(e): i for i, e in enumerate(fire_elev)}
    return tuple(pos[float(e)] for e in elev_sorted)


def _os1_elevations() -> tuple:
    return tuple(float(round(v, 4)) for v in np.linspace(-16.611, 16.611, 64))


PRESETS: dict[str, LidarPreset] = {
    # Paper 000 Table 1: 16 channels, +/-3 cm, 0.2 deg at 10 Hz, emission angle 7.4 x 0.7 mrad.
    # (Table 1's "-25..+15 deg, 0.33 deg" vertical figures are the RS-LiDAR-32's; the RS-16
    # has 16 beams at 2 deg spacing over -15..+15 deg, which is what 16 channels allow.)
    "rs16": LidarPreset(
        name="rs16", model="RoboSense RS-LiDAR-16",
        elevations_deg=tuple(float(e) for e in range(-15, 16, 2)),
        azimuth_step_deg=0.2, rate_hz=10.0,
        fire_order=tuple(range(16)), laser_fire_dt_s=3.0e-6,
        range_min_m=0.4, range_max_m=150.0, range_sigma_m=0.015, range_resolution_m=0.005,
        dropout_prob=0.003, divergence_h_rad=7.4e-3, divergence_v_rad=0.7e-3,
        intensity_scale="uint8", fields=ALL_FIELDS),
    "vlp16": LidarPreset(
        name="vlp16", model="Velodyne VLP-16",
        elevations_deg=tuple(float(e) for e in range(-15, 16, 2)),
        azimuth_step_deg=0.2, rate_hz=10.0,
        fire_order=_fire_order_from(_VLP16_FIRE_ELEV, tuple(range(-15, 16, 2))),
        laser_fire_dt_s=2.304e-6,
        range_min_m=0.5, range_max_m=100.0, range_sigma_m=0.015, range_resolution_m=0.002,
        dropout_prob=0.003, divergence_h_rad=3.0e-3, divergence_v_rad=1.5e-3,
        intensity_scale="uint8", fields=ALL_FIELDS),
    "vlp32": LidarPreset(
        name="vlp32", model="Velodyne VLP-32C",
        elevations_deg=_VLP32_ELEV, azimuth_step_deg=0.2, rate_hz=10.0,
        fire_order=tuple(i // 2 for i in range(32)), laser_fire_dt_s=2.304e-6,
        range_min_m=0.5, range_max_m=200.0, range_sigma_m=0.015, range_resolution_m=0.004,
        dropout_prob=0.004, divergence_h_rad=3.0e-3, divergence_v_rad=1.5e-3,
        intensity_scale="unit", fields=ALL_FIELDS),
    # Older driver layout: x, y, z, intensity, ring (no per-point time).
    "hdl64": LidarPreset(
        name="hdl64", model="Velodyne HDL-64E S2",
        elevations_deg=_hdl64_elevations(), azimuth_step_deg=0.1728, rate_hz=10.0,
        range_min_m=0.9, range_max_m=120.0, range_sigma_m=0.01, range_resolution_m=0.002,
        dropout_prob=0.005, divergence_h_rad=2.0e-3, divergence_v_rad=2.0e-3,
        intensity_scale="uint8", fields=("x", "y", "z", "intensity", "ring")),
    # Ouster: all beams of a column fire together, staggered beam azimuths, ring 0 = top beam,
    # 16-bit intensity.
    "os1_64": LidarPreset(
        name="os1_64", model="Ouster OS1-64 (gen 1) like, 1024x10",
        elevations_deg=_os1_elevations(), azimuth_step_deg=360.0 / 1024, rate_hz=10.0,
        azimuth_offsets_deg=tuple((3.164, 1.055, -1.055, -3.164)[i % 4] for i in range(64)),
        ring_order="descending",
        range_min_m=0.8, range_max_m=120.0, range_sigma_m=0.015, range_resolution_m=0.003,
        dropout_prob=0.005, divergence_h_rad=3.1e-3, divergence_v_rad=3.1e-3,
        intensity_scale="uint16", fields=ALL_FIELDS),
}


# other spellings accepted by get_preset (command lines)
ALIASES = {"os1": "os1_64", "vlp32c": "vlp32", "hdl64e": "hdl64", "rs_lidar_16": "rs16"}


def get_preset(name: str) -> LidarPreset:
    """A preset by key; raises ValueError naming the known keys."""
    try:
        return PRESETS[ALIASES.get(name, name)]
    except KeyError:
        raise ValueError(f"unknown LiDAR preset {name!r}; known: {', '.join(PRESETS)}") from None


__all__ = ["ALIASES", "ALL_FIELDS", "INTENSITY_SCALES", "PRESETS", "LidarPreset", "azimuth_mask", "get_preset"]
