"""Feature extraction for the lrf method (paper 003, Section 3.1), ROS-free.

Board (:class:`BoardModel`): a back rectangle ``width_m`` x ``height_m`` with two
triangles ABC and ACD folded out of it. Board frame: origin at the bottom
centre of the rectangle, x to the right as seen from the sensors, y up, z out
of the rectangle towards the sensors. A, B and D lie anywhere on the back
plane (B the left one), the apex C stands ``c_xyz_m[2]`` out of it (up, down
or sideways of A). The scan crosses the board E-F-G-H-I: EF and HI on the back
plane, F on AB, FG on ABC, G on AC, GH on ACD, H on AD.

Laser (:func:`extract_scan_features`): cluster the scan by range jumps (the
gap grows with the beam spacing at that range), fit on every cluster the
*folded-line model* "back line, FG, GH, back line again" by exhaustive search
of the three break points (prefix-sum moments, total least squares; coarse
grid then local refinement). Lines are refitted on inliers away from the
corners; F, G, H are line intersections with covariances. The range noise is
estimated from the line residuals (``ScanFeatures.sigma_m``; the configured
``laser_sigma_m`` is only the prior when there are too few points).

Depth (:func:`extract_depth_features`), model-based and noise-adaptive:
1. the depth noise ``sigma(z) = k z^2`` (plus a quantisation floor for 16UC1
   millimetres) is estimated from the image itself (robust second differences
   on the decimated grid; :func:`estimate_depth_noise`); the configured
   ``depth_sigma_k`` is the prior when the image is too small;
2. normals from box-filtered points whose window grows with the noise at that
   depth, so the normal noise stays near ``depth_normal_sigma_deg``;
3. planes by one-point RANSAC on (point, normal) pairs with noise-scaled
   distance and normal tolerances, each grown as the connected region of
   compatible pixels (no fixed edge threshold: shallow folds do not merge
   faces, noisy far faces do not shatter);
4. the board is the triple of planes that touch pairwise, meet in one point
   and whose fold angles and sizes match the configured board; a triple that
   looks like a folded board but with other angles is refused with the
   measured and the configured angles;
5. the three planes are refitted (k-planes, points outside the fold bands,
   weights from the estimated noise at the depth each plane predicts).

Correspondence: the laser ordering E..I is left-to-right (decreasing laser
angle); the camera triangle whose centroid is further left (smaller x/z) is
ABC. :func:`solvers.resolve_assignment` verifies it.

Failures raise :class:`FeatureError` with a reason string.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.calibrator import cfg_field
from ..core.errors import CalibError, ConfigError
from ..core.fitting import (
    FitError,
    fit_line_2d_lsq,
    fit_plane_lsq,
    intersect_lines_2d,
    intersect_planes,
    intersect_three_planes,
    line_2d_distances,
)
from .solvers import LrfObservation, PlaneStats


class FeatureError(CalibError):
    """Feature extraction failed; ``str(err)`` is the reason shown to the user."""


# ----------------------------------------------------------------------------
# Board and configuration
# ----------------------------------------------------------------------------
_XY = (-10.0, 10.0)


@dataclasses.dataclass
class BoardModel:
    """Geometry of the folded board (board frame, metres): see the module docstring."""
    width_m: float = cfg_field(1.0, "Width of the board's back rectangle (m).", range=(0.1, 5.0),
                               exclusive_min=True)
    height_m: float = cfg_field(1.0, "Height of the board's back rectangle (m).", range=(0.1, 5.0),
                                exclusive_min=True)
    a_xy_m: tuple = cfg_field((0.0, 0.0), "A, where both triangles meet the back plane: (x, y) in the "
                              "board frame (origin bottom centre of the rectangle, x right, y up; m).",
                              range=_XY, length=2)
    b_xy_m: tuple = cfg_field((-0.5, 1.0), "B, the far end of the left fold line AB on the back plane: "
                              "(x, y) in the board frame (m).", range=_XY, length=2)
    d_xy_m: tuple = cfg_field((0.5, 1.0), "D, the far end of the right fold line AD on the back plane: "
                              "(x, y) in the board frame (m).", range=_XY, length=2)
    c_xyz_m: tuple = cfg_field((0.0, 1.0, 0.6), "Apex C of both triangles: (x, y, z) in the board frame, "
                               "z = how far it stands out of the back plane towards the sensors (m).",
                               range=_XY, length=3)

    @classmethod
    def from_config(cls, cfg) -> BoardModel:
        """From a sim BoardConfig-like object (width_m, height_m, a_xy_m, c_xyz_m[, b_xy_m, d_xy_m])."""
        w, h = float(cfg.width_m), float(cfg.height_m)
        b = tuple(getattr(cfg, "b_xy_m", None) or (-w / 2, h))
        d = tuple(getattr(cfg, "d_xy_m", None) or (w / 2, h))
        return cls(w, h, tuple(cfg.a_xy_m), b, d, tuple(cfg.c_xyz_m))

    @property
    def vertices(self) -> dict:
        w, h = self.width_m, self.height_m
        return {"P": np.array([-w / 2, 0.0, 0.0]), "Q": np.array([w / 2, 0.0, 0.0]),
                "TL": np.array([-w / 2, h, 0.0]), "TR": np.array([w / 2, h, 0.0]),
                "A": np.array([self.a_xy_m[0], self.a_xy_m[1], 0.0]),
                "B": np.array([self.b_xy_m[0], self.b_xy_m[1], 0.0]),
                "D": np.array([self.d_xy_m[0], self.d_xy_m[1], 0.0]),
                "C": np.array(self.c_xyz_m, dtype=float)}

    def face_triangles(self) -> list:
        """Triangles (board frame) per face: back rectangle as two triangles, ABC, ACD."""
        v = self.vertices
        return [[np.stack([v["P"], v["Q"], v["TR"]]), np.stack([v["P"], v["TR"], v["TL"]])],
                [np.stack([v["A"], v["B"], v["C"]])],
                [np.stack([v["A"], v["C"], v["D"]])]]

    def normals(self) -> np.ndarray:
        """(3,3) unit normals of back plane, ABC, ACD, pointing towards the sensors (+z)."""
        v = self.vertices
        out = [np.array([0.0, 0.0, 1.0])]
        for p, q in ((v["B"], v["C"]), (v["C"], v["D"])):
            n = np.cross(p - v["A"], q - v["A"])
            nn = np.linalg.norm(n)
            n = n / nn if nn > 1e-12 else n
            out.append(n if n[2] >= 0 else -n)
        return np.stack(out)

    def normal_angles_deg(self) -> tuple:
        """Angles between the face normals: (back-ABC, back-ACD, ABC-ACD) in degrees."""
        n = self.normals()
        ang = lambda a, b: float(np.degrees(np.arccos(np.clip(abs(a @ b), 0.0, 1.0))))
        return ang(n[0], n[1]), ang(n[0], n[2]), ang(n[1], n[2])

    def face_areas_m2(self) -> tuple:
        """(visible back plane, ABC, ACD) areas: the rectangle minus the tent's footprint ABD."""
        v = self.vertices
        tri = lambda a, b, c: 0.5 * float(np.linalg.norm(np.cross(b - a, c - a)))
        return (self.width_m * self.height_m - tri(v["A"], v["B"], v["D"]),
                tri(v["A"], v["B"], v["C"]), tri(v["A"], v["C"], v["D"]))

    def max_extent_m(self) -> float:
        pts = np.stack(list(self.vertices.values()))
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    def validate(self) -> None:
        """Raise :class:`ConfigError` when the geometry cannot be a folded board."""
        v = self.vertices
        w, h = self.width_m, self.height_m
        for name in ("A", "B", "D"):
            x, y = v[name][:2]
            if not (-w / 2 - 1e-6 <= x <= w / 2 + 1e-6 and -1e-6 <= y <= h + 1e-6):
                raise ConfigError(f"board_{name.lower()}_xy_m = ({x:.3f}, {y:.3f}) lies outside the "
                                  f"{w:.2f} x {h:.2f} m back rectangle (x in [-w/2, w/2], y in [0, h])")
        if self.c_xyz_m[2] <= 0.02:
            raise ConfigError(f"board_c_xyz_m[2] = {self.c_xyz_m[2]:.3f} m: the apex must stand out of the "
                              "back plane towards the sensors (> 0.02 m)")
        if self.b_xy_m[0] >= self.d_xy_m[0]:
            raise ConfigError("board_b_xy_m must be left of board_d_xy_m (smaller x): B ends the left fold line")
        a = self.normal_angles_deg()
        if min(a) < 15.0:
            raise ConfigError(f"board fold angles {a[0]:.0f}/{a[1]:.0f}/{a[2]:.0f} deg: every pair of faces "
                              "must meet at >= 15 deg (move the apex C)")


