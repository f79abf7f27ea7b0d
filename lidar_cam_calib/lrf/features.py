"""Feature extraction for the lrf method (paper 003, Section 3.1), ROS-free.

Laser (:func:`extract_scan_features`): the scan line crosses the folded board
as E-F-G-H-I. EF and HI lie on the base (one line), FG on triangle ABC, GH on
triangle ACD. We cluster the scan by range jumps and fit, on every cluster,
the *folded-line model* "base line, FG, GH, base line again" by exhaustive
search of the three break points (prefix-sum moments, total least squares;
coarse grid then local refinement). The cluster whose fold fits best and
matches the board size is the board. Lines are refitted on the inliers away
from the corners; F, G, H are line intersections, with covariances.

Depth (:func:`extract_depth_features`): back-project the depth image (with a
stride), cut it into planar segments where smoothed normals change or depth
jumps (:func:`_segment_planes`), fit a RANSAC plane with per-point thresholds
(stereo noise sigma = k z^2) to each segment, choose the triple of planes that touch pairwise and meet in one point
near all three (the board), refit the three by a k-planes assignment and
weighted least squares, and intersect them into AB, AC, AD.

Correspondence: the laser ordering E..I is left-to-right (decreasing laser
angle, angle grows to the left); the camera triangle whose centroid is further
left (smaller x/z) is ABC. So FG <-> ABC (plane 2) and GH <-> ACD (plane 3).
That holds when both sensors are upright; :func:`solvers.resolve_assignment`
verifies it (tries the swap and keeps the lower residual).

Board frame (same as lidar_cam_calib.sim.scenario.BoardConfig): origin at the
bottom-centre of the base rectangle PBDQ, x to the viewer's right, y up, z out
of the front face. B/D top-left/top-right, A on the base, apex C.

Failures raise :class:`FeatureError` with a reason string.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.fitting import (FitError, fit_line_2d_lsq, fit_plane_lsq, intersect_lines_2d,
                            intersect_planes, intersect_three_planes, line_2d_distances,
                            ransac_plane)
from ..core.errors import CalibError
from .solvers import LrfObservation, PlaneStats


class FeatureError(CalibError):
    """Feature extraction failed; ``str(err)`` is the reason shown to the user."""


# ----------------------------------------------------------------------------
# Board and configuration
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class BoardModel:
    width_m: float = 1.0
    height_m: float = 1.0
    a_xy_m: tuple = (0.0, 0.0)
    c_xyz_m: tuple = (0.0, 1.0, 0.6)

    @classmethod
    def from_config(cls, cfg) -> "BoardModel":
        """From a sim BoardConfig-like object (width_m, height_m, a_xy_m, c_xyz_m)."""
        return cls(float(cfg.width_m), float(cfg.height_m), tuple(cfg.a_xy_m), tuple(cfg.c_xyz_m))

    @property
    def vertices(self) -> dict:
        w, h = self.width_m, self.height_m
        return {"P": np.array([-w / 2, 0.0, 0.0]), "Q": np.array([w / 2, 0.0, 0.0]),
                "B": np.array([-w / 2, h, 0.0]), "D": np.array([w / 2, h, 0.0]),
                "A": np.array([self.a_xy_m[0], self.a_xy_m[1], 0.0]),
                "C": np.array(self.c_xyz_m, dtype=float)}

    def face_triangles(self) -> list:
        """Triangles (board frame) per face: base as two triangles, ABC, ACD."""
        v = self.vertices
        return [[np.stack([v["P"], v["Q"], v["D"]]), np.stack([v["P"], v["D"], v["B"]])],
                [np.stack([v["A"], v["B"], v["C"]])],
                [np.stack([v["A"], v["C"], v["D"]])]]

    def normal_angles_deg(self) -> tuple:
        """Angles between the face normals: (base-ABC, base-ACD, ABC-ACD)."""
        v = self.vertices
        nb = np.array([0.0, 0.0, 1.0])
        n1 = np.cross(v["B"] - v["A"], v["C"] - v["A"])
        n2 = np.cross(v["C"] - v["A"], v["D"] - v["A"])
        n1, n2 = n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2)
        ang = lambda a, b: float(np.degrees(np.arccos(np.clip(abs(a @ b), 0.0, 1.0))))  # noqa: E731
        return ang(nb, n1), ang(nb, n2), ang(n1, n2)

    def max_extent_m(self) -> float:
        pts = np.stack(list(self.vertices.values()))
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))


@dataclasses.dataclass
class FeatureConfig:
    """Feature-extraction parameters (metres, degrees)."""
    board: BoardModel = dataclasses.field(default_factory=BoardModel)
    # laser
    laser_sigma_m: float = 0.0125          # a-priori range noise (R2000: +/-25 mm = 2 sigma)
    scan_max_range_m: float = 8.0          # ignore beams farther than this
    scan_angle_window_deg: tuple | None = None  # (min, max) laser angles to search, None = all
    cluster_gap_m: float = 0.10            # range jump that separates clusters
    min_points_per_segment: int = 8
    scan_grid_points: int = 70             # coarse break-point grid per cluster
    scan_rms_max_m: float = 0.04           # folded-model RMS above this -> not the board
    min_fold_depth_m: float = 0.04         # G must be this far from the base line
    corner_trim_m: float = 0.02            # drop points this close (along the line) to F/G/H
    # depth
    depth_stride: int = 2
    depth_max_m: float = 6.0
    depth_sigma_k: float = 0.0031          # stereo depth sigma = k z^2 (1/m)
    depth_sigma_floor_m: float = 0.003
    depth_nsigma: float = 2.5              # inlier / assignment threshold in sigmas
    depth_ransac_iterations: int = 60  
    depth_ransac_points: int = 1000        # RANSAC hypotheses scored on this many points
    depth_max_planes: int = 14            # largest planar segments considered
    depth_normal_window: int = 5           # box window (decimated pixels) for normals
    depth_angle_tol_deg: float = 12.0      # sum of |angle - board model angle| over the 3 pairs
    depth_edge_deg: float = 15.0           # normal change that cuts segments (board folds: 38-67 deg)
    depth_min_plane_points: int = 60       # at the stride resolution
    depth_touch_m: float = 0.15            # planes "touch" when both have points this close to their line
    depth_refit_iterations: int = 3
    keep_points_per_plane: int = 3000      # stored per plane (subsampled) for the overlay/solver
    seed: int = 0


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


def _clusters(xy: np.ndarray, gap_m: float) -> list[np.ndarray]:
    if len(xy) == 0:
        return []
    jumps = np.nonzero(np.linalg.norm(np.diff(xy, axis=0), axis=1) > gap_m)[0]
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
    if cfg.scan_angle_window_deg is not None:
        ang = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
        m = (ang >= cfg.scan_angle_window_deg[0]) & (ang <= cfg.scan_angle_window_deg[1])
        xy, beam = xy[m], beam[m]
    # left-to-right as seen from the laser: decreasing angle
    xy = xy[::-1]
    board = cfg.board
    width = board.width_m
    k = cfg.min_points_per_segment
    best = None
    reasons = []
    for ci in _clusters(xy, cfg.cluster_gap_m):
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
        score = rms / cfg.laser_sigma_m - 0.001 * len(pts)
        if best is None or score < best[0]:
            best = (score, res, pts, rms)
    if best is None:
        why = "; ".join(sorted(set(reasons))[:3]) if reasons else "no cluster of board size"
        raise FeatureError(f"scan: board not found ({why})")
    _, (corners, cov, faces, lines, ends), pts, rms = best
    return ScanFeatures(corners, cov, faces, lines, all_xy, pts, float(rms), ends)


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
    sig = cfg.laser_sigma_m
    lines = []
    for s in segs:
        lines.append(fit_line_2d_lsq(s))
    corners = _fold_corners(lines)
    if corners is None:
        return "segments nearly parallel: no fold"
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
    return corners, cov, tuple(faces), tuple(lines), ends


# ----------------------------------------------------------------------------
# Depth
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class DepthFeatures:
    """Camera features in the camera optical frame (metres).

    ``planes`` (3,4) rows [n, d] of base, ABC, ACD (normals towards the
    camera); ``stats`` PlaneStats per plane; ``lines`` AB, AC, AD as (point,
    unit_dir); ``A`` the common point of the three planes; ``points`` per
    plane (subsampled inliers); ``pixel_index`` per plane (v * width + u)."""
    planes: np.ndarray
    stats: tuple
    lines: tuple
    A: np.ndarray
    points: tuple
    pixel_index: tuple


def _sigma_depth(pts: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    return np.maximum(cfg.depth_sigma_k * pts[:, 2] ** 2, cfg.depth_sigma_floor_m)


def _largest_component(pix: np.ndarray, shape: tuple, stride: int) -> np.ndarray:
    """Mask (len(pix),) of the pixels in the largest 8-connected component,
    computed on the stride-decimated image grid."""
    import cv2
    H, W = shape
    h, w = (H + stride - 1) // stride, (W + stride - 1) // stride
    v, u = pix // W // stride, pix % W // stride
    img = np.zeros((h, w), np.uint8)
    img[v, u] = 1
    img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    n, lab = cv2.connectedComponents(img, connectivity=8)
    if n <= 2:
        return np.ones(len(pix), bool)
    l = lab[v, u]
    counts = np.bincount(l[l > 0], minlength=n)
    return l == int(np.argmax(counts))


def extract_depth_features(frame, cfg: FeatureConfig | None = None) -> DepthFeatures:
    """Find the three board planes in a depth image; see the module docstring."""
    cfg = cfg or FeatureConfig()
    cam = frame.camera
    depth = np.asarray(frame.depth_m, dtype=np.float32)
    pts, pix = cam.depth_to_points(depth, stride=cfg.depth_stride)
    keep = pts[:, 2] <= cfg.depth_max_m
    pts, pix = pts[keep], pix[keep]
    if len(pts) < 3 * cfg.depth_min_plane_points:
        raise FeatureError(f"depth: no valid depth pixels ({len(pts)} valid points within "
                           f"{cfg.depth_max_m:.1f} m)" if len(pts) == 0 else
                           f"depth: too few valid depth pixels ({len(pts)})")
    sig = _sigma_depth(pts, cfg)
    cands = _segment_planes(depth, cam, pts, pix, sig, cfg)
    if len(cands) < 3:
        raise FeatureError(f"depth: only {len(cands)} planes found (need the base and both triangles)")
    triple = _choose_board(cands, pts, sig, cfg)
    if triple is None:
        raise FeatureError(f"depth: board not found among {len(cands)} planes "
                           "(no three planes touching pairwise with the board's fold angles; board partly seen or too far?)")
    return _refine_board(triple, cands, pts, pix, sig, cfg, cam)


def _segment_planes(depth: np.ndarray, cam, pts: np.ndarray, pix: np.ndarray, sig: np.ndarray,
                    cfg: FeatureConfig) -> list:
    """Planar segments of the depth image as plane candidates ``(n, d, idx)``.

    Sequential RANSAC on the whole cloud mixes the two triangles with the base
    near the folds (stereo noise is centimetres at 3 m while a fold only leaves
    the base plane slowly). Instead we smooth the back-projected points with a
    box window, take normals from central differences ``window`` pixels apart,
    and cut the image where normals on either side of a pixel differ by more
    than ``depth_edge_deg`` (folds, object borders) or depth jumps. The
    connected pieces that are left are the faces of the scene; each gets a
    RANSAC plane (per-point stereo thresholds) refitted by least squares.
    ``idx`` indexes ``pts`` (the stride-decimated valid points)."""
    import cv2

    s = cfg.depth_stride
    H, W = cam.height, cam.width
    h, w = (H + s - 1) // s, (W + s - 1) // s
    grid = np.full(h * w, -1, np.int64)
    v, u = pix // W // s, pix % W // s
    grid[v * w + u] = np.arange(len(pts))
    grid = grid.reshape(h, w)
    valid = grid >= 0
    P = np.zeros((h, w, 3), np.float32)
    P[valid] = pts[grid[valid]]
    k = max(3, int(cfg.depth_normal_window) | 1)
    wsum = cv2.boxFilter(valid.astype(np.float32), -1, (k, k), normalize=False,
                         borderType=cv2.BORDER_CONSTANT)
    M = cv2.boxFilter(P, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    M = M / np.maximum(wsum, 1.0)[..., None]
    good = valid & (wsum >= 0.6 * k * k)
    o = k // 2
    du = np.zeros_like(M)
    dv = np.zeros_like(M)
    du[:, o:w - o] = M[:, 2 * o:] - M[:, :w - 2 * o]
    dv[o:h - o, :] = M[2 * o:, :] - M[:h - 2 * o, :]
    N = np.cross(du, dv)
    nn = np.linalg.norm(N, axis=2)
    good &= nn > 1e-12
    N = N / np.maximum(nn, 1e-12)[..., None]
    flip = np.einsum("ijk,ijk->ij", N, M) > 0  # normals towards the camera
    N[flip] *= -1
    cos_thr = np.cos(np.radians(cfg.depth_edge_deg))
    edge = ~good
    # normals o pixels to either side disagree -> a fold or a border lies between
    cu = np.einsum("ijk,ijk->ij", N[:, 2 * o:], N[:, :w - 2 * o])
    cv_ = np.einsum("ijk,ijk->ij", N[2 * o:, :], N[:h - 2 * o, :])
    edge[:, o:w - o] |= cu < cos_thr
    edge[o:h - o, :] |= cv_ < cos_thr
    # depth jumps between neighbours (occlusion borders)
    z = np.where(valid, P[..., 2], np.nan)
    jump = 4.0 * np.maximum(cfg.depth_sigma_k * np.nan_to_num(z, nan=0.0) ** 2, cfg.depth_sigma_floor_m) + 0.03 * s
    with np.errstate(invalid="ignore"):
        edge[:, 1:] |= ~(np.abs(z[:, 1:] - z[:, :-1]) <= jump[:, 1:])
        edge[1:, :] |= ~(np.abs(z[1:, :] - z[:-1, :]) <= jump[1:, :])
    interior = (valid & ~edge).astype(np.uint8)
    n_lab, lab = cv2.connectedComponents(interior, connectivity=4)
    counts = np.bincount(lab.ravel(), minlength=n_lab)
    counts[0] = 0
    order = np.argsort(-counts)
    rng = np.random.default_rng(cfg.seed)
    cands = []
    for L in order[: cfg.depth_max_planes]:
        if counts[L] < cfg.depth_min_plane_points:
            break
        idx = grid[lab == L]
        sub = idx if len(idx) <= cfg.depth_ransac_points else \
            idx[rng.choice(len(idx), cfg.depth_ransac_points, replace=False)]
        try:
            n, d, _ = ransac_plane(pts[sub], cfg.depth_nsigma * sig[sub], cfg.depth_ransac_iterations, rng,
                                   min_inliers=max(10, len(sub) // 3), refit_iterations=1)
        except FitError:
            continue
        inl = idx[np.abs(pts[idx] @ n + d) < cfg.depth_nsigma * sig[idx]]
        if len(inl) < cfg.depth_min_plane_points:
            continue
        n, d = fit_plane_lsq(pts[inl])
        cands.append((n, d, inl))
    return _merge_coplanar(cands, pts, sig, cfg)


def _merge_coplanar(cands: list, pts: np.ndarray, sig: np.ndarray, cfg: FeatureConfig) -> list:
    """Merge segments of one plane cut apart by something in front of it (the
    base rectangle is split in two by the triangles): a pair merges when each
    one's points lie, on average, within ``depth_nsigma`` sigmas of the
    other's plane and the normals agree within 5 degrees."""
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
                    n, d = fit_plane_lsq(pts[idx])
                    cands[i] = (n, d, idx)
                    del cands[j]
                    merged = True
                    break
            if merged:
                break
    return cands


