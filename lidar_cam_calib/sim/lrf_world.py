"""Synthetic world for the ``lrf`` method (paper 003): folded board, 2D laser, stereo depth camera.

Frames (``T_a_b`` maps points from b into a, 4x4):

* ``world``  (``map``): floor at z = 0, z up; the room is an axis-aligned box.
* ``agv``    (``base_link``): x forward, y left, z up, on the floor.
* ``laser``  (``laser``): x forward, y left, z up; the scan plane is the laser's z = 0 plane.
  Beam k has angle ``angle_min + k * angle_increment`` counter-clockwise about +z from +x
  (ROS LaserScan convention; with the defaults angle_min = -pi, so beam 0 looks backwards).
* ``camera`` (``camera_depth_optical_frame``): left camera of the stereo pair, optical
  (z forward, x right, y down). Depth and colour images are in this frame.
* ``camera_right``: right camera, ``baseline_m`` along the left camera's +x.
* ``board``: folded board, see :class:`FoldedBoard`.

Truth: ``T_camera_laser = inv(T_agv_camera) @ T_agv_laser``.

Everything is numpy and vectorised: a 360 deg scan (8571 beams) plus a 640x360 depth image take
a few tens of milliseconds.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from lidar_cam_calib.core.camera import CameraModel
from lidar_cam_calib.core.geometry import R_BODY_OPTICAL, R_from_rpy, inv_T, make_T, transform_points
from lidar_cam_calib.sim.scenario import Scenario, load_scenario

# Label values used in the per-pixel / per-beam label arrays.
LABEL_NONE = -1
FACE_BASE, FACE_ABC, FACE_ACD, FACE_STAND = 0, 1, 2, 3
FACE_NAMES = ("base", "abc", "acd", "stand")
LABEL_ROOM = 10  # + 2 * axis + (1 if the ray leaves through the 'hi' side): 10..15


# ----------------------------------------------------------------------------------------------
# Board
# ----------------------------------------------------------------------------------------------
class FoldedBoard:
    """Folded calibration board of paper 003 (Fig. 3/4), geometry in the board frame (metres).

    Board frame: origin at the bottom-centre of the base rectangle PBDQ, x to the right as seen
    from in front of the board, y up along the board, z out of the front face (towards the
    viewer). Vertices::

        P = (-w/2, 0, 0)  bottom-left      TL = (-w/2, h, 0)  top-left
        Q = ( w/2, 0, 0)  bottom-right     TR = ( w/2, h, 0)  top-right
        A = (a_x, a_y, 0), B = (b_x, b_y, 0), D = (d_x, d_y, 0) anywhere on the back
        rectangle (default: A bottom-centre, B = TL, D = TR; B is the left one)
        C = (c_x, c_y, c_z) apex, c_z > 0 out of the base, above or below A

    Faces (index = label): 0 'base' = rectangle PBDQ (plane z = 0), 1 'abc' = triangle ABC (left
    flap), 2 'acd' = triangle ACD (right flap). Edges: AB = base/abc, AC = abc/acd,
    AD = acd/base. A horizontal scan at height y crosses it as E-F-G-H-I from left to right
    (viewer's left): E..F on the base, F on AB, F..G on ABC, G on AC, G..H on ACD, H on AD,
    H..I on the base. An optional 'stand' (label 3) is a rectangle from the top edge down and
    back to ``z = -stand_depth_m`` at y = 0 (only visible from behind).
    """

    def __init__(self, width_m: float = 1.0, height_m: float = 1.0,
                 a_xy_m: Sequence[float] = (0.0, 0.0),
                 c_xyz_m: Sequence[float] = (0.0, 1.0, 0.6), stand_depth_m: float = 0.0,
                 b_xy_m: Optional[Sequence[float]] = None, d_xy_m: Optional[Sequence[float]] = None):
        self.width_m = float(width_m)
        self.height_m = float(height_m)
        w2, h = 0.5 * self.width_m, self.height_m
        b = (-w2, h) if not b_xy_m else (float(b_xy_m[0]), float(b_xy_m[1]))
        d = (w2, h) if not d_xy_m else (float(d_xy_m[0]), float(d_xy_m[1]))
        self.vertices = {
            "P": np.array([-w2, 0.0, 0.0]), "TL": np.array([-w2, h, 0.0]),
            "TR": np.array([w2, h, 0.0]), "Q": np.array([w2, 0.0, 0.0]),
            "B": np.array([b[0], b[1], 0.0]), "D": np.array([d[0], d[1], 0.0]),
            "A": np.array([float(a_xy_m[0]), float(a_xy_m[1]), 0.0]),
            "C": np.array([float(c) for c in c_xyz_m]),
        }
        self.stand_depth_m = float(stand_depth_m)
        if abs(self.vertices["C"][1] - self.vertices["A"][1]) < 1e-3:
            raise ValueError("apex C must lie above or below A (c_y != a_y) so a horizontal scan crosses AC")
        n = self.planes()[0]
        # Any three faces must be non-parallel (linearly independent normals).
        if abs(np.linalg.det(n)) < 1e-3:
            raise ValueError("folded board faces are (nearly) parallel; move the apex C")

    @classmethod
    def from_config(cls, cfg) -> "FoldedBoard":
        return cls(cfg.width_m, cfg.height_m, cfg.a_xy_m, cfg.c_xyz_m, cfg.stand_depth_m,
                   getattr(cfg, "b_xy_m", None), getattr(cfg, "d_xy_m", None))

    def faces(self, include_stand: bool = True) -> list[np.ndarray]:
        """Face polygons in the board frame, index = label: [base PBDQ, ABC, ACD(, stand)].

        Each is a (k, 3) array ordered counter-clockwise around its front normal."""
        v = self.vertices
        out = [np.stack([v["P"], v["Q"], v["TR"], v["TL"]])]
        for tri in (np.stack([v["A"], v["C"], v["B"]]), np.stack([v["A"], v["D"], v["C"]])):
            out.append(tri if _newell_normal(tri)[2] > 0 else tri[::-1].copy())
        if include_stand and self.stand_depth_m > 0:
            s = self.stand_depth_m
            w2 = 0.5 * self.width_m
            out.append(np.array([[w2, self.height_m, 0.0], [w2, 0.0, -s],
                                 [-w2, 0.0, -s], [-w2, self.height_m, 0.0]]))
        return out

    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Planes of (base, ABC, ACD) in the board frame: unit normals n (3, 3) pointing to the
        front (board +z side) and offsets d (3,) with ``n @ p + d = 0`` (paper eq. 6 form)."""
        normals, offsets = [], []
        for poly in self.faces(include_stand=False):
            nrm = _newell_normal(poly)
            normals.append(nrm)
            offsets.append(0.0 - float(nrm @ poly[0]) + 0.0)
        return np.array(normals), np.array(offsets)

    def edge_lines(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Edges AB, AC, AD as (point A, unit direction towards B/C/D) in the board frame.

        AB = base ∩ ABC, AC = ABC ∩ ACD, AD = ACD ∩ base."""
        v = self.vertices
        out = {}
        for name in ("B", "C", "D"):
            d = v[name] - v["A"]
            out["A" + name] = (v["A"].copy(), d / np.linalg.norm(d))
        return out

    def corners(self) -> np.ndarray:
        """(6, 3) rectangle corners P, TL, TR, Q, then A, C in the board frame."""
        return np.stack([self.vertices[k] for k in ("P", "TL", "TR", "Q", "A", "C")])


def _newell_normal(poly: np.ndarray) -> np.ndarray:
    """Unit normal of a planar polygon, right-handed with its vertex order (Newell's method)."""
    nxt = np.roll(poly, -1, axis=0)
    n = np.array([np.sum((poly[:, 1] - nxt[:, 1]) * (poly[:, 2] + nxt[:, 2])),
                  np.sum((poly[:, 2] - nxt[:, 2]) * (poly[:, 0] + nxt[:, 0])),
                  np.sum((poly[:, 0] - nxt[:, 0]) * (poly[:, 1] + nxt[:, 1]))])
    return n / np.linalg.norm(n)


# ----------------------------------------------------------------------------------------------
# Room (environment)
# ----------------------------------------------------------------------------------------------
@dataclass
class RoomBox:
    """Axis-aligned room in the world frame; rays start inside it and leave through a wall,
    the floor or the ceiling."""

    lo_m: np.ndarray
    hi_m: np.ndarray

    @classmethod
    def from_config(cls, cfg) -> "RoomBox":
        sx, sy, sz = (float(s) for s in cfg.size_m)
        cx, cy = (float(c) for c in cfg.center_xy_m)
        return cls(np.array([cx - sx / 2, cy - sy / 2, 0.0]), np.array([cx + sx / 2, cy + sy / 2, sz]))

    def exit(self, origin_w: np.ndarray, dirs_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray parameter t (origin + t * dir) where each ray leaves the box, and its label
        (LABEL_ROOM + 2 * axis + side). (N,) each; inf / LABEL_NONE for zero directions."""
        o = np.asarray(origin_w, dtype=float).reshape(1, 3)
        d = np.asarray(dirs_w, dtype=float)
        bound = np.where(d > 0, self.hi_m, self.lo_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d != 0, (bound - o) / d, np.inf)
        axis = np.argmin(t, axis=1)
        rows = np.arange(t.shape[0])
        tmin = t[rows, axis]
        label = LABEL_ROOM + 2 * axis + (d[rows, axis] > 0)
        label = np.where(np.isfinite(tmin), label, LABEL_NONE)
        return tmin, label


# ----------------------------------------------------------------------------------------------
# Laser
# ----------------------------------------------------------------------------------------------
class LaserModel:
    """2D laser range finder (defaults: Pepperl+Fuchs R2000: 360 deg, 0.042 deg, 0.1-30 m,
    sigma 12.5 mm).

    Rays lie in the laser's z = 0 plane; beam k points at ``angle_min_rad + k *
    angle_increment_rad`` counter-clockwise from +x about +z. Output ranges (float32, metres):
    +inf = no return or beyond range_max, -inf = closer than range_min (REP 117),
    NaN = dropped beam.
    """

    def __init__(self, angle_min_rad: float = -np.pi, angle_increment_rad: float = np.radians(360 / 8571),
                 n_beams: int = 8571, range_min_m: float = 0.1, range_max_m: float = 30.0,
                 range_sigma_m: float = 0.0125, dropout_fraction: float = 0.0):
        self.angle_min_rad = float(angle_min_rad)
        self.angle_increment_rad = float(angle_increment_rad)
        self.n_beams = int(n_beams)
        self.range_min_m = float(range_min_m)
        self.range_max_m = float(range_max_m)
        self.range_sigma_m = float(range_sigma_m)
        self.dropout_fraction = float(dropout_fraction)
        a = self.angles_rad
        self._dirs = np.stack([np.cos(a), np.sin(a)], axis=1)

    @classmethod
    def from_config(cls, cfg) -> "LaserModel":
        fov = np.radians(cfg.fov_deg)
        res = np.radians(cfg.resolution_deg)
        if cfg.fov_deg >= 360.0 - 1e-9:
            n = int(round(2 * np.pi / res))
            inc = 2 * np.pi / n
        else:
            n = int(np.floor(fov / res + 1e-9)) + 1
            inc = res
        return cls(np.radians(cfg.angle_min_deg), inc, n, cfg.range_min_m, cfg.range_max_m,
                   cfg.range_sigma_m, cfg.dropout_fraction)

    @property
    def angles_rad(self) -> np.ndarray:
        return self.angle_min_rad + self.angle_increment_rad * np.arange(self.n_beams)

    @property
    def angle_max_rad(self) -> float:
        return self.angle_min_rad + self.angle_increment_rad * (self.n_beams - 1)

    @property
    def directions(self) -> np.ndarray:
        """(n_beams, 2) unit beam directions (x, y) in the laser frame."""
        return self._dirs

    def cast(self, faces_laser: Sequence[np.ndarray], labels: Optional[Sequence[int]] = None,
             room: Optional[RoomBox] = None, T_world_laser: Optional[np.ndarray] = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Exact noise-free ranges (float64, inf = nothing hit) and per-beam labels.

        ``faces_laser``: convex planar polygons (k, 3) in the laser frame; each is cut by the
        z = 0 plane into a segment and intersected with every beam. ``room`` (world frame) with
        ``T_world_laser`` adds the walls / floor / ceiling."""
        n = self.n_beams
        rng_m = np.full(n, np.inf)
        lab = np.full(n, LABEL_NONE, dtype=np.int64)
        if room is not None:
            if T_world_laser is None:
                raise ValueError("room given without T_world_laser")
            R = T_world_laser[:3, :3]
            d3 = np.concatenate([self._dirs, np.zeros((n, 1))], axis=1) @ R.T
            rng_m, lab = room.exit(T_world_laser[:3, 3], d3)
        if labels is None:
            labels = list(range(len(faces_laser)))
        segs, seg_labels = [], []
        for poly, lb in zip(faces_laser, labels):
            seg = _polygon_cut_z0(np.asarray(poly, dtype=float))
            if seg is not None:
                segs.append(seg)
                seg_labels.append(lb)
        if segs:
            S = np.array(segs)                       # (M, 2, 2)
            p0 = S[:, 0, :]                          # (M, 2)
            e = S[:, 1, :] - p0                      # (M, 2)
            d = self._dirs                           # (N, 2)
            denom = d[:, :1] * e[None, :, 1] - d[:, 1:] * e[None, :, 0]   # d x e  (N, M)
            p0xe = p0[:, 0] * e[:, 1] - p0[:, 1] * e[:, 0]                  # (M,)
            p0xd = p0[None, :, 0] * d[:, 1:] - p0[None, :, 1] * d[:, :1]    # (N, M)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = p0xe[None, :] / denom
                s = p0xd / denom
            ok = (np.abs(denom) > 1e-15) & (t > 0) & (s >= 0) & (s <= 1)
            t = np.where(ok, t, np.inf)
            j = np.argmin(t, axis=1)
            tb = t[np.arange(n), j]
            closer = tb < rng_m
            rng_m = np.where(closer, tb, rng_m)
            lab = np.where(closer, np.asarray(seg_labels)[j], lab)
        return rng_m, lab

    def apply_noise(self, ranges_m: np.ndarray, rng: Optional[np.random.Generator],
                    noise: bool = True) -> np.ndarray:
        """Gaussian range noise, range limits and dropout; returns float32."""
        r = np.array(ranges_m, dtype=float)
        if noise and rng is not None and self.range_sigma_m > 0:
            fin = np.isfinite(r)
            r[fin] += rng.normal(0.0, self.range_sigma_m, int(fin.sum()))
        r[r > self.range_max_m] = np.inf
        r[r < self.range_min_m] = -np.inf
        if noise and rng is not None and self.dropout_fraction > 0:
            r[rng.random(r.size) < self.dropout_fraction] = np.nan
        return r.astype(np.float32)

    def scan(self, faces_laser: Sequence[np.ndarray], rng: Optional[np.random.Generator] = None,
             noise: bool = True, room: Optional[RoomBox] = None,
             T_world_laser: Optional[np.ndarray] = None) -> np.ndarray:
        """Simulated LaserScan ranges (float32, metres) of polygons in the laser frame."""
        r, _ = self.cast(faces_laser, room=room, T_world_laser=T_world_laser)
        return self.apply_noise(r, rng, noise)


def _polygon_cut_z0(poly: np.ndarray) -> Optional[np.ndarray]:
    """Segment (2, 2) (x, y endpoints) where a convex planar polygon meets the plane z = 0."""
    z = poly[:, 2]
    if np.all(z > 0) or np.all(z < 0) or np.all(z == 0):
        return None
    nxt = np.roll(poly, -1, axis=0)
    zn = nxt[:, 2]
    pts = [poly[z == 0, :2]]
    cross = (z * zn) < 0
    if np.any(cross):
        f = z[cross] / (z[cross] - zn[cross])
        pts.append(poly[cross, :2] + f[:, None] * (nxt[cross, :2] - poly[cross, :2]))
    P = np.concatenate(pts, axis=0)
    if P.shape[0] < 2:
        return None
    dd = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    i, j = np.unravel_index(np.argmax(dd), dd.shape)
    if dd[i, j] < 1e-12:
        return None
    return np.stack([P[i], P[j]])


# ----------------------------------------------------------------------------------------------
# Depth camera
# ----------------------------------------------------------------------------------------------
_FACE_BGR = {FACE_BASE: (235, 235, 235), FACE_ABC: (60, 60, 230), FACE_ACD: (230, 120, 40),
             FACE_STAND: (120, 160, 160)}
_ROOM_BGR = {0: (150, 170, 190), 1: (150, 170, 190), 2: (170, 150, 130), 3: (170, 150, 130),
             4: (90, 100, 100), 5: (200, 200, 200)}


class DepthCameraModel:
    """Stereo depth camera (ZED2i-like) rendering z-depth images (float32 metres, optical frame).

    Noise: Gaussian with sigma = k * z^2, ``k = sigma_disparity_px / (fx_stereo * baseline_m)``
    where ``fx_stereo = fx * stereo_width_px / width`` (matching resolution; default: the image's).
    Pixels outside [depth_min_m, depth_max_m], without a surface, or dropped get
    ``invalid_value`` (NaN by default, or 0).
    """

    def __init__(self, camera: CameraModel, depth_min_m: float = 0.3, depth_max_m: float = 20.0,
                 sigma_disparity_px: float = 0.1, baseline_m: float = 0.12,
                 dropout_fraction: float = 0.0, invalid_value: float = np.nan,
                 stereo_width_px: Optional[int] = None, k_override: float = 0.0,
                 quantise_mm: bool = False):
        self.camera = camera
        self.k_override = float(k_override)
        self.quantise_mm = bool(quantise_mm)
        self.stereo_width_px = int(stereo_width_px or camera.width)
        self.depth_min_m = float(depth_min_m)
        self.depth_max_m = float(depth_max_m)
        self.sigma_disparity_px = float(sigma_disparity_px)
        self.baseline_m = float(baseline_m)
        self.dropout_fraction = float(dropout_fraction)
        self.invalid_value = float(invalid_value)
        rays = np.asarray(camera.pixel_rays(), dtype=float)
        self._rays = rays / rays[:, 2:3]  # z = 1 exactly

    @property
    def k_noise(self) -> float:
        """sigma_z = k_noise * z^2 (1/m)."""
        if self.k_override > 0:
            return self.k_override
        fx_stereo = self.camera.fx * self.stereo_width_px / self.camera.width
        return self.sigma_disparity_px / (fx_stereo * self.baseline_m)

    def cast(self, faces_cam: Sequence[np.ndarray], labels: Optional[Sequence[int]] = None,
             room: Optional[RoomBox] = None, T_world_camera: Optional[np.ndarray] = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Exact z-depth (H*W,) float64 (inf = nothing) and labels of polygons in the camera frame."""
        rays = self._rays
        n = rays.shape[0]
        if room is not None:
            if T_world_camera is None:
                raise ValueError("room given without T_world_camera")
            z, lab = room.exit(T_world_camera[:3, 3], rays @ T_world_camera[:3, :3].T)
        else:
            z, lab = np.full(n, np.inf), np.full(n, LABEL_NONE, dtype=np.int64)
        if labels is None:
            labels = list(range(len(faces_cam)))
        for poly, lb in zip(faces_cam, labels):
            V = np.asarray(poly, dtype=float)
            nrm = _newell_normal(V)
            dpl = float(nrm @ V[0])
            if np.all(V[:, 2] > 1e-6):
                # Any ray through a convex polygon lies inside the bbox of its vertices' rays.
                xn, yn = V[:, 0] / V[:, 2], V[:, 1] / V[:, 2]
                m = ((rays[:, 0] >= xn.min()) & (rays[:, 0] <= xn.max())
                     & (rays[:, 1] >= yn.min()) & (rays[:, 1] <= yn.max()))
                idx = np.flatnonzero(m)
            elif np.all(V[:, 2] <= 0):
                continue
            else:
                idx = np.arange(n)
            if idx.size == 0:
                continue
            r = rays[idx]
            den = r @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                t = dpl / den
            p = r * t[:, None]
            E = np.roll(V, -1, axis=0) - V                 # edges (k, 3)
            M = np.cross(nrm[None, :], E)                  # inward edge normals (k, 3)
            s = p @ M.T - np.sum(M * V, axis=1)[None, :]   # (m, k) >= 0 inside
            ok = (np.abs(den) > 1e-12) & (t > 0) & np.all(s >= -1e-12, axis=1) & (t < z[idx])
            sel = idx[ok]
            z[sel] = t[ok]
            lab[sel] = lb
        return z, lab

    def apply_noise(self, z: np.ndarray, rng: Optional[np.random.Generator], noise: bool = True) -> np.ndarray:
        """Depth noise, range limits, dropout; returns (H, W) float32."""
        d = np.array(z, dtype=float)
        if noise and rng is not None and self.sigma_disparity_px > 0:
            fin = np.isfinite(d)
            zf = d[fin]
            d[fin] = zf + rng.normal(0.0, 1.0, zf.size) * (self.k_noise * zf * zf)
        bad = ~np.isfinite(d) | (d < self.depth_min_m) | (d > self.depth_max_m)
        if noise and rng is not None and self.dropout_fraction > 0:
            bad |= rng.random(d.size) < self.dropout_fraction
        if self.quantise_mm:
            d = np.round(d * 1000.0) / 1000.0
        d[bad] = self.invalid_value
        return d.reshape(self.camera.height, self.camera.width).astype(np.float32)

    def shade(self, labels: np.ndarray, normals_cam: dict) -> np.ndarray:
        """BGR uint8 image: a colour per surface, shaded by |cos| between ray and surface normal.

        ``normals_cam``: label -> unit normal (3,) in the camera frame."""
        lab = np.asarray(labels).ravel()
        rays_u = self._rays / np.linalg.norm(self._rays, axis=1, keepdims=True)
        img = np.zeros((lab.size, 3), dtype=float)
        for lb, nrm in normals_cam.items():
            m = lab == lb
            if not np.any(m):
                continue
            base = _FACE_BGR.get(lb) or _ROOM_BGR.get(lb - LABEL_ROOM, (128, 128, 128))
            cosang = np.abs(rays_u[m] @ np.asarray(nrm, dtype=float))
            img[m] = np.asarray(base, dtype=float)[None, :] * (0.35 + 0.65 * cosang[:, None])
        return np.clip(img, 0, 255).astype(np.uint8).reshape(self.camera.height, self.camera.width, 3)

    def render(self, faces_cam: Sequence[np.ndarray], rng: Optional[np.random.Generator] = None,
               noise: bool = True, room: Optional[RoomBox] = None,
               T_world_camera: Optional[np.ndarray] = None) -> np.ndarray:
        """Depth image (H, W) float32 metres of polygons in the camera frame (+ optional room)."""
        z, _ = self.cast(faces_cam, room=room, T_world_camera=T_world_camera)
        return self.apply_noise(z, rng, noise)


def camera_from_config(cfg) -> CameraModel:
    """Pinhole (optionally distorted) camera from a CameraConfig: fx = fy from the hfov."""
    fx = float(cfg.fx_px) if getattr(cfg, "fx_px", 0.0) > 0 else \
        0.5 * cfg.width_px / np.tan(0.5 * np.radians(cfg.hfov_deg))
    model = cfg.distortion_model or ""
    return CameraModel.from_K(cfg.width_px, cfg.height_px, fx, fx, 0.5 * (cfg.width_px - 1),
                              0.5 * (cfg.height_px - 1), D=list(cfg.D) if cfg.D else np.zeros(0),
                              distortion_model=model)


# ----------------------------------------------------------------------------------------------
# Simulation results
# ----------------------------------------------------------------------------------------------
@dataclass
class SimTruth:
    """Ground truth of a run. ``T_camera_laser`` maps laser points into the left camera optical
    frame; ``T_camera_right_laser`` into the right camera; ``T_right_left`` maps left-camera
    points into the right camera (translation (-baseline, 0, 0)). ``frames``: frame ids by role.
    ``params``: scenario (dict) plus board geometry."""

    T_camera_laser: np.ndarray
    T_camera_right_laser: np.ndarray
    T_right_left: np.ndarray
    T_agv_laser: np.ndarray
    T_agv_camera: np.ndarray
    T_agv_camera_right: np.ndarray
    frames: dict
    params: dict


@dataclass
class SimObservation:
    """One synchronised laser scan + depth frame. Poses are world-frame 4x4 transforms.

    ``scan_ranges_m`` float32 (see :class:`LaserModel` for inf/NaN), ``depth_m`` (H, W) float32
    z-depth in the left optical frame, invalid = NaN (or 0 per scenario). ``visibility``: noise-free
    counts of laser beams / pixels per board face (keys 'laser', 'camera', 'camera_right')."""

    stamp_s: float
    T_world_agv: np.ndarray
    T_world_board: np.ndarray
    scan_ranges_m: np.ndarray
    scan_angle_min_rad: float
    scan_angle_increment_rad: float
    scan_range_min_m: float
    scan_range_max_m: float
    depth_m: np.ndarray
    depth_right_m: Optional[np.ndarray]
    color_bgr: Optional[np.ndarray]
    camera: CameraModel
    camera_right: Optional[CameraModel]
    visibility: dict = field(default_factory=dict)


@dataclass
class SimRun:
    truth: SimTruth
    observations: list
    scenario: Optional[Scenario] = None


# ----------------------------------------------------------------------------------------------
# World
# ----------------------------------------------------------------------------------------------
def agv_pose(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    """T_world_agv of an AGV on the floor."""
    return make_T(R_from_rpy(0.0, 0.0, yaw_rad), [x_m, y_m, 0.0])


# Board frame (x right, y up, z towards the viewer) of a board facing world -x at yaw 0.
_R_WORLD_BOARD0 = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def board_pose(x_m: float, y_m: float, base_height_m: float, yaw_rad: float = 0.0,
               tilt_rad: float = 0.0) -> np.ndarray:
    """T_world_board: board bottom-centre at (x, y, base_height); yaw 0 = front faces world -x
    (yaw rotates about world z); tilt > 0 leans the top back, away from the viewer."""
    R = R_from_rpy(0.0, 0.0, yaw_rad) @ _R_WORLD_BOARD0 @ R_from_rpy(-tilt_rad, 0.0, 0.0)
    return make_T(R, [x_m, y_m, base_height_m])


class LrfWorld:
    """Room + folded board + AGV carrying a 2D laser and a stereo depth camera."""

    def __init__(self, scenario=None):
        sc = load_scenario(scenario)
        self.scenario = sc
        self.board = FoldedBoard.from_config(sc.board)
        self.room = RoomBox.from_config(sc.room)
        self.laser = LaserModel.from_config(sc.laser)
        cam = camera_from_config(sc.camera)
        inv = np.nan if str(sc.camera.invalid_value).lower() == "nan" else 0.0
        kw = dict(depth_min_m=sc.camera.depth_min_m, depth_max_m=sc.camera.depth_max_m,
                  sigma_disparity_px=sc.camera.sigma_disparity_px, baseline_m=sc.camera.baseline_m,
                  dropout_fraction=sc.camera.dropout_fraction, invalid_value=inv,
                  stereo_width_px=sc.camera.stereo_width_px, k_override=sc.camera.depth_sigma_k,
                  quantise_mm=sc.camera.depth_encoding == "16UC1")
        self.depth_cam = DepthCameraModel(cam, **kw)
        self.has_right = bool(sc.camera.right_camera)
        self.depth_cam_right = DepthCameraModel(
            CameraModel(cam.width, cam.height, cam.K.copy(), cam.D.copy(), cam.distortion_model), **kw
        ) if self.has_right else None
        m = sc.mount
        self.T_agv_laser = make_T(R_from_rpy(*np.radians(m.laser_rpy_deg)), m.laser_xyz_m)
        self.T_agv_camera = make_T(R_from_rpy(*np.radians(m.camera_rpy_deg)) @ R_BODY_OPTICAL,
                                   m.camera_xyz_m)
        self.T_agv_camera_right = self.T_agv_camera @ make_T(np.eye(3), [sc.camera.baseline_m, 0, 0])
        self._faces_board = self.board.faces()
        self._labels = list(range(len(self._faces_board)))

    # -- truth -----------------------------------------------------------------------------------
    def truth(self) -> SimTruth:
        sc = self.scenario
        n, d = self.board.planes()
        params = {"scenario": sc.to_dict(),
                  "board": {"vertices_m": {k: v.tolist() for k, v in self.board.vertices.items()},
                            "face_names": list(FACE_NAMES[:3]),
                            "plane_normals": n.tolist(), "plane_offsets_m": d.tolist()},
                  "laser": {"angle_min_rad": self.laser.angle_min_rad,
                            "angle_increment_rad": self.laser.angle_increment_rad,
                            "n_beams": self.laser.n_beams},
                  "camera_K": self.depth_cam.camera.K.tolist(),
                  "depth_noise_k_per_m": self.depth_cam.k_noise}
        frames = {"world": sc.mount.world_frame_id, "agv": sc.mount.agv_frame_id,
                  "laser": sc.laser.frame_id, "camera": sc.camera.frame_id,
                  "camera_right": sc.camera.right_frame_id if self.has_right else None}
        return SimTruth(
            T_camera_laser=inv_T(self.T_agv_camera) @ self.T_agv_laser,
            T_camera_right_laser=inv_T(self.T_agv_camera_right) @ self.T_agv_laser,
            T_right_left=inv_T(self.T_agv_camera_right) @ self.T_agv_camera,
            T_agv_laser=self.T_agv_laser.copy(), T_agv_camera=self.T_agv_camera.copy(),
            T_agv_camera_right=self.T_agv_camera_right.copy(), frames=frames, params=params)

    # -- sensing ---------------------------------------------------------------------------------
    def _faces_in(self, T_sensor_board: np.ndarray) -> list[np.ndarray]:
        return [transform_points(T_sensor_board, f) for f in self._faces_board]

    def cast_scan(self, T_world_agv: np.ndarray, T_world_board: np.ndarray):
        """Noise-free (ranges float64, labels) of the laser at this AGV / board pose."""
        T_world_laser = T_world_agv @ self.T_agv_laser
        faces = self._faces_in(inv_T(T_world_laser) @ T_world_board)
        return self.laser.cast(faces, self._labels, self.room, T_world_laser)

    def cast_depth(self, T_world_agv: np.ndarray, T_world_board: np.ndarray, right: bool = False):
        """Noise-free (z-depth (H*W,) float64, labels) of the left (or right) camera."""
        T_world_cam = T_world_agv @ (self.T_agv_camera_right if right else self.T_agv_camera)
        cam = self.depth_cam_right if right else self.depth_cam
        faces = self._faces_in(inv_T(T_world_cam) @ T_world_board)
        return cam.cast(faces, self._labels, self.room, T_world_cam)

    def _normals_cam(self, T_world_cam: np.ndarray, T_world_board: np.ndarray) -> dict:
        R_cw = T_world_cam[:3, :3].T
        out = {}
        for lb, f in enumerate(self._faces_board):
            out[lb] = R_cw @ T_world_board[:3, :3] @ _newell_normal(f)
        for axis in range(3):
            for side in range(2):
                out[LABEL_ROOM + 2 * axis + side] = R_cw[:, axis]
        return out

    def observe(self, stamp_s: float, T_world_agv: np.ndarray, T_world_board: np.ndarray,
                rng: Optional[np.random.Generator] = None, noise: bool = True,
                color: Optional[bool] = None, right: Optional[bool] = None,
                depth: bool = True) -> SimObservation:
        """Simulate one scan + depth frame (+ right depth, colour) at a static pose."""
        if rng is None:
            rng = np.random.default_rng()
        color = self.scenario.camera.render_color if color is None else color
        right = self.has_right if right is None else (right and self.has_right)
        r, lab_l = self.cast_scan(T_world_agv, T_world_board)
        ranges = self.laser.apply_noise(r, rng, noise)
        vis = {"laser": _counts(lab_l)}
        depth_m = depth_r = col = None
        if depth:
            z, lab_c = self.cast_depth(T_world_agv, T_world_board)
            vis["camera"] = _counts(lab_c)
            depth_m = self.depth_cam.apply_noise(z, rng, noise)
            if color:
                col = self.depth_cam.shade(lab_c, self._normals_cam(T_world_agv @ self.T_agv_camera,
                                                                    T_world_board))
            if right:
                zr, lab_r = self.cast_depth(T_world_agv, T_world_board, right=True)
                vis["camera_right"] = _counts(lab_r)
                depth_r = self.depth_cam_right.apply_noise(zr, rng, noise)
        return SimObservation(
            stamp_s=float(stamp_s), T_world_agv=np.array(T_world_agv, dtype=float),
            T_world_board=np.array(T_world_board, dtype=float), scan_ranges_m=ranges,
            scan_angle_min_rad=self.laser.angle_min_rad,
            scan_angle_increment_rad=self.laser.angle_increment_rad,
            scan_range_min_m=self.laser.range_min_m, scan_range_max_m=self.laser.range_max_m,
            depth_m=depth_m, depth_right_m=depth_r, color_bgr=col, camera=self.depth_cam.camera,
            camera_right=self.depth_cam_right.camera if right else None, visibility=vis)

    # -- visibility ------------------------------------------------------------------------------
    def check_visibility(self, T_world_agv: np.ndarray, T_world_board: np.ndarray) -> tuple[bool, str]:
        """Do both sensors see all three faces? (ok, reason). Laser: >= min points on ABC, ACD
        and on the base on both sides of the flaps (E-F and H-I); cameras: every board vertex in
        the image and >= min pixels per face (left and, if enabled, right)."""
        pc = self.scenario.poses
        r, lab = self.cast_scan(T_world_agv, T_world_board)
        for f in (FACE_ABC, FACE_ACD):
            if np.count_nonzero(lab == f) < pc.min_laser_points_per_face:
                return False, f"laser sees too little of face {FACE_NAMES[f]}"
        base = lab == FACE_BASE
        if np.count_nonzero(base) < 2 * pc.min_laser_points_per_face:
            return False, "laser sees too little of the base"
        # Split base hits into left (E-F) and right (H-I) of the line AC.
        T_board_laser = inv_T(T_world_board) @ T_world_agv @ self.T_agv_laser
        pts = np.concatenate([self.laser.directions[base] * r[base, None],
                              np.zeros((int(base.sum()), 1))], axis=1)
        pb = transform_points(T_board_laser, pts)
        A, C = self.board.vertices["A"], self.board.vertices["C"]
        x_ac = A[0] + (C[0] - A[0]) * (pb[:, 1] - A[1]) / (C[1] - A[1])
        if min(np.count_nonzero(pb[:, 0] < x_ac), np.count_nonzero(pb[:, 0] > x_ac)) < pc.min_laser_points_per_face:
            return False, "laser misses the base on one side of the flaps"
        corners = self.board.corners()
        for right in ([False, True] if self.has_right else [False]):
            T_wc = T_world_agv @ (self.T_agv_camera_right if right else self.T_agv_camera)
            cam = (self.depth_cam_right if right else self.depth_cam)
            pc_cam = transform_points(inv_T(T_wc) @ T_world_board, corners)
            _, valid = cam.camera.project(pc_cam)
            if not np.all(valid) or np.any(pc_cam[:, 2] < cam.depth_min_m) or np.any(pc_cam[:, 2] > cam.depth_max_m):
                return False, f"board not fully in the {'right' if right else 'left'} camera image"
            # pixel counts on a 4x coarser image (x 16): the check runs for every pose attempt
            vcam = self._vis_cam(right)
            faces = self._faces_in(inv_T(T_wc) @ T_world_board)
            _, labc = vcam.cast(faces, self._labels, None, None)
            for f in (FACE_BASE, FACE_ABC, FACE_ACD):
                if 16 * np.count_nonzero(labc == f) < pc.min_pixels_per_face:
                    return False, f"{'right' if right else 'left'} camera sees too little of {FACE_NAMES[f]}"
        return True, "ok"

    def _vis_cam(self, right: bool) -> "DepthCameraModel":
        key = "_vis_right" if right else "_vis_left"
        if getattr(self, key, None) is None:
            cam = (self.depth_cam_right if right else self.depth_cam).camera
            setattr(self, key, DepthCameraModel(cam.scaled(0.25)))
        return getattr(self, key)

    # -- pose generation -------------------------------------------------------------------------
    def _board_pose_sample(self, u: np.ndarray) -> np.ndarray:
        pc = self.scenario.poses
        bx, by = pc.board_position_m
        if not pc.replace_board:
            return board_pose(bx, by, pc.board_base_height_m, np.radians(pc.board_yaw_deg),
                              np.radians(pc.board_tilt_deg))
        lerp = lambda rg, x: rg[0] + (rg[1] - rg[0]) * x
        return board_pose(bx, by, lerp(pc.board_base_height_range_m, u[0]),
                          np.radians(pc.board_yaw_deg + lerp(pc.board_yaw_range_deg, u[1])),
                          np.radians(pc.board_tilt_deg + lerp(pc.board_tilt_range_deg, u[2])))

    def _agv_pose_sample(self, T_world_board: np.ndarray, u: np.ndarray) -> Optional[np.ndarray]:
        pc = self.scenario.poses
        lerp = lambda rg, x: rg[0] + (rg[1] - rg[0]) * x
        dist, lat, yaw = lerp(pc.distance_m, u[0]), lerp(pc.lateral_m, u[1]), np.radians(lerp(pc.yaw_deg, u[2]))
        nz = T_world_board[:3, 2].copy()
        nz[2] = 0.0
        nz /= np.linalg.norm(nz)
        xh = np.array([-nz[1], nz[0], 0.0])  # board's horizontal "right" = up x normal... sign below
        if xh @ T_world_board[:3, 0] < 0:
            xh = -xh
        centre = T_world_board[:3, 3] + 0.5 * self.board.height_m * T_world_board[:3, 1]
        p = centre + dist * nz + lat * xh
        look = np.arctan2(centre[1] - p[1], centre[0] - p[0])
        lo, hi = self.room.lo_m, self.room.hi_m
        margin = 0.4
        if not (lo[0] + margin < p[0] < hi[0] - margin and lo[1] + margin < p[1] < hi[1] - margin):
            return None
        return agv_pose(p[0], p[1], look + yaw)

    def sample_poses(self, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
        """Seeded, stratified (Latin hypercube) (T_world_agv, T_world_board) pairs that pass
        :meth:`check_visibility`. Raises RuntimeError when a pose cannot be found."""
        pc = self.scenario.poses
        n = pc.n_poses
        strata = np.stack([rng.permutation(n) for _ in range(6)], axis=1)  # (n, 6)
        out = []
        for i in range(n):
            last = "no attempt"
            for attempt in range(pc.max_attempts):
                jitter = rng.random(6)
                if attempt < pc.max_attempts // 4:
                    u = (strata[i] + jitter) / n
                else:  # the stratum may be infeasible: widen to the full range
                    u = jitter
                T_wb = self._board_pose_sample(u[3:])
                T_wa = self._agv_pose_sample(T_wb, u[:3])
                if T_wa is None:
                    last = "AGV outside the room"
                    continue
                ok, last = self.check_visibility(T_wa, T_wb)
                if ok:
                    out.append((T_wa, T_wb))
                    break
            else:
                raise RuntimeError(f"could not find a valid observation pose {i} after "
                                   f"{pc.max_attempts} attempts (last reason: {last})")
        return out


def _counts(labels: np.ndarray) -> dict:
    return {FACE_NAMES[f]: int(np.count_nonzero(labels == f)) for f in (FACE_BASE, FACE_ABC, FACE_ACD)}


def simulate(scenario=None, rng: Optional[np.random.Generator] = None, noise: bool = True) -> SimRun:
    """Simulate the static observations of a scenario: one noisy scan + depth frame per pose.

    ``rng`` defaults to ``np.random.default_rng(scenario.seed)``. Stamps are the middle of each
    pose's static interval on the bag timeline (see :mod:`lidar_cam_calib.sim.lrf_bag`)."""
    world = LrfWorld(scenario)
    sc = world.scenario
    if rng is None:
        rng = np.random.default_rng(sc.seed)
    poses = world.sample_poses(rng)
    tl = sc.timeline
    obs = []
    for i, (T_wa, T_wb) in enumerate(poses):
        stamp = tl.start_s + i * (tl.static_s + tl.drive_s) + 0.5 * tl.static_s
        obs.append(world.observe(stamp, T_wa, T_wb, rng, noise=noise))
    return SimRun(truth=world.truth(), observations=obs, scenario=sc)