def _window_field(default):
    return cfg_field(default, "Laser angles (deg, counter-clockwise from the laser's x axis) to search "
                     "for the board as [min, max]; [0, 0] = the whole scan.", range=(-360.0, 360.0), length=2)


@dataclasses.dataclass
class FeatureConfig:
    """Feature-extraction parameters (metres, degrees). Noise values are priors:
    the features estimate the noise from the data."""
    board: BoardModel = dataclasses.field(default_factory=BoardModel)
    # laser
    laser_sigma_m: float = cfg_field(0.0125, "Prior laser range noise, 1 sigma (m); the residuals of the "
                                     "board's lines give the value used.", range=(0.0, 1.0), exclusive_min=True)
    scan_max_range_m: float = cfg_field(8.0, "Ignore laser beams farther than this (m).", range=(0.2, 100.0))
    scan_angle_window_deg: tuple = _window_field((0.0, 0.0))
    cluster_gap_m: float = cfg_field(0.10, "Minimum range jump that separates laser clusters (m); it grows "
                                     "with the beam spacing at long range.", range=(0.01, 2.0))
    min_points_per_segment: int = cfg_field(5, "Fewest laser points on each of the four board segments.",
                                            range=(3, 1000))
    scan_grid_points: int = cfg_field(70, "Coarse break-point grid per laser cluster (search cost).",
                                      range=(10, 500))
    scan_rms_max_m: float = cfg_field(0.08, "A cluster whose folded-line fit RMS exceeds this is not the "
                                      "board (m).", range=(0.001, 1.0))
    min_fold_depth_m: float = cfg_field(0.03, "The fold corner G must stand this far from the back line (m).",
                                        range=(0.0, 2.0))
    corner_trim_m: float = cfg_field(0.02, "Laser points this close to F/G/H are left out of the line fits (m).",
                                     range=(0.0, 0.5))
    # depth
    depth_stride: int = cfg_field(2, "Use every n-th depth pixel in rows and columns (grows by itself so "
                                  "that at most depth_grid_width_px columns are used).", range=(1, 16))
    depth_grid_width_px: int = cfg_field(320, "Widest decimated depth grid processed (bounds the cost per "
                                         "frame on large images).", range=(80, 4096))
    depth_max_m: float = cfg_field(6.0, "Ignore depth pixels farther than this (m).", range=(0.3, 100.0))
    depth_sigma_k: float = cfg_field(0.0031, "Prior depth noise: sigma = k z^2 (1/m); the image's own "
                                     "second differences give the value used.", range=(0.0, 1.0),
                                     exclusive_min=True)
    depth_sigma_floor_m: float = cfg_field(0.0005, "Smallest per-pixel depth sigma (m).", range=(0.0, 0.1))
    depth_nsigma: float = cfg_field(2.5, "Inlier / assignment threshold in sigmas of the depth noise.",
                                    range=(1.0, 10.0))
    depth_normal_sigma_deg: float = cfg_field(8.0, "Largest normal noise the adaptive normal window aims "
                                              "at (deg); it also stays below a sixth of the board's "
                                              "smallest fold angle.", range=(0.5, 20.0))
    depth_normal_window_max: int = cfg_field(15, "Largest normal window (decimated pixels).", range=(3, 61))
    depth_max_planes: int = cfg_field(16, "Most planes extracted from one depth image.", range=(3, 64))
    depth_ransac_hypotheses: int = cfg_field(24, "One-point (point + normal) plane hypotheses per plane.",
                                             range=(5, 1000))
    depth_angle_tol_deg: float = cfg_field(4.0, "Largest difference between a measured and the configured "
                                           "fold angle (deg), per fold.", range=(0.5, 45.0))
    depth_min_plane_points: int = cfg_field(40, "Fewest decimated pixels of a plane candidate.",
                                            range=(10, 100000))
    depth_touch_m: float = cfg_field(0.15, "Two planes touch when both have points this close to their "
                                     "intersection line (m).", range=(0.0, 2.0))
    depth_region_close_px: int = cfg_field(0, "Refit the board planes on the faces' image region closed by "
                                           "this many grid pixels (0: on the board's 3D bounding box).",
                                           range=(0, 101))
    depth_refit_iterations: int = cfg_field(2, "k-planes refits of the three board planes.", range=(1, 20))
    keep_points_per_plane: int = cfg_field(3000, "Inlier points stored per plane (overlay).", range=(10, 10**6))
    seed: int = cfg_field(0, "Seed of the random sampling (results are repeatable).", range=(0, 2**31 - 1))

    def angle_window(self) -> tuple | None:
        w = tuple(self.scan_angle_window_deg) if self.scan_angle_window_deg is not None else (0.0, 0.0)
        return None if w[0] == 0.0 and w[1] == 0.0 else w


# ----------------------------------------------------------------------------
# Laser
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class ScanFeatures:
    """Laser features in the laser frame (metres, xy in the scan plane z = 0).

    ``corners_m`` (3,2) F, G, H; ``corner_cov`` (3,2,2); ``face_points_m``:
    base (EF+HI), FG, GH inlier points (left-to-right); ``lines``: (point,
    unit_dir) of base, FG, GH; ``points_m`` all valid scan points;
    ``board_points_m`` the board cluster; ``rms_m`` folded-model RMS."""
    corners_m: np.ndarray
    corner_cov: np.ndarray
    face_points_m: tuple
    lines: tuple
    points_m: np.ndarray
    board_points_m: np.ndarray
    rms_m: float
    endpoints_m: np.ndarray  # (2,2) E and I
    sigma_m: float = float("nan")  # range noise estimated from the line residuals
    sigma_source: str = "prior"