def _touch(ci, cj, pts, sig, cfg) -> tuple[bool, np.ndarray, np.ndarray]:
    try:
        p0, u = intersect_planes(ci[:2], cj[:2])
    except FitError:
        return False, None, None
    out = []
    for c in (ci, cj):
        idx = c[2] if len(c[2]) <= 2000 else c[2][:: len(c[2]) // 2000 + 1]  # enough to find 5 near points
        q = pts[idx] - p0
        dist = np.linalg.norm(q - np.outer(q @ u, u), axis=1)
        out.append(int((dist < cfg.depth_touch_m + 2 * sig[idx]).sum()))
    return min(out) >= 5, p0, u


def _choose_board(cands, pts, sig, cfg):
    """(base, tri_a, tri_b) candidate indices of the board, or None."""
    K = len(cands)
    ext = []
    for n, d, idx in cands:
        q = pts[idx] - pts[idx].mean(axis=0)
        ext.append(float(2.0 * np.sqrt(np.linalg.eigvalsh(q.T @ q / len(idx))[-1]) * 1.73))
    limit = 1.3 * cfg.board.max_extent_m()
    model_ang = cfg.board.normal_angles_deg()
    touch = {}
    for i in range(K):
        for j in range(i + 1, K):
            if min(ext[i], ext[j]) > limit or max(ext[i], ext[j]) > 2.0 * limit:
                touch[(i, j)] = touch[(j, i)] = False  # walls and floor: no board triple has two of them
                continue
            ang = np.degrees(np.arccos(np.clip(abs(cands[i][0] @ cands[j][0]), 0, 1)))
            touch[(i, j)] = touch[(j, i)] = (ang > 8.0) and _touch(cands[i], cands[j], pts, sig, cfg)[0]
    best = None
    for i in range(K):
        for j in range(K):
            for k in range(j + 1, K):
                if len({i, j, k}) < 3 or not (touch[(i, j)] and touch[(i, k)] and touch[(j, k)]):
                    continue
                if ext[j] > limit or ext[k] > limit or ext[i] > 2.0 * limit:
                    continue
                try:
                    A = intersect_three_planes([cands[i][:2], cands[j][:2], cands[k][:2]])
                except FitError:
                    continue
                near = [float(np.min(np.linalg.norm(pts[cands[m][2]] - A, axis=1))) for m in (i, j, k)]
                if max(near) > 0.15 + cfg.depth_touch_m:
                    continue
                # The board's shape fixes the angles between its normals: a
                # triple of scene planes (walls, floor, a table) rarely fits them.
                ang = lambda a, b: float(np.degrees(np.arccos(np.clip(abs(cands[a][0] @ cands[b][0]), 0, 1))))  # noqa: E731,E501
                err = (abs(ang(i, j) - model_ang[0]) + abs(ang(i, k) - model_ang[1])
                       + abs(ang(j, k) - model_ang[2]))
                if err > cfg.depth_angle_tol_deg:
                    continue
                score = -err + 1e-6 * sum(len(cands[m][2]) for m in (i, j, k))
                if best is None or score > best[0]:
                    best = (score, (i, j, k))
    return None if best is None else best[1]


def _plane_sigmas(P: np.ndarray, planes, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """(distance in sigmas (N,3), sigma (N,3)) of every point to each plane.

    The stereo sigma k z^2 is taken at the depth the *plane* predicts along the
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
        S[:, f] = np.maximum(cfg.depth_sigma_k * z * z, cfg.depth_sigma_floor_m)
        D[:, f] = np.abs(P @ n + d) / S[:, f]
    return D, S


def _face_inliers(P: np.ndarray, D: np.ndarray, Sp: np.ndarray, labels: np.ndarray, planes,
                  nsigma: float) -> np.ndarray:
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
            band = nsigma * Sp[m, g] / max(sin_t, 0.05)
            w = q - p0
            dist = np.linalg.norm(w - np.outer(w @ u, u), axis=1)
            ok[m[dist < band]] = False
    return ok


def _refine_board(triple, cands, pts, pix, sig, cfg, cam) -> DepthFeatures:
    i, j, k = triple
    planes = [cands[m][:2] for m in (i, j, k)]
    region = np.concatenate([cands[m][2] for m in (i, j, k)])
    lo = pts[region].min(axis=0) - 0.05
    hi = pts[region].max(axis=0) + 0.05
    box = np.all((pts >= lo) & (pts <= hi), axis=1)
    bidx = np.nonzero(box)[0]
    P = pts[bidx]
    labels = None
    for _ in range(cfg.depth_refit_iterations):
        D, Sp = _plane_sigmas(P, planes, cfg)
        labels = np.argmin(D, axis=1)
        ok = _face_inliers(P, D, Sp, labels, planes, cfg.depth_nsigma)
        new = []
        for f in range(3):
            m = ok & (labels == f)
            if m.sum() < 10:
                raise FeatureError(f"depth: only {int(m.sum())} points left on the "
                                   f"{('base', 'first triangle', 'second triangle')[f]} after refit")
            new.append(fit_plane_lsq(P[m], weights=1.0 / Sp[m, f] ** 2))
        planes = new
    D, Sp = _plane_sigmas(P, planes, cfg)
    labels = np.argmin(D, axis=1)
    ok = _face_inliers(P, D, Sp, labels, planes, cfg.depth_nsigma)
    # left/right: ABC is the triangle further left in the image (smaller x/z)
    cen = [np.mean(P[ok & (labels == f)][:, 0] / P[ok & (labels == f)][:, 2]) for f in (1, 2)]
    order = [0, 1, 2] if cen[0] <= cen[1] else [0, 2, 1]
    planes = [planes[f] for f in order]
    stats, points, pixels = [], [], []
    rng = np.random.default_rng(cfg.seed + 1)
    for f in order:
        m = ok & (labels == f)
        Pm = P[m]
        n, d = planes[len(stats)]
        # per-point perpendicular sigma: along-ray sigma times |cos(incidence)|
        ray = Pm / np.linalg.norm(Pm, axis=1, keepdims=True)
        sp = np.maximum(Sp[m, f] * np.abs(ray @ n), 0.5 * cfg.depth_sigma_floor_m)
        stats.append(PlaneStats.from_points(Pm, n, d, weights=1.0 / sp ** 2))
        sel = np.arange(len(Pm))
        if len(sel) > cfg.keep_points_per_plane:
            sel = np.sort(rng.choice(len(sel), cfg.keep_points_per_plane, replace=False))
        points.append(Pm[sel])
        pixels.append(pix[bidx][m][sel])
    pl = np.array([[*n, d] for n, d in planes])
    try:
        lines = tuple(intersect_planes(planes[a], planes[b]) for a, b in ((0, 1), (1, 2), (2, 0)))
        A = intersect_three_planes(planes)
    except FitError as e:
        raise FeatureError(f"depth: board planes degenerate ({e})") from e
    return DepthFeatures(pl, tuple(stats), lines, A, tuple(points), tuple(pixels))


def make_observation(scan: ScanFeatures, depth: DepthFeatures, stamp_s: float = 0.0,
                     laser_sigma_m: float = 0.0125) -> LrfObservation:
    """Pair laser and camera features into one solver observation."""
    return LrfObservation(corners_laser_m=scan.corners_m, planes_cam=depth.planes,
                          face_points_laser_m=scan.face_points_m, plane_stats=depth.stats,
                          corner_cov_laser=scan.corner_cov, stamp_s=stamp_s, laser_sigma_m=laser_sigma_m)