def scan_points(ranges_m, angle_min_rad: float, angle_increment_rad: float,
                range_min_m: float, range_max_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Valid scan points: (xy (N,2) in the laser frame, beam index (N,))."""
    r = np.asarray(ranges_m, dtype=float).ravel()
    ang = angle_min_rad + angle_increment_rad * np.arange(r.size)
    ok = np.isfinite(r) & (r >= range_min_m) & (r <= range_max_m) & (r > 0)
    idx = np.nonzero(ok)[0]
    return np.column_stack([r[idx] * np.cos(ang[idx]), r[idx] * np.sin(ang[idx])]), idx


def _moments(xy: np.ndarray) -> np.ndarray:
    """Prefix sums of (1, x, y, xx, xy, yy): (N+1, 6)."""
    x, y = xy[:, 0], xy[:, 1]
    m = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    return np.vstack([np.zeros((1, 6)), np.cumsum(m, axis=0)])


def _tls_cost(M: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of the central scatter for moment rows (..., 6)."""
    n = np.maximum(M[..., 0], 1e-12)
    mx, my = M[..., 1] / n, M[..., 2] / n
    a = M[..., 3] - n * mx * mx
    b = M[..., 4] - n * mx * my
    c = M[..., 5] - n * my * my
    return np.maximum(0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b), 0.0)


def _fold_cost(C: np.ndarray, iF, iG, iH, n: int) -> np.ndarray:
    base = C[iF] - C[0] + C[n] - C[iH]
    return _tls_cost(base) + _tls_cost(C[iG] - C[iF]) + _tls_cost(C[iH] - C[iG])


def _fit_fold(xy: np.ndarray, cfg: FeatureConfig) -> tuple[float, tuple[int, int, int]]:
    """Best break points (iF, iG, iH) of the folded-line model on ordered points."""
    n = len(xy)
    k = cfg.min_points_per_segment
    C = _moments(xy)
    grid = np.unique(np.linspace(k, n - k, min(cfg.scan_grid_points, n - 2 * k + 1)).round().astype(int))
    F, G, H = np.meshgrid(grid, grid, grid, indexing="ij")
    ok = (G - F >= k) & (H - G >= k)
    F, G, H = F[ok], G[ok], H[ok]
    if F.size == 0:
        raise FeatureError("scan: cluster too small for the folded board")
    cost = _fold_cost(C, F, G, H, n)
    b = int(np.argmin(cost))
    best = [int(F[b]), int(G[b]), int(H[b])]
    step = int(np.max(np.diff(grid))) if grid.size > 1 else 1
    # local refinement of each break point at full resolution (coordinate descent)
    for _ in range(3):
        moved = False
        for j in range(3):
            lo = best[j - 1] + k if j > 0 else k
            hi = best[j + 1] - k if j < 2 else n - k
            cand = np.arange(max(lo, best[j] - step), min(hi, best[j] + step) + 1)
            if cand.size == 0:
                continue
            trial = np.repeat(np.array(best)[None, :], cand.size, axis=0)
            trial[:, j] = cand
            c = _fold_cost(C, trial[:, 0], trial[:, 1], trial[:, 2], n)
            bj = int(cand[int(np.argmin(c))])
            if bj != best[j]:
                best[j] = bj
                moved = True
        if not moved:
            break
    cost_best = float(_fold_cost(C, *[np.array([v]) for v in best], n)[0])
    return cost_best, tuple(best)


def _line_offset_var(pts: np.ndarray, point: np.ndarray, u: np.ndarray, sigma: float, at: np.ndarray) -> float:
    """Variance of a TLS line's perpendicular position at ``at``."""
    s = (pts - point) @ u
    s0 = (at - point) @ u
    return sigma ** 2 * (1.0 / len(pts) + (s0 - s.mean()) ** 2 / max(((s - s.mean()) ** 2).sum(), 1e-12))


def corner_covariance(l1, pts1, l2, pts2, sigma: float, X: np.ndarray) -> np.ndarray:
    """2x2 covariance of the intersection X of two independently fitted lines."""
    (p1, u1), (p2, u2) = l1, l2
    s = abs(u1[0] * u2[1] - u1[1] * u2[0])
    v1 = _line_offset_var(pts1, p1, u1, sigma, X)
    v2 = _line_offset_var(pts2, p2, u2, sigma, X)
    return (v1 * np.outer(u2, u2) + v2 * np.outer(u1, u1)) / max(s * s, 1e-6)


def _clusters(xy: np.ndarray, gap_m: float, inc_rad: float = 0.0, sigma_m: float = 0.0) -> list[np.ndarray]:
    """Split ordered scan points where consecutive points jump by more than
    ``max(gap_m, 6 r inc + 6 sigma)``: the beam spacing at that range (an
    oblique face spreads it further) and the noise set the gap."""
    if len(xy) == 0:
        return []
    r = np.linalg.norm(xy, axis=1)
    gap = np.maximum(gap_m, 6.0 * abs(inc_rad) * np.maximum(r[1:], r[:-1]) + 6.0 * sigma_m)
    jumps = np.nonzero(np.linalg.norm(np.diff(xy, axis=0), axis=1) > gap)[0]
    bounds = np.concatenate([[0], jumps + 1, [len(xy)]])
    return [np.arange(bounds[i], bounds[i + 1]) for i in range(len(bounds) - 1)]


def extract_scan_features(frame, cfg: FeatureConfig | None = None) -> ScanFeatures:
    """Find the folded board in a laser scan; see the module docstring."""
    cfg = cfg or FeatureConfig()
    xy, beam = scan_points(frame.scan_ranges_m, frame.scan_angle_min_rad, frame.scan_angle_increment_rad,
                           frame.scan_range_min_m, min(frame.scan_range_max_m, cfg.scan_max_range_m))
    if len(xy) == 0:
        raise FeatureError("scan: no valid ranges (all beams inf/NaN or out of range)")
    all_xy = xy
    win = cfg.angle_window()
    if win is not None:
        ang = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
        m = (ang >= win[0]) & (ang <= win[1])
        xy, beam = xy[m], beam[m]
    # left-to-right as seen from the laser: decreasing angle
    xy = xy[::-1]
    board = cfg.board
    width = board.width_m
    k = cfg.min_points_per_segment
    best = None
    reasons = []
    for ci in _clusters(xy, cfg.cluster_gap_m, frame.scan_angle_increment_rad, cfg.laser_sigma_m):
        pts = xy[ci]
        ext = float(np.linalg.norm(pts[-1] - pts[0]))
        if len(pts) < 4 * k:
            continue
        if ext < 0.3 * width or ext > 1.25 * board.max_extent_m():
            continue
        try:
            cost, (iF, iG, iH) = _fit_fold(pts, cfg)
        except FeatureError as e:
            reasons.append(str(e))
            continue
        rms = np.sqrt(cost / len(pts))
        if rms > cfg.scan_rms_max_m:
            reasons.append(f"fold RMS {rms * 1000:.0f} mm")
            continue
        res = _refine_fold(pts, (iF, iG, iH), cfg)
        if isinstance(res, str):
            reasons.append(res)
            continue
        score = rms / max(res[5], 1e-4) - 0.001 * len(pts)
        if best is None or score < best[0]:
            best = (score, res, pts, rms)
    if best is None:
        why = "; ".join(sorted(set(reasons))[:3]) if reasons else "no cluster of board size"
        raise FeatureError(f"scan: board not found ({why})")
    _, (corners, cov, faces, lines, ends, sig, src), pts, rms = best
    return ScanFeatures(corners, cov, faces, lines, all_xy, pts, float(rms), ends, float(sig), src)


def _range_sigma(segs, lines, prior: float) -> tuple[float, str]:
    """Along-beam range noise from the perpendicular residuals of the three
    lines (robust: MAD), each divided by |cos| between beam and line normal.
    Falls back to the prior with fewer than 20 points."""
    ratios = []
    for s, (p, u) in zip(segs, lines):
        if len(s) < 3:
            continue
        nrm = np.array([-u[1], u[0]])
        beam = s / np.maximum(np.linalg.norm(s, axis=1, keepdims=True), 1e-9)
        c = np.abs(beam @ nrm)
        ok = c > 0.2
        ratios.append(np.abs(line_2d_distances(s[ok], p, u)) / c[ok])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(r) < 20:
        return prior, "prior"
    # MAD of residuals of a fitted line: correct for the 2 fitted parameters per line
    n = len(r)
    return float(max(1.4826 * np.median(r) * math.sqrt(n / max(n - 6, 1)), 1e-5)), "data"


def _fold_corners(lines) -> np.ndarray | None:
    """F, G, H (3,2): intersections base/FG, FG/GH, GH/base; None if two
    segments are nearly parallel (no fold)."""
    try:
        return np.stack([intersect_lines_2d(*lines[a], *lines[b], min_angle_rad=np.radians(5))
                         for a, b in ((0, 1), (1, 2), (2, 0))])
    except FitError:
        return None


def _refine_fold(pts: np.ndarray, brk, cfg: FeatureConfig):
    """Refit the three lines on trimmed inliers; corners and checks.

    Returns a tuple or a reason string."""
    iF, iG, iH = brk
    k = cfg.min_points_per_segment
    segs = [np.concatenate([pts[:iF], pts[iH:]]), pts[iF:iG], pts[iG:iH]]
    lines = []
    for s in segs:
        lines.append(fit_line_2d_lsq(s))
    corners = _fold_corners(lines)
    if corners is None:
        return "segments nearly parallel: no fold"
    trimmed = []
    for fi, s in enumerate(segs):
        keep = np.ones(len(s), bool)
        for c in {0: (0, 2), 1: (0, 1), 2: (1, 2)}[fi]:
            keep &= np.linalg.norm(s - corners[c], axis=1) > max(cfg.corner_trim_m, 0.03)
        trimmed.append(s[keep])
    sig, src = _range_sigma(trimmed, lines, cfg.laser_sigma_m)
    for _ in range(2):
        new_faces = []
        for fi, s in enumerate(segs):
            p, u = lines[fi]
            d = np.abs(line_2d_distances(s, p, u))
            keep = d < max(3.0 * sig, 0.02)
            # trim points near the corners that bound this face
            cs = {0: (0, 2), 1: (0, 1), 2: (1, 2)}[fi]
            for c in cs:
                keep &= np.linalg.norm(s - corners[c], axis=1) > cfg.corner_trim_m
            if keep.sum() < max(3, k // 2):
                return f"only {int(keep.sum())} laser points on the {('base', 'ABC', 'ACD')[fi]} segment"
            new_faces.append(s[keep])
            lines[fi] = fit_line_2d_lsq(s[keep])
        corners = _fold_corners(lines)
        if corners is None:
            return "segments nearly parallel: no fold"
    faces = new_faces
    sig, src = _range_sigma(faces, lines, cfg.laser_sigma_m)
    F, G, H = corners
    depth = abs(float(line_2d_distances(G[None], *lines[0])[0]))
    if depth < cfg.min_fold_depth_m:
        return f"fold depth {depth * 1000:.0f} mm too small (flat object, only 1 line)"
    if np.linalg.norm(H - F) > 1.2 * cfg.board.width_m:
        return f"F-H distance {np.linalg.norm(H - F):.2f} m larger than the board"
    cov = np.stack([
        corner_covariance(lines[0], faces[0], lines[1], faces[1], sig, F),
        corner_covariance(lines[1], faces[1], lines[2], faces[2], sig, G),
        corner_covariance(lines[2], faces[2], lines[0], faces[0], sig, H)])
    ends = np.stack([pts[0], pts[-1]])
    return corners, cov, tuple(faces), tuple(lines), ends, sig, src


# ----------------------------------------------------------------------------
# Depth
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class DepthNoise:
    """Depth noise of one image, estimated from the data: sigma at depth z is
    interpolated (in log z) between per-depth-band estimates ``band_sigma_m``
    at ``band_z_m`` and extrapolated as z^2 outside; ``k_per_m`` is the
    summary sigma / z^2; ``floor_m`` the quantisation / systematic floor."""
    k_per_m: float
    floor_m: float
    samples: int
    source: str
    band_z_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    band_sigma_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def sigma(self, z) -> np.ndarray:
        z = np.asarray(z, dtype=float)
        if self.band_z_m.size >= 2:
            lk = np.interp(np.log(np.maximum(z, 1e-3)), np.log(self.band_z_m),
                           np.log(self.band_sigma_m / self.band_z_m ** 2))
            s = np.exp(lk) * z * z
        else:
            s = self.k_per_m * z * z
        return np.sqrt(s * s + self.floor_m ** 2)


@dataclasses.dataclass
class DepthFeatures:
    """Camera features in the camera optical frame (metres).

    ``planes`` (3,4) rows [n, d] of back plane, ABC, ACD (normals towards the
    camera); ``stats`` PlaneStats per plane; ``lines`` AB, AC, AD as (point,
    unit_dir); ``A`` the common point of the three planes; ``points`` per
    plane (subsampled inliers); ``pixel_index`` per plane (v * width + u);
    ``noise`` the depth noise estimated from the image; ``angles_deg`` the
    measured fold angles (back-ABC, back-ACD, ABC-ACD)."""
    planes: np.ndarray
    stats: tuple
    lines: tuple
    A: np.ndarray
    points: tuple
    pixel_index: tuple
    noise: DepthNoise | None = None
    angles_deg: tuple = ()


def _quantisation_m(Z: np.ndarray) -> float:
    """Standard deviation of the rounding of a depth image stored in whole
    millimetres (16UC1), else 0."""
    v = Z[np.isfinite(Z)]
    if v.size == 0:
        return 0.0
    v = v[:: max(1, v.size // 2000)] * 1000.0
    return 0.001 / math.sqrt(12.0) if np.mean(np.abs(v - np.round(v)) < 1e-3) > 0.99 else 0.0


def estimate_depth_noise(Z: np.ndarray, prior_k: float, floor_m: float = 0.0) -> DepthNoise:
    """Depth noise from the image itself: second differences of neighbouring
    (decimated) depths along rows and columns are ``sqrt(6) sigma`` on any
    smooth surface; edges are outliers, so per depth band sigma is the
    scaled median absolute value. Too few samples -> the prior ``k``."""
    q = _quantisation_m(Z)
    floor = max(floor_m, q)
    rs, zs = [], []
    for a, b, c in ((Z[:, :-2], Z[:, 1:-1], Z[:, 2:]), (Z[:-2], Z[1:-1], Z[2:])):
        with np.errstate(invalid="ignore"):
            d2 = a - 2.0 * b + c
        ok = np.isfinite(d2)
        rs.append(np.abs(d2[ok]))
        zs.append(b[ok])
    r = np.concatenate(rs) / math.sqrt(6.0)
    z = np.concatenate(zs)
    if r.size > 60000:
        step = r.size // 60000 + 1
        r, z = r[::step], z[::step]
    if r.size < 300:
        return DepthNoise(prior_k, floor, int(r.size), "prior")
    nb = int(np.clip(r.size // 3000, 1, 8))
    edges = np.quantile(z, np.linspace(0, 1, nb + 1))
    bz, bs = [], []
    for i in range(nb):
        m = (z >= edges[i]) & (z <= edges[i + 1])
        if m.sum() < 100:
            continue
        s = 1.4826 * float(np.median(r[m]))
        s = math.sqrt(max(s * s - q * q, 0.0))  # rounding adds q^2 to the differences' variance
        bz.append(float(np.median(z[m])))
        bs.append(max(s, 1e-5))
    if not bz:
        return DepthNoise(prior_k, floor, int(r.size), "prior")
    bz, bs = np.array(bz), np.array(bs)
    # monotone in z: the noise of a depth camera does not fall with range
    k = float(np.median(bs / bz ** 2))
    if bz.size >= 2:
        order = np.argsort(bz)
        bz, bs = bz[order], np.maximum.accumulate(bs[order])
    return DepthNoise(k, floor, int(r.size), "data", bz, bs)


_GRID_CACHE: dict = {}


def _depth_grid(depth: np.ndarray, cam, stride: int):
    """Decimated z-depth grid ``Z`` (h,w; NaN invalid), points ``P`` (h,w,3),
    and pixel index of every grid cell."""
    H, W = cam.height, cam.width
    if depth.shape != (H, W):
        raise FeatureError(f"depth: image is {depth.shape[1] if depth.ndim > 1 else '?'}x{depth.shape[0]} "
                           f"but the CameraInfo says {W}x{H}")
    key = (id(cam), stride)
    if key not in _GRID_CACHE:
        if len(_GRID_CACHE) > 8:
            _GRID_CACHE.clear()
        rays = cam.pixel_rays().reshape(H, W, 3)[::stride, ::stride].astype(np.float32)
        v, u = np.mgrid[0:H:stride, 0:W:stride]
        _GRID_CACHE[key] = (cam, rays, (v * W + u).astype(np.int64))
    _, rays, pix = _GRID_CACHE[key]
    Z = np.asarray(depth[::stride, ::stride], dtype=np.float32).copy()
    Z[~(np.isfinite(Z) & (Z > 0))] = np.nan
    P = rays * Z[..., None]
    return Z, P, pix


def _normals(P: np.ndarray, valid: np.ndarray, sigma: np.ndarray, f_eff: float, cfg: FeatureConfig):
    """Smoothed points ``M`` and unit normals ``N`` (towards the camera) with
    a window per pixel that grows with the depth noise there, so the normal
    noise stays near ``depth_normal_sigma_deg``; ``good`` where a normal
    exists, ``sig_n`` its expected noise (rad)."""
    import cv2
    h, w = valid.shape
    z = np.where(valid, P[..., 2], np.nan)
    target = min(cfg.depth_normal_sigma_deg, max(1.0, min(cfg.board.normal_angles_deg()) / 6.0))
    tan_t = math.tan(math.radians(target))
    with np.errstate(invalid="ignore", divide="ignore"):
        need = np.sqrt(math.sqrt(2.0) * sigma * f_eff / (z * tan_t))
    kmax = max(3, int(cfg.depth_normal_window_max) | 1)
    sizes = sorted({k for k in (3, 5, 7, 9, 13, 17, 25, 33, 45, 61) if k < kmax} | {kmax})
    choice = np.full((h, w), -1, np.int64)
    fin = np.isfinite(need)
    ki = np.searchsorted(np.array(sizes, float), np.where(fin, need, 0.0))
    ki = np.minimum(ki, len(sizes) - 1)
    choice[fin] = ki[fin]
    Pz = np.where(valid[..., None], P, 0.0).astype(np.float32)
    vf = valid.astype(np.float32)
    M = np.zeros((h, w, 3), np.float32)
    N = np.zeros((h, w, 3), np.float32)
    good = np.zeros((h, w), bool)
    sig_n = np.full((h, w), np.inf, np.float32)
    for j in np.unique(choice[choice >= 0]):
        k = sizes[int(j)]
        o = k // 2
        cnt = cv2.boxFilter(vf, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        S = cv2.boxFilter(Pz, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        Mk = S / np.maximum(cnt, 1.0)[..., None]
        big = cv2.boxFilter(vf, -1, (k + 2 * o, k + 2 * o), normalize=True, borderType=cv2.BORDER_CONSTANT)
        du = np.zeros_like(Mk)
        dv = np.zeros_like(Mk)
        du[:, o:w - o] = Mk[:, 2 * o:] - Mk[:, :w - 2 * o]
        dv[o:h - o, :] = Mk[2 * o:, :] - Mk[:h - 2 * o, :]
        Nk = np.empty_like(du)
        Nk[..., 0] = du[..., 1] * dv[..., 2] - du[..., 2] * dv[..., 1]
        Nk[..., 1] = du[..., 2] * dv[..., 0] - du[..., 0] * dv[..., 2]
        Nk[..., 2] = du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]
        nn = np.sqrt(np.einsum("ijk,ijk->ij", Nk, Nk))
        sel = (choice == j) & valid & (big >= 0.7) & (nn > 1e-12)
        M[sel] = Mk[sel]
        N[sel] = Nk[sel] / nn[sel][:, None]
        good |= sel
        with np.errstate(invalid="ignore", divide="ignore"):
            sn = math.sqrt(2.0) * sigma * f_eff / (z * k * k)
        sig_n[sel] = sn[sel]
    flip = np.einsum("ijk,ijk->ij", N, M) > 0
    N[flip] *= -1
    return M, N, good, sig_n


def _component(mask: np.ndarray, seed: int) -> np.ndarray:
    """Flat mask of the 8-connected component of ``mask`` (h,w) holding the
    flat index ``seed`` (the largest one if the seed is not in the mask)."""
    import cv2
    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    lab = lab.ravel()
    L = lab[seed]
    if L == 0:
        if n <= 1:
            return np.zeros(lab.size, bool)
        cnt = np.bincount(lab, minlength=n)
        cnt[0] = 0
        L = int(np.argmax(cnt))
    return lab == L


def _extract_planes(Pf, Mf, Nf, good, valid, S, cosT, shape, cfg: FeatureConfig, rng) -> list:
    """Planes ``(n, d, idx)`` (idx: flat grid indices) by one-point RANSAC on
    (smoothed point, normal) pairs; every hypothesis is grown as the connected
    region of free pixels within ``depth_nsigma`` of the plane whose normal
    agrees within the pixel's noise-scaled tolerance, and refitted."""
    import cv2
    nsig = np.float32(cfg.depth_nsigma)
    minp = cfg.depth_min_plane_points
    # work on the pixels with a normal only; they shrink as planes are taken
    cand = np.flatnonzero(good & valid)
    P, N, Th, C = Pf[cand], Nf[cand], nsig * S[cand], cosT[cand]
    Ms = Mf[cand]
    alive = np.ones(cand.size, bool)
    img = np.zeros(shape[0] * shape[1], np.uint8)
    out = []
    fails = 0
    while len(out) < cfg.depth_max_planes and fails < 12:
        na = int(alive.sum())
        if na < minp:
            break
        if na < 0.7 * alive.size:  # compact: later planes cost less
            cand, P, N, Th, C, Ms = (a[alive] for a in (cand, P, N, Th, C, Ms))
            alive = np.ones(cand.size, bool)
        idx = np.flatnonzero(alive)
        seeds = rng.choice(idx, min(cfg.depth_ransac_hypotheses, idx.size), replace=False)
        sub = rng.choice(idx, min(800, idx.size), replace=False)
        ns = N[seeds]
        ds = -np.einsum("ij,ij->i", ns, Ms[seeds])
        ok = (np.abs(P[sub] @ ns.T + ds) < Th[sub][:, None]) & ((N[sub] @ ns.T) > C[sub][:, None])
        b = int(np.argmax(ok.sum(axis=0)))
        n, d, seed = ns[b].astype(np.float32), np.float32(ds[b]), int(seeds[b])
        comp = np.zeros(0, np.int64)
        m = np.zeros(0, np.int64)
        for _ in range(2):
            mm = alive & (np.abs(P @ n + d) < Th) & ((N @ n) > C)
            m = np.flatnonzero(mm)
            img[:] = 0
            img[cand[m]] = 1
            nl, lab = cv2.connectedComponents(img.reshape(shape), connectivity=8)
            lab = lab.ravel()[cand[m]]
            L = lab[np.searchsorted(m, seed)] if mm[seed] else 0
            if L == 0:
                if nl <= 1:
                    comp = m[:0]
                    break
                cnt = np.bincount(lab, minlength=nl)
                cnt[0] = 0
                L = int(np.argmax(cnt))
            comp = m[lab == L]
            if comp.size < minp:
                break
            try:
                n64, d64 = fit_plane_lsq(P[comp].astype(np.float64),
                                         weights=1.0 / (Th[comp].astype(np.float64)) ** 2)
            except FitError:
                comp = m[:0]
                break
            n, d = n64.astype(np.float32), np.float32(d64)
        if comp.size < minp:
            alive[seed] = False
            alive[m] = False
            fails += 1
            continue
        out.append((np.asarray(n, np.float64), float(d), cand[comp]))
        # the plane's pixels, connected or not, seed nothing new
        alive[m] = False
        alive[comp] = False
    return out


def extract_depth_features(frame, cfg: FeatureConfig | None = None,
                           prior: DepthFeatures | None = None) -> DepthFeatures:
    """Find the three board planes in a depth image; see the module docstring.

    ``prior``: the board found earlier in the same static scene (e.g. in the
    first frames of a stop): its planes start the refit directly (no search)."""
    cfg = cfg or FeatureConfig()
    cam = frame.camera
    depth = np.asarray(frame.depth_m, dtype=np.float32)
    s = max(int(cfg.depth_stride), math.ceil(cam.width / float(cfg.depth_grid_width_px)))
    Z, P, pixg = _depth_grid(depth, cam, s)
    with np.errstate(invalid="ignore"):
        Z[Z > cfg.depth_max_m] = np.nan
    valid = np.isfinite(Z)
    nvalid = int(valid.sum())
    if nvalid < 3 * cfg.depth_min_plane_points:
        raise FeatureError(f"depth: no valid depth pixels ({nvalid} valid points within "
                           f"{cfg.depth_max_m:.1f} m)" if nvalid == 0 else
                           f"depth: too few valid depth pixels ({nvalid})")
    noise = estimate_depth_noise(Z, cfg.depth_sigma_k, cfg.depth_sigma_floor_m)
    sigma = np.where(valid, noise.sigma(np.where(valid, Z, 1.0)), np.inf).astype(np.float32)
    if prior is not None:
        Pd = np.where(valid[..., None], P, 0.0).reshape(-1, 3).astype(np.float64)
        sig = sigma.ravel().astype(np.float64)
        vi = np.flatnonzero(valid.ravel())
        gw = Z.shape[1]
        cands = []
        for row, px in zip(prior.planes, prior.pixel_index):
            g = (px // cam.width // s) * gw + (px % cam.width) // s
            g = g[valid.ravel()[g]]
            cands.append((row[:3], float(row[3]), g))
        if min(len(c[2]) for c in cands) >= 10:
            return _refine_board((0, 1, 2), cands, Pd, pixg.ravel(), sig, vi, noise, cfg, Z.shape, valid.ravel())
    f_eff = float(cam.K[0, 0]) / s
    M, N, good, sig_n = _normals(P, valid, sigma, f_eff, cfg)
    min_fold = min(cfg.board.normal_angles_deg())
    tol = np.clip(3.0 * np.degrees(sig_n), 6.0, max(6.0, 0.45 * min_fold))
    cosT = np.cos(np.radians(tol)).astype(np.float32).ravel()
    shape = Z.shape
    Pf = np.where(valid[..., None], P, 0.0).reshape(-1, 3).astype(np.float32)
    rng = np.random.default_rng(cfg.seed)
    cands = _extract_planes(Pf, M.reshape(-1, 3), N.reshape(-1, 3), good.ravel(), valid.ravel(),
                            sigma.ravel(), cosT, shape, cfg, rng)
    Pd = Pf.astype(np.float64)
    sig = sigma.ravel().astype(np.float64)
    cands = _merge_coplanar(cands, Pd, sig, cfg)
    if len(cands) < 3:
        raise FeatureError(f"depth: only {len(cands)} planes found (need the back plane and both triangles; "
                           f"depth noise {1000 * noise.k_per_m:.1f} mm at 1 m)")
    triple, why = _choose_board(cands, Pd, sig, cfg, s / float(cam.K[0, 0]))
    if triple is None:
        raise FeatureError(f"depth: board not found among {len(cands)} planes ({why})")
    vi = np.flatnonzero(valid.ravel())
    return _refine_board(triple, cands, Pd, pixg.ravel(), sig, vi, noise, cfg, shape, valid.ravel())


def _merge_coplanar(cands: list, pts: np.ndarray, sig: np.ndarray, cfg: FeatureConfig) -> list:
    """Merge segments of one plane cut apart by something in front of it (the
    back rectangle is split by the triangles): a pair merges when each one's
    points lie, on average, within ``depth_nsigma`` sigmas of the other's
    plane and the normals agree within 5 degrees."""
    cands = list(cands)
    merged = True
    while merged:
        merged = False
        for i in range(len(cands)):
            for j in range(i + 1, len(cands)):
                (ni, di, ii), (nj, dj, jj) = cands[i], cands[j]
                if ni @ nj < np.cos(np.radians(5.0)):
                    continue
                ri = np.mean(np.abs(pts[jj] @ ni + di) / sig[jj])
                rj = np.mean(np.abs(pts[ii] @ nj + dj) / sig[ii])
                if max(ri, rj) < cfg.depth_nsigma:
                    idx = np.concatenate([ii, jj])
                    n, d = fit_plane_lsq(pts[idx], weights=1.0 / sig[idx] ** 2)
                    cands[i] = (n, d, idx)
                    del cands[j]
                    merged = True
                    break
            if merged:
                break
    return cands


def _touch(ci, cj, si, sj, cfg) -> bool:
    """Both planes have >= 5 (subsampled) points within ``depth_touch_m`` (plus
    twice their noise) of the planes' intersection line. ``si``/``sj``:
    (points, sigmas) subsamples of the two candidates."""
    try:
        p0, u = intersect_planes(ci[:2], cj[:2])
    except FitError:
        return False
    for P, S in (si, sj):
        q = P - p0
        t = q @ u
        dist2 = np.einsum("ij,ij->i", q, q) - t * t
        if int((dist2 < (cfg.depth_touch_m + 2 * S) ** 2).sum()) < 5:
            return False
    return True


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(a @ b)), 0.0, 1.0))))


def _area_m2(c, pts, px_per_m: float) -> float:
    """Metric area of a plane candidate: each decimated pixel covers
    (z s / f)^2 / |cos(incidence)| square metres."""
    p = pts[c[2]]
    z = p[:, 2]
    cosi = np.abs(p @ c[0]) / np.maximum(np.linalg.norm(p, axis=1), 1e-9)
    return float(np.sum((z * px_per_m) ** 2 / np.maximum(cosi, 0.2)))


def _choose_board(cands, pts, sig, cfg, px_per_m: float):
    """((back, tri_a, tri_b) candidate indices, "") of the board, or (None, reason).

    A triple qualifies when its planes touch pairwise, meet near all three
    and the triangles are no larger than the board's; among those the one
    whose fold angles best match the configured board is taken, if within
    ``depth_angle_tol_deg`` per fold; otherwise the reason gives the
    measured angles of the best-shaped triple and the configured ones."""
    K = len(cands)
    board = cfg.board
    model = board.normal_angles_deg()
    areas_model = board.face_areas_m2()
    ext = []
    for _n, _d, idx in cands:
        q = pts[idx] - pts[idx].mean(axis=0)
        ext.append(float(2.0 * np.sqrt(max(np.linalg.eigvalsh(q.T @ q / len(idx))[-1], 0.0)) * 1.73))
    area = [_area_m2(c, pts, px_per_m) for c in cands]
    sel = [c[2][:: max(1, len(c[2]) // 1500)] for c in cands]
    subs = [pts[x] for x in sel]
    tsub = [(pts[x[:: max(1, len(x) // 500)]], sig[x[:: max(1, len(x) // 500)]]) for x in sel]
    limit = 1.3 * board.max_extent_m()
    tri_ok = [ext[i] <= limit and area[i] <= 1.8 * max(areas_model[1:]) for i in range(K)]
    base_ok = [ext[i] <= 2.0 * limit for i in range(K)]
    touch = {}

    def touches(i, j):
        key = (min(i, j), max(i, j))
        if key not in touch:
            touch[key] = _angle(cands[i][0], cands[j][0]) > 8.0 and _touch(cands[i], cands[j], tsub[i], tsub[j], cfg)
        return touch[key]

    best, best_any = None, None
    for i in range(K):
        if not base_ok[i]:
            continue
        for j in range(K):
            for k in range(K):
                if len({i, j, k}) < 3 or not (tri_ok[j] and tri_ok[k]):
                    continue
                # the left/right order of the triangles is decided later; j < k avoids doing it twice
                # unless the board is asymmetric (then both orders are compared with the model)
                if j > k and abs(model[0] - model[1]) < 1e-6:
                    continue
                obs = (_angle(cands[i][0], cands[j][0]), _angle(cands[i][0], cands[k][0]),
                       _angle(cands[j][0], cands[k][0]))
                if min(obs) < 10.0:
                    continue
                if not (touches(i, j) and touches(i, k) and touches(j, k)):
                    continue
                try:
                    A = intersect_three_planes([cands[m][:2] for m in (i, j, k)])
                except FitError:
                    continue
                near = [float(np.min(np.linalg.norm(subs[m] - A, axis=1))) for m in (i, j, k)]
                if max(near) > 0.15 + cfg.depth_touch_m:
                    continue
                err = max(abs(o - m) for o, m in zip(obs, model))
                score = -err + 1e-7 * sum(len(cands[m][2]) for m in (i, j, k))
                if best_any is None or score > best_any[0]:
                    best_any = (score, (i, j, k), obs)
                # candidate planes are rough: twice the tolerance here, the refit is held to it
                if err <= 2.0 * cfg.depth_angle_tol_deg and (best is None or score > best[0]):
                    best = (score, (i, j, k))
    if best is not None:
        return best[1], ""
    if best_any is not None:
        o = best_any[2]
        return None, (f"a folded board is seen with fold angles {o[0]:.0f}/{o[1]:.0f}/{o[2]:.0f} deg "
                      f"(back-left, back-right, left-right), configured {model[0]:.0f}/{model[1]:.0f}/"
                      f"{model[2]:.0f} deg: check the board_* parameters")
    return None, ("no three planes touching pairwise with the board's size and fold angles; "
                  "board partly seen, too far or too noisy?")


def _plane_sigmas(P: np.ndarray, planes, noise: DepthNoise) -> tuple[np.ndarray, np.ndarray]:
    """(distance in sigmas (N,3), sigma (N,3)) of every point to each plane.

    The depth sigma is taken at the depth the *plane* predicts along the
    pixel's ray, not at the measured depth: weighting by the measured depth
    favours points whose noise brought them closer and biases the fitted
    plane towards the camera (about 4 sigma^2 / z, millimetres at 3 m)."""
    r = P / P[:, 2:3]
    D = np.empty((len(P), len(planes)))
    S = np.empty((len(P), len(planes)))
    for f, (n, d) in enumerate(planes):
        den = r @ n
        z = np.where(np.abs(den) > 1e-6, -d / np.where(np.abs(den) > 1e-6, den, 1.0), P[:, 2])
        z = np.where(z > 0, z, P[:, 2])
        S[:, f] = noise.sigma(z)
        D[:, f] = np.abs(P @ n + d) / S[:, f]
    return D, S


def _face_inliers(P: np.ndarray, D: np.ndarray, Sp: np.ndarray, labels: np.ndarray, planes,
                  nsigma: float, band_factor: float = 2.0) -> np.ndarray:
    """Points within ``nsigma`` of their plane and outside the bands along the
    folds where two planes cannot be told apart.

    Near a fold a point fits both planes; which one it is given to depends on
    its noise, so any residual-based rule keeps the points whose noise pushed
    them away from the other face and biases both planes (millimetres at 3 m).
    The band is measured *in the plane* (point projected onto its plane, then
    distance to the fold line), which does not depend on the noise along the
    normal: no selection bias."""
    ok = D[np.arange(len(P)), labels] < nsigma
    for f in range(len(planes)):
        m = np.nonzero(ok & (labels == f))[0]
        n_f, d_f = planes[f]
        q = P[m] - np.outer(P[m] @ n_f + d_f, n_f)
        for g in range(len(planes)):
            if g == f:
                continue
            try:
                p0, u = intersect_planes(planes[f], planes[g])
            except FitError:
                continue
            sin_t = np.linalg.norm(np.cross(n_f, planes[g][0]))
            band = band_factor * nsigma * Sp[m, g] / max(sin_t, 0.05)
            w = q - p0
            dist = np.linalg.norm(w - np.outer(w @ u, u), axis=1)
            ok[m[dist < band]] = False
    return ok


_FACE_LABELS = ("back plane", "first triangle", "second triangle")


def _board_region(region: np.ndarray, valid: np.ndarray, shape, close_px: int) -> np.ndarray:
    """Grid indices of the board's image region: the three faces' pixels,
    closed over the fold bands between them (where normals were blurred) and
    grown by two pixels, valid depth only. Other surfaces inside the board's
    3D bounding box (the floor under it) stay out."""
    import cv2
    m = np.zeros(shape[0] * shape[1], np.uint8)
    m[region] = 1
    m = m.reshape(shape)
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px | 1, close_px | 1)))
    m = cv2.dilate(m, np.ones((5, 5), np.uint8))
    return np.flatnonzero(m.ravel().astype(bool) & valid)


def _refine_board(triple, cands, pts, pixg, sig, vi, noise: DepthNoise, cfg, shape=None,
                  valid=None) -> DepthFeatures:
    i, j, k = triple
    planes = [cands[m][:2] for m in (i, j, k)]
    region = np.concatenate([cands[m][2] for m in (i, j, k)])
    if shape is not None and cfg.depth_region_close_px > 0:
        bidx = _board_region(region, valid, shape, cfg.depth_region_close_px)
    else:
        lo = pts[region].min(axis=0) - 0.05
        hi = pts[region].max(axis=0) + 0.05
        Pv = pts[vi]
        bidx = vi[np.all((Pv >= lo) & (Pv <= hi), axis=1)]
    P = pts[bidx]
    # which face's region (grown with agreeing normals, so without the blurred
    # fold bands) each point came from: those keep their face near the folds
    memb = np.full(pts.shape[0], -1, np.int64)
    for f, m in enumerate((i, j, k)):
        memb[cands[m][2]] = f
    memb = memb[bidx]

    def inliers(D, Sp, labels):
        near = _face_inliers(P, D, Sp, labels, planes, cfg.depth_nsigma, 1.0) & (memb == labels)
        return near | _face_inliers(P, D, Sp, labels, planes, cfg.depth_nsigma, 2.0)

    labels = None
    for _ in range(cfg.depth_refit_iterations):
        D, Sp = _plane_sigmas(P, planes, noise)
        labels = np.argmin(D, axis=1)
        ok = inliers(D, Sp, labels)
        new = []
        for f in range(3):
            m = ok & (labels == f)
            if m.sum() < 10:
                raise FeatureError(f"depth: only {int(m.sum())} points left on the {_FACE_LABELS[f]} after "
                                   "the refit (board too small in the image or too noisy)")
            new.append(fit_plane_lsq(P[m], weights=1.0 / Sp[m, f] ** 2))
        planes = new
    D, Sp = _plane_sigmas(P, planes, noise)
    labels = np.argmin(D, axis=1)
    ok = inliers(D, Sp, labels)
    model = cfg.board.normal_angles_deg()
    # left/right: ABC is the triangle further left in the image (smaller x/z)
    cen = []
    for f in (1, 2):
        q = P[ok & (labels == f)]
        cen.append(np.mean(q[:, 0] / q[:, 2]))
    order = [0, 1, 2] if cen[0] <= cen[1] else [0, 2, 1]
    planes = [planes[f] for f in order]
    ang = (_angle(planes[0][0], planes[1][0]), _angle(planes[0][0], planes[2][0]),
           _angle(planes[1][0], planes[2][0]))
    if max(abs(a - m) for a, m in zip(ang, model)) > cfg.depth_angle_tol_deg:
        raise FeatureError(f"depth: board planes refitted with fold angles {ang[0]:.1f}/{ang[1]:.1f}/{ang[2]:.1f} "
                           f"deg (back-left, back-right, left-right), configured {model[0]:.1f}/{model[1]:.1f}/"
                           f"{model[2]:.1f} deg: wrong board_* parameters or a mixed-up face")
    stats, points, pixels = [], [], []
    rng = np.random.default_rng(cfg.seed + 1)
    for f in order:
        m = ok & (labels == f)
        Pm = P[m]
        n, d = planes[len(stats)]
        # per-point perpendicular sigma: along-ray sigma times |cos(incidence)|
        ray = Pm / np.linalg.norm(Pm, axis=1, keepdims=True)
        sp = np.maximum(Sp[m, f] * np.abs(ray @ n), 1e-5)
        stats.append(PlaneStats.from_points(Pm, n, d, weights=1.0 / sp ** 2))
        sel = np.arange(len(Pm))
        if len(sel) > cfg.keep_points_per_plane:
            sel = np.sort(rng.choice(len(sel), cfg.keep_points_per_plane, replace=False))
        points.append(Pm[sel])
        pixels.append(pixg[bidx][m][sel])
    pl = np.array([[*n, d] for n, d in planes])
    try:
        lines = tuple(intersect_planes(planes[a], planes[b]) for a, b in ((0, 1), (1, 2), (2, 0)))
        A = intersect_three_planes(planes)
    except FitError as e:
        raise FeatureError(f"depth: board planes degenerate ({e})") from e
    return DepthFeatures(pl, tuple(stats), lines, A, tuple(points), tuple(pixels), noise, ang)


def make_observation(scan: ScanFeatures, depth: DepthFeatures, stamp_s: float = 0.0,
                     laser_sigma_m: float | None = None) -> LrfObservation:
    """Pair laser and camera features into one solver observation. The laser
    noise is the one estimated from the scan (``laser_sigma_m`` overrides it)."""
    sig = laser_sigma_m if laser_sigma_m is not None else scan.sigma_m
    if not (sig is not None and np.isfinite(sig) and sig > 0):
        sig = 0.0125
    return LrfObservation(corners_laser_m=scan.corners_m, planes_cam=depth.planes,
                          face_points_laser_m=scan.face_points_m, plane_stats=depth.stats,
                          corner_cov_laser=scan.corner_cov, stamp_s=stamp_s, laser_sigma_m=float(sig),
                          depth_noise=depth.noise)
