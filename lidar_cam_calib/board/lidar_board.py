"""The board in one LiDAR sweep (ROS-free): paper 000, section 2.1.2 (1).

Pipeline for one sweep:

1. Candidate points: those above the intensity threshold (the reflective
   border). The threshold is the paper's fixed value when
   ``intensity_threshold`` is set, otherwise automatic: several thresholds
   from the intensity histogram are tried and the one whose bright points
   form the best board-shaped planar cluster wins (intensity scales differ
   between LiDARs). Without an intensity field, or when it is saturated, the
   board is found by geometry: a planar cluster of the known size and shape.
2. RANSAC plane; every point of the sweep on that plane and inside the board
   is a board point (the checker area too, it is on the same plane).
3. Rings: the ``ring`` field, or recovered from the elevation angle.
4. Per ring the start and end points, projected to the plane. A spinning
   LiDAR samples the edge at one azimuth step: the true edge lies between the
   last point on the board and the next beam that missed it, so each end is
   moved to the midpoint of the two (the missed beam is cast on the fitted
   plane). What is left is the beam divergence: with an intensity threshold the
   board shrinks (about 5 mm per edge in the paper), by geometry a bright board
   outshines the background and grows; either way along the scan direction, so
   the known board size is fitted with one growth along the scan per sweep
   (the joint solver adds an asymmetry between ring starts and ends).
5. A rectangle of the known size fitted to the ends (four edges, corners,
   centre and axes), giving the board pose ``T_lidar_board`` and the 54
   virtual corners of eq. 1.

Without ring ends (``use_edges`` False: a dense scanner without rings) only the board's plane
is used: the sweep's planes are taken one after the other, each split into connected parts, and
the board is the part a rectangle of the known size holds (what touches it, a stand's arms, is
left outside); its points well inside that rectangle give the plane (:func:`_plane_only_search`).

The board pose has a two-fold ambiguity left (rotation by 180 deg about the
board normal); :mod:`lidar_cam_calib.board.solvers` resolves it against the
image. The z axis always points towards the LiDAR.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.errors import CalibError
from ..core.fitting import FitError, fit_plane_lsq, ransac_plane
from .frame import BoardGeometry


class BoardNotFound(CalibError):
    """No board in this sweep; the message says what was seen."""


@dataclasses.dataclass
class LidarDetectConfig:
    """Parameters of the LiDAR board finder (see the calibrator's config for help texts)."""
    intensity_threshold: float | None = None
    min_rings: int = 4
    min_points: int = 30
    range_min_m: float = 0.5
    range_max_m: float = 15.0
    plane_threshold_m: float = 0.05
    cluster_angle_deg: float = 4.0
    cluster_range_ratio: float = 0.06
    size_tolerance: float = 0.15
    use_edges: bool = True  # False: a dense scanner without rings; the board's plane only
    plane_only_margin_m: float = 0.02  # use_edges False: board points at least this far inside the outline


@dataclasses.dataclass
class LidarBoard:
    """The board found in one sweep.

    ``T_lidar_board``: board pose (z towards the LiDAR); ``points``: board
    points (on the plane, inside the outline); ``edge_points``: one per ring
    end, corrected to the edge estimate, on the plane; ``edge_sigma_m``:
    their in-scan-direction quantisation half-step; ``edge_dir``: unit scan
    direction at each end (outwards, in the plane); ``edge_range_m``: range of
    each end; ``shrink_m``: fitted growth of the board along the scan
    direction at each end (beam divergence; positive: the board looks larger); ``size_fit_m``: board size
    from the four free edges (diagnostic, as the paper's Fig. 10)."""
    T_lidar_board: np.ndarray
    points: np.ndarray
    edge_points: np.ndarray
    edge_step_m: np.ndarray
    edge_dir: np.ndarray
    edge_range_m: np.ndarray
    rings_on_board: int
    plane_rms_m: float
    edge_rms_m: float
    shrink_m: float
    mode: str
    threshold: float | None = None
    size_fit_m: tuple = (math.nan, math.nan)
    alternatives: list = dataclasses.field(default_factory=list)  # [(T_lidar_board, growth_m)] fitting about as well
    point_ring: np.ndarray | None = None  # ring id of each board point (None: rings recovered, not ids)
    edge_side: np.ndarray | None = None  # per end: -1 where a ring enters the board (scan order), +1 where it leaves

    def with_pose(self, T: np.ndarray, growth_m: float) -> "LidarBoard":
        """The same measurement with another board pose (an alternative)."""
        return dataclasses.replace(self, T_lidar_board=np.asarray(T, float).copy(), shrink_m=float(growth_m),
                                   alternatives=[])

    @property
    def centre(self) -> np.ndarray:
        return self.T_lidar_board[:3, 3]

    @property
    def normal(self) -> np.ndarray:
        return self.T_lidar_board[:3, 2]

    def virtual_corners(self, board: BoardGeometry) -> np.ndarray:
        """(n, 3) virtual inner corners in the LiDAR frame (eq. 1)."""
        P = board.inner_corners_board()
        return P @ self.T_lidar_board[:3, :3].T + self.T_lidar_board[:3, 3]


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------
def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def recover_rings(points: np.ndarray, gap_deg: float = 0.12) -> np.ndarray:
    """Ring index per point from the elevation angle (no ring field): sorted
    elevations are split where consecutive ones differ by more than
    ``gap_deg``."""
    p = np.asarray(points, dtype=float)
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    order = np.argsort(el)
    gaps = np.diff(el[order]) > math.radians(gap_deg)
    lab_sorted = np.concatenate([[0], np.cumsum(gaps)])
    ring = np.empty(len(p), dtype=np.int64)
    ring[order] = lab_sorted
    return ring


def _connected_components(n: int, pairs: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    if len(pairs) == 0:
        return np.arange(n)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def cluster_points(points: np.ndarray, angle_deg: float, range_ratio: float) -> np.ndarray:
    """Label per point: connected within ``angle_deg`` of direction and
    ``range_ratio`` of relative range (a neighbourhood that grows with range,
    as a spinning LiDAR's sampling does)."""
    from scipy.spatial import cKDTree
    p = np.asarray(points, dtype=float)
    r = np.linalg.norm(p, axis=1)
    u = p / r[:, None]
    q = np.column_stack([u / math.radians(angle_deg), np.log(r) / range_ratio])
    pairs = cKDTree(q).query_pairs(1.0, output_type="ndarray")
    return _connected_components(len(p), pairs)


def _ring_ends(P: np.ndarray, ring: np.ndarray, n: np.ndarray, d: float):
    """Per ring on the board: start and end points, corrected half an azimuth
    step outwards. Returns (ends (E,3), step (E,), dir (E,3), range (E,), n_rings)."""
    ends, steps, dirs, rngs = [], [], [], []
    centre_az = math.atan2(P[:, 1].mean(), P[:, 0].mean())
    rings = 0
    for rid in np.unique(ring):
        m = ring == rid
        if m.sum() < 3:
            continue
        Q = P[m]
        az = np.arctan2(Q[:, 1], Q[:, 0]) - centre_az
        az = (az + np.pi) % (2 * np.pi) - np.pi
        o = np.argsort(az)
        Q, az = Q[o], az[o]
        daz = np.diff(az)
        daz = daz[daz > 1e-7]
        if len(daz) < 2:
            continue
        step = float(np.median(daz))
        el = float(np.median(np.arctan2(Q[:, 2], np.hypot(Q[:, 0], Q[:, 1]))))
        rings += 1
        for idx, sgn in ((0, -1.0), (-1, 1.0)):
            e = Q[idx]
            a = az[idx] + centre_az + sgn * step
            ray = np.array([math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)])
            den = float(n @ ray)
            if abs(den) < 1e-6:
                continue
            # the end's own ray cut with the plane: its direction is exact, its range is not
            ue = e / np.linalg.norm(e)
            de = float(n @ ue)
            e_on = ue * (-d / de) if abs(de) > 1e-6 else e - (n @ e + d) * n
            miss = ray * (-d / den)
            v = miss - e_on
            ln = float(np.linalg.norm(v))
            if not math.isfinite(ln) or ln < 1e-6 or ln > 0.5:
                continue
            ends.append(e_on + 0.5 * v)
            steps.append(ln)
            dirs.append(v / ln)
            rngs.append(float(np.linalg.norm(e)) * sgn)  # signed: - start of the ring, + end
    if not ends:
        return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0), rings
    return np.array(ends), np.array(steps), np.array(dirs), np.array(rngs), rings


def _rect_residuals(params, q, dq, a, b):
    """Signed distance of each end, moved inwards by the growth ``s`` along its
    scan direction ``dq``, to the nearest edge of the rectangle."""
    cx, cy, th, s = params
    c, sn = math.cos(th), math.sin(th)
    qx, qy = q[:, 0] - s * dq[:, 0] - cx, q[:, 1] - s * dq[:, 1] - cy
    x = qx * c + qy * sn
    y = -qx * sn + qy * c
    dx = np.abs(x) - a
    dy = np.abs(y) - b
    return np.where(np.abs(dx) < np.abs(dy), dx, dy)


def fit_rectangle(q: np.ndarray, dq: np.ndarray, size_m: tuple, init: tuple, prior_growth_sigma_m: float = 0.02):
    """Known-size rectangle fitted to 2D ring ends ``q`` (E,2) with outward
    scan directions ``dq`` (E,2): every end on its nearest edge once moved
    back by one growth ``s`` (beam divergence) along its scan direction.
    ``init``: (cx, cy, theta). Returns a list of (params (cx, cy, theta, s),
    residuals, cost), best first: both assignments of the long side are
    tried (when the rings cover only one corner of the board they can fit
    about equally well)."""
    from scipy.optimize import least_squares
    a, b = size_m[0] / 2, size_m[1] / 2

    def fun(p):
        return np.concatenate([_rect_residuals(p, q, dq, a, b), [p[3] / prior_growth_sigma_m * 0.003]])
    sols = []
    for dth in (0.0, math.pi / 2):
        x0 = np.array([init[0], init[1], init[2] + dth, 0.0])
        r = least_squares(fun, x0, loss="soft_l1", f_scale=0.01, method="trf", max_nfev=80,
                          bounds=([-np.inf, -np.inf, -np.inf, -0.06], [np.inf, np.inf, np.inf, 0.06]))
        p = r.x.copy()
        p[2] = (p[2] + math.pi / 2) % math.pi - math.pi / 2
        sols.append((p, _rect_residuals(p, q, dq, a, b), float(r.cost)))
    sols.sort(key=lambda z: z[2])
    return sols


def _free_size(q, p):
    """Board size from the four edges fitted independently (paper Fig. 10)."""
    cx, cy, th = p[0], p[1], p[2]
    c, sn = math.cos(th), math.sin(th)
    x = (q[:, 0] - cx) * c + (q[:, 1] - cy) * sn
    y = -(q[:, 0] - cx) * sn + (q[:, 1] - cy) * c
    out = []
    for coord in (x, y):
        hi, lo = coord[coord > 0], coord[coord < 0]
        out.append(float(np.median(hi) - np.median(lo)) if len(hi) and len(lo) else math.nan)
    return tuple(out)


# ----------------------------------------------------------------------------
# candidate evaluation
# ----------------------------------------------------------------------------
def _evaluate(cand: np.ndarray, allp: np.ndarray, ring_all: np.ndarray | None, board: BoardGeometry,
              cfg: LidarDetectConfig, rng: np.random.Generator, mode: str, thr) -> LidarBoard:
    """Try one candidate cluster as the board; raise BoardNotFound with the reason."""
    import cv2
    if len(cand) < cfg.min_points:
        raise BoardNotFound(f"{len(cand)} points < {cfg.min_points}")
    try:
        n, d, inl = ransac_plane(cand, cfg.plane_threshold_m, 200, rng, min_inliers=cfg.min_points)
    except FitError as e:
        raise BoardNotFound(f"no plane: {e}") from e
    u, v = _plane_basis(n)
    q0 = cand[inl]
    q2 = np.column_stack([q0 @ u, q0 @ v])
    (cx, cy), (w, h), ang = cv2.minAreaRect(q2.astype(np.float32))
    L, S = max(w, h), min(w, h)
    W, H = board.size_m
    tol = cfg.size_tolerance
    if not cfg.use_edges:
        # plane only: what touches the board (a stand's arms) may be in the cluster; the
        # known-size rectangle in _plane_only_board cuts it off, so the cluster is larger than
        # the board only when that rectangle holds little of it
        frac = _fit_box(q2, board.size_m)[3] / len(q2)
        if frac < 0.6:
            raise BoardNotFound(f"planar cluster is {L:.2f} x {S:.2f} m, larger than the {W} x {H} m board "
                                f"(it holds only {frac:.0%} of the plane's points)")
    elif L > W * (1 + tol) + 0.05 or S > H * (1 + tol) + 0.05:
        raise BoardNotFound(f"planar cluster is {L:.2f} x {S:.2f} m, larger than the {W} x {H} m board")
    if L < 0.5 * W or S < 0.25 * H:
        raise BoardNotFound(f"planar cluster is {L:.2f} x {S:.2f} m, much smaller than the {W} x {H} m board")
    th0 = math.radians(ang) if w >= h else math.radians(ang) + math.pi / 2
    centre = n * (-d) + cx * u + cy * v
    # every point of the sweep on the plane near the candidate
    dist = np.abs(allp @ n + d)
    radius = 0.5 * math.hypot(max(W, L), max(H, S)) + 0.1 if not cfg.use_edges else 0.5 * math.hypot(W, H) + 0.1
    near = (dist < cfg.plane_threshold_m) & (np.linalg.norm(allp - centre, axis=1) < radius)
    P = allp[near]
    ring = recover_rings(P) if ring_all is None else ring_all[near]
    # refine plane on those points (robust: 3 MAD)
    n, d = fit_plane_lsq(P)
    res = P @ n + d
    mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
    keep = np.abs(res) < max(3 * mad, 0.005)
    P, ring = P[keep], ring[keep]
    n, d = fit_plane_lsq(P)
    if d < 0:
        n, d = -n, -d
    u, v = _plane_basis(n)
    if not cfg.use_edges:
        return _plane_only_board(P, n, d, board, mode, thr, cfg, allp)
    ends, steps, dirs, srngs, nr = _ring_ends(P, ring, n, d)
    rngs, side = np.abs(srngs), np.sign(srngs)
    if nr < cfg.min_rings:
        raise BoardNotFound(f"only {nr} LiDAR rings on the board (need {cfg.min_rings}): bring it closer "
                            "or tilt it so more rings cross it")
    if len(ends) < 6:
        raise BoardNotFound(f"only {len(ends)} ring ends on the board edges")
    base = -d * n
    qe = np.column_stack([(ends - base) @ u, (ends - base) @ v])
    dq = np.column_stack([dirs @ u, dirs @ v])
    sols = fit_rectangle(qe, dq, board.size_m, (cx, cy, th0))
    p, r, cost0 = sols[0]
    edge_rms = float(np.sqrt(np.mean(r ** 2)))
    if edge_rms > 0.04:
        raise BoardNotFound(f"edges do not fit a {W} x {H} m rectangle (rms {edge_rms * 1000:.0f} mm)")

    def pose_of(p):
        c, s = math.cos(p[2]), math.sin(p[2])
        xa = c * u + s * v
        # canonical sign: x up if it is the more vertical axis, else to the left
        if abs(xa[2]) > 0.3:
            xa = xa if xa[2] >= 0 else -xa
        else:
            lateral = np.cross(np.array([0.0, 0.0, 1.0]), n)
            xa = xa if xa @ lateral >= 0 else -xa
        T = np.eye(4)
        T[:3, :3] = np.column_stack([xa, np.cross(n, xa), n])
        T[:3, 3] = base + p[0] * u + p[1] * v
        return T
    T = pose_of(p)
    alternatives = []
    for p2, _r2, cost2 in sols[1:]:
        T2 = pose_of(p2)
        if cost2 < 4.0 * max(cost0, 1e-12) + 1e-6 and np.linalg.norm(T2[:3, 3] - T[:3, 3]) > 0.02:
            alternatives.append((T2, float(p2[3])))
    # keep board points inside the outline (+2 cm)
    loc = (P - T[:3, 3]) @ T[:3, :3]
    inside = (np.abs(loc[:, 0]) < W / 2 + 0.02) & (np.abs(loc[:, 1]) < H / 2 + 0.02)
    if inside.sum() < 0.8 * len(P) and not alternatives:
        raise BoardNotFound(f"the fitted {W} x {H} m outline holds only {int(inside.sum())} of {len(P)} plane points")
    if inside.sum() >= 0.8 * len(P):
        P, ring = P[inside], ring[inside]
    prms = float(np.sqrt(np.mean((P @ n + d) ** 2)))
    return LidarBoard(T, P, ends, steps, dirs, rngs, nr, prms, edge_rms, float(p[3]), mode, thr,
                      _free_size(qe, p), alternatives,
                      None if ring_all is None else np.asarray(ring, dtype=np.int64), side)


def _evaluate_peeling(cand, allp, ring_all, board, cfg, rng, mode, thr) -> LidarBoard:
    """:func:`_evaluate` on the cluster; when it is larger than the board (the board touching a
    stand, a table, a person), peel off its dominant planes one by one and try the board-sized
    connected parts of each."""
    try:
        return _evaluate(cand, allp, ring_all, board, cfg, rng, mode, thr)
    except BoardNotFound as e:
        if "larger" not in str(e):
            raise
        first = e
    rest = cand
    for _ in range(4):
        if len(rest) < cfg.min_points:
            break
        try:
            n, d, inl = ransac_plane(rest, min(cfg.plane_threshold_m, 0.03), 200, rng, min_inliers=cfg.min_points)
        except FitError:
            break
        sub = rest[inl]
        lab = cluster_points(sub, cfg.cluster_angle_deg / 2, cfg.cluster_range_ratio / 2)
        ids, counts = np.unique(lab, return_counts=True)
        for k in np.argsort(-counts)[:3]:
            if counts[k] < cfg.min_points:
                break
            try:
                return _evaluate(sub[lab == ids[k]], allp, ring_all, board, cfg, rng, mode, thr)
            except BoardNotFound:
                continue
        rest = rest[~inl]
    raise first


def _box_count(q: np.ndarray, th: float, nw: int, nh: int, ne: int, bin_m: float) -> tuple:
    """Best place of an (nw x nh)-bin box with its long side at angle ``th`` over the points ``q``:
    most points inside and fewest in the ``ne``-bin band around it (score inside - 2 x band).
    Returns (cx, cy, score, points inside)."""
    c, s = math.cos(th), math.sin(th)
    x = q[:, 0] * c + q[:, 1] * s
    y = -q[:, 0] * s + q[:, 1] * c
    pad = ne + 1
    x0, y0 = x.min() - pad * bin_m, y.min() - pad * bin_m
    ix = ((x - x0) / bin_m).astype(np.int64)
    iy = ((y - y0) / bin_m).astype(np.int64)
    shape = (int(ix.max()) + nw + 2 * pad + 1, int(iy.max()) + nh + 2 * pad + 1)
    hist = np.bincount(ix * shape[1] + iy, minlength=shape[0] * shape[1]).reshape(shape).astype(float)
    ii = np.zeros((shape[0] + 1, shape[1] + 1))
    ii[1:, 1:] = hist.cumsum(0).cumsum(1)

    def boxes(w, h):  # sums of every w x h window, indexed by its lower corner
        return ii[w:, h:] - ii[:-w, h:] - ii[w:, :-h] + ii[:-w, :-h]
    inner = boxes(nw, nh)
    outer = boxes(nw + 2 * ne, nh + 2 * ne)
    # align: the inner window at (a, b) sits in the outer one at (a - ne, b - ne)
    inner_c = inner[ne:ne + outer.shape[0], ne:ne + outer.shape[1]]
    score = inner_c - 2.0 * (outer - inner_c)
    a, b = np.unravel_index(int(np.argmax(score)), score.shape)
    bx, by = x0 + (a + ne + nw / 2) * bin_m, y0 + (b + ne + nh / 2) * bin_m
    return bx * c - by * s, bx * s + by * c, float(score[a, b]), int(inner_c[a, b])


def _best_box(q: np.ndarray, size_m: tuple, th0: float, bin_m: float) -> tuple:
    """The known-size rectangle (long side ``size_m[0]``) that holds the most 2D points ``q``
    with the fewest just around it (what touches the board, a stand's arms, crosses that band
    only where it touches): every turn (3 deg steps from ``th0``, then 0.5 deg steps about the
    best), every position on a ``bin_m`` grid (box sums of a 2D histogram). Returns
    (cx, cy, theta, points inside)."""
    W, H = size_m
    nw, nh = max(1, int(round(W / bin_m))), max(1, int(round(H / bin_m)))
    ne = max(1, int(round(0.1 * H / bin_m)))
    best = (0.0, 0.0, th0, -math.inf, 0)
    for th in th0 + np.radians(np.arange(0.0, 180.0, 3.0)):
        cx, cy, sc, cnt = _box_count(q, th, nw, nh, ne, bin_m)
        if sc > best[3]:
            best = (cx, cy, th, sc, cnt)
    th1 = best[2]
    for th in th1 + np.radians(np.arange(-2.5, 2.51, 0.5)):
        cx, cy, sc, cnt = _box_count(q, th, nw, nh, ne, bin_m)
        if sc > best[3]:
            best = (cx, cy, th, sc, cnt)
    return best[0], best[1], best[2], best[4]


def _fit_box(q: np.ndarray, size_m: tuple) -> tuple:
    """:func:`_best_box` started from the minimum-area rectangle, binned by the point spacing."""
    import cv2
    (_cx, _cy), (w, h), ang = cv2.minAreaRect(q.astype(np.float32))
    th0 = math.radians(ang) if w >= h else math.radians(ang) + math.pi / 2
    # point spacing sets the histogram bin (a few points per bin on the board)
    spacing = math.sqrt(max(w * h, 1e-6) / max(len(q), 1))
    bin_m = float(np.clip(2.0 * spacing, 0.005, 0.05))
    return _best_box(q, size_m, th0, bin_m)


def _plane_only_search(p: np.ndarray, board: BoardGeometry, cfg: LidarDetectConfig, rng: np.random.Generator,
                       reasons: list, mode: str = "geometry", thr=None, max_planes: int = 10):
    """Board by geometry for a dense scanner without rings (``use_edges`` False): the sweep's
    planes one after the other (RANSAC, then removed), each split into its connected parts; a
    part is the board when a rectangle of the known size holds most of it (what is left
    outside: a stand's arms, a hand) and covers it (:func:`_plane_only_board`). The part with
    the most board points wins. Returns the LidarBoard or None (``reasons`` says why)."""
    from scipy.spatial import cKDTree
    W, H = board.size_m
    rest = np.arange(len(p))
    best = None
    thr_m = min(cfg.plane_threshold_m, 0.02)
    for _ in range(max_planes):
        if len(rest) < max(cfg.min_points, 0 if best is None else len(best.points)):
            break  # what is left cannot hold a larger board
        try:
            n, d, inl = ransac_plane(p[rest], thr_m, 300, rng, min_inliers=cfg.min_points)
        except FitError:
            break
        Q = p[rest[inl]]
        rest = rest[~inl]
        sample = Q[rng.choice(len(Q), min(len(Q), 2000), replace=False)]
        nn = cKDTree(Q).query(sample, k=2)[0][:, 1]
        u, v = _plane_basis(n)
        q2 = np.column_stack([Q @ u, Q @ v])
        # connected parts on the plane: gaps of a few point spacings first; where that finds no
        # board (a spinning LiDAR's rings cross the board far apart), gaps up to a third of
        # the board's short side
        for cell in (float(np.clip(2.0 * np.median(nn), 0.005, 0.05)), min(H / 6.0, 0.12)):
            lab = _raster_components(q2, cell)
            b = _best_part(Q, lab, board, cfg, reasons, mode, thr, p, cell)
            if b is not None:
                break
        if b is not None and (best is None or len(b.points) > len(best.points)):
            best = b
    return best


def _raster_components(q2: np.ndarray, cell: float) -> np.ndarray:
    """Label per 2D point: 8-connected occupied cells of a ``cell`` grid."""
    from scipy import ndimage
    ij = np.floor((q2 - q2.min(axis=0)) / cell).astype(np.int64)
    shape = tuple(int(v) + 1 for v in ij.max(axis=0))
    if shape[0] * shape[1] > 4e7:  # a plane kilometres wide at this cell: one part
        return np.zeros(len(q2), dtype=np.int64)
    occ = np.zeros(shape, dtype=bool)
    occ[ij[:, 0], ij[:, 1]] = True
    lab, _n = ndimage.label(occ, structure=np.ones((3, 3), dtype=int))
    return lab[ij[:, 0], ij[:, 1]]


def _best_part(Q, lab, board, cfg, reasons, mode, thr, allp=None, gap_m: float = 0.0):
    """The connected part of plane points ``Q`` (labels ``lab``) with most board points, or None."""
    W, H = board.size_m
    best = None
    ids, counts = np.unique(lab, return_counts=True)
    for k in np.argsort(-counts)[:5]:
        if counts[k] < cfg.min_points:
            break
        C = Q[lab == ids[k]]
        try:
            n_c, d_c = fit_plane_lsq(C)
            if d_c < 0:
                n_c, d_c = -n_c, -d_c
            u, v = _plane_basis(n_c)
            q2 = np.column_stack([C @ u, C @ v])
            L, S = _extent(q2)
            if L < 0.5 * W or S < 0.25 * H:
                raise BoardNotFound(f"planar part is {L:.2f} x {S:.2f} m, much smaller than the {W} x {H} m board")
            frac = _fit_box(q2, board.size_m)[3] / len(C)
            if frac < 0.5:
                raise BoardNotFound(f"planar part is {L:.2f} x {S:.2f} m, larger than the {W} x {H} m board "
                                    f"(a board-sized rectangle holds only {frac:.0%} of it)")
            b = _plane_only_board(C, n_c, d_c, board, mode, thr, cfg, allp, gap_m)
        except (BoardNotFound, FitError) as e:
            reasons.append(f"{mode}: planar part of {len(C)} points: {e}")
            continue
        if best is None or len(b.points) > len(best.points):
            best = b
    return best


def _extent(q2: np.ndarray) -> tuple:
    import cv2
    (_cx, _cy), (w, h), _ang = cv2.minAreaRect(q2.astype(np.float32))
    return max(w, h), min(w, h)


def _plane_only_board(P, n, d, board, mode, thr, cfg, allp: np.ndarray | None = None,
                      gap_m: float = 0.0) -> LidarBoard:
    """Board from its plane only (no ring ends), for a dense scanner without rings.

    The plane points near the candidate may hold what touches the board (a stand's arms, a
    hand) and mixed returns at its edges; both tilt a plane fitted to all of them. So the
    board is the rectangle of the known size that holds the most plane points, the board
    points are those inside it by ``cfg.plane_only_margin_m`` (away from the edges) and on the
    plane (3 robust sigmas), and the plane is refitted to them. A candidate whose plane goes
    on around the rectangle (a wall) is refused."""
    W, H = board.size_m
    Pall = P
    u, v = _plane_basis(n)
    base = -d * n
    q = np.column_stack([(P - base) @ u, (P - base) @ v])
    cx, cy, th, _cnt = _fit_box(q, (W, H))
    c, s = math.cos(th), math.sin(th)
    x = (q[:, 0] - cx) * c + (q[:, 1] - cy) * s
    y = -(q[:, 0] - cx) * s + (q[:, 1] - cy) * c
    m = min(float(cfg.plane_only_margin_m), 0.25 * H)
    inner = (np.abs(x) < W / 2 - m) & (np.abs(y) < H / 2 - m)
    # the plane around the rectangle, in every point of the sweep (a part cut out of a wall by
    # sparse sampling is still in a wall)
    if allp is None:
        xs, ys = x, y
    else:
        on = np.abs(allp @ n + d) < min(cfg.plane_threshold_m, 0.02)
        qa = np.column_stack([(allp[on] - base) @ u, (allp[on] - base) @ v])
        xs = (qa[:, 0] - cx) * c + (qa[:, 1] - cy) * s
        ys = -(qa[:, 0] - cx) * s + (qa[:, 1] - cy) * c
    box = (np.abs(xs) < W / 2) & (np.abs(ys) < H / 2)
    band = ~box & (np.abs(xs) < W / 2 + 0.1 * H) & (np.abs(ys) < H / 2 + 0.1 * H)
    band_area = (W + 0.2 * H) * (1.2 * H) - W * H
    dens_in = max(box.sum(), 1) / (W * H)
    dens_band = band.sum() / band_area
    if dens_band > 0.5 * dens_in:
        raise BoardNotFound(f"the plane goes on around the {W} x {H} m board ({dens_band / dens_in:.0%} of its "
                            "point density just outside it): a wall or a larger panel, not the board")
    if inner.sum() < cfg.min_points:
        raise BoardNotFound(f"only {int(inner.sum())} points inside the {W} x {H} m board")
    bin_m = max(0.01, 0.1 * H, 2.0 * gap_m)  # coverage in cells no finer than the gaps allowed
    occ = np.unique(np.column_stack([np.floor(x[inner] / bin_m), np.floor(y[inner] / bin_m)]), axis=0)
    n_bins = max(1, int(round((W - 2 * m) / bin_m)) * int(round((H - 2 * m) / bin_m)))
    if len(occ) < 0.6 * n_bins:
        raise BoardNotFound(f"the points cover only {min(1.0, len(occ) / n_bins):.0%} of the {W} x {H} m board")
    # the board points: every point of the sweep inside the rectangle by the margin and on the
    # plane; the plane refitted to them (3 robust sigmas) and the points taken again, until stable
    src = P if allp is None else allp
    xa = c * u + s * v
    ctr = base + cx * u + cy * v
    thr_z = float(cfg.plane_threshold_m)
    n0 = n.copy()
    Q = P[inner]
    for _ in range(6):
        xa = xa - (xa @ n) * n
        xa /= np.linalg.norm(xa)
        ya = np.cross(n, xa)
        ctr = ctr - (ctr @ n + d) * n
        rel = src - ctr
        sel = (np.abs(rel @ xa) < W / 2 - m) & (np.abs(rel @ ya) < H / 2 - m) & (np.abs(src @ n + d) < thr_z)
        if sel.sum() < cfg.min_points:
            break
        Q = src[sel]
        for _ in range(3):
            n2, d2 = fit_plane_lsq(Q)
            res = Q @ n2 + d2
            mad = float(np.median(np.abs(res - np.median(res)))) * 1.4826
            keep = np.abs(res) < max(3 * mad, 1e-4)
            if keep.all():
                break
            Q = Q[keep]
        n2, d2 = fit_plane_lsq(Q)
        if n2 @ n0 < 0:
            n2, d2 = -n2, -d2
        moved = math.degrees(math.acos(min(1.0, abs(float(n2 @ n))))) + 1000 * abs(d2 - d)
        n, d = n2, d2
        thr_z = max(4.0 * mad, 0.002)
        if moved < 1e-3:
            break
    P = Q
    if d < 0:
        n, d = -n, -d
    # the rectangle's axes and centre on the refitted plane
    xa = xa - (xa @ n) * n
    xa /= np.linalg.norm(xa)
    ctr = ctr - (ctr @ n + d) * n
    T = np.eye(4)
    T[:3, :3] = np.column_stack([xa, np.cross(n, xa), n])
    T[:3, 3] = ctr
    prms = float(np.sqrt(np.mean((P @ n + d) ** 2)))
    # diagnostic: the extent of the plane points in and just around the rectangle
    near = (np.abs(x) < W / 2 + 0.1 * H) & (np.abs(y) < H / 2 + 0.1 * H) & \
        (np.abs(Pall @ n + d) < max(3 * prms, 0.003))
    size_fit = (float(np.ptp(np.percentile(x[near], [0.5, 99.5]))), float(np.ptp(np.percentile(y[near], [0.5, 99.5]))))\
        if near.sum() > 10 else (math.nan, math.nan)
    z3, z1 = np.zeros((0, 3)), np.zeros(0)
    return LidarBoard(T, P, z3, z1, z3, z1, 0, prms, 0.0, 0.0, mode, thr, size_fit, [], None, z1)


def _auto_thresholds(intensity: np.ndarray) -> list:
    """Candidate thresholds, best guess first: fractions of the level of the
    brightest returns (the retro-reflective border), then Otsu on log intensity."""
    v = intensity[np.isfinite(intensity)]
    if v.size == 0:
        return []
    top = float(np.percentile(v, 99.9))
    out = [f * top for f in (0.5, 0.7, 0.35, 0.85)]
    lv = np.log1p(np.clip(v, 0, None))
    hist, edges = np.histogram(lv, bins=128)
    w = hist.astype(float) / max(hist.sum(), 1)
    mids = 0.5 * (edges[1:] + edges[:-1])
    cw, cm = np.cumsum(w), np.cumsum(w * mids)
    between = (cm[-1] * cw - cm) ** 2 / np.maximum(cw * (1 - cw), 1e-12)
    out.append(float(np.expm1(mids[int(np.argmax(between[:-1]))])))
    return [t for t in out if t > 0]


def intensity_usable(intensity: np.ndarray | None) -> tuple[bool, str]:
    """(usable, why not)."""
    if intensity is None:
        return False, "the cloud has no intensity field"
    v = np.asarray(intensity, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0 or np.ptp(v) == 0:
        return False, "intensity is constant"
    top = float(v.max())
    if np.mean(v >= top) > 0.3:
        return False, f"intensity is saturated ({100 * np.mean(v >= top):.0f} % of points at {top:g})"
    return True, ""


def detect_board(points: np.ndarray, intensity: np.ndarray | None, ring: np.ndarray | None,
                 board: BoardGeometry, cfg: LidarDetectConfig | None = None, seed: int = 0) -> LidarBoard:
    """Find the board in one sweep. Raises :class:`BoardNotFound` with what was seen."""
    cfg = cfg or LidarDetectConfig()
    rng = np.random.default_rng(seed)
    p = np.asarray(points, dtype=float)
    r = np.linalg.norm(p, axis=1)
    ok = np.all(np.isfinite(p), axis=1) & (r >= cfg.range_min_m) & (r <= cfg.range_max_m)
    if ok.sum() < cfg.min_points:
        raise BoardNotFound(f"the sweep has {int(ok.sum())} valid points between {cfg.range_min_m} and "
                            f"{cfg.range_max_m} m")
    p = p[ok]
    ring_v = None if ring is None else np.asarray(ring)[ok]
    inten = None if intensity is None else np.asarray(intensity, dtype=float)[ok]
    usable, why = intensity_usable(inten)
    reasons = []
    best = None

    def consider(mask, mode, thr):
        nonlocal best
        cand_all = p[mask]
        if len(cand_all) < cfg.min_points:
            reasons.append(f"{mode}{'' if thr is None else f' >= {thr:g}'}: {len(cand_all)} points")
            return
        lab = cluster_points(cand_all, cfg.cluster_angle_deg, cfg.cluster_range_ratio)
        ids, counts = np.unique(lab, return_counts=True)
        order = np.argsort(-counts)
        diag = math.hypot(*board.size_m)
        tried = 0
        for k in order:
            if counts[k] < cfg.min_points or tried >= 12:
                break
            cand = cand_all[lab == ids[k]]
            ext = float(np.linalg.norm(cand.max(axis=0) - cand.min(axis=0)))
            if ext > 1.6 * diag + 0.2 and (mode != "geometry" or len(cand) > 60000):
                reasons.append(f"{mode}: cluster of {counts[k]} points spans {ext:.1f} m, larger than the board")
                continue
            tried += 1
            try:
                b = _evaluate_peeling(cand, p, ring_v, board, cfg, rng, mode, thr)
            except BoardNotFound as e:
                msg = f"{mode}: board-sized cluster of {counts[k]} points: {e}"
                if "ring" in str(e) or "edges" in str(e):
                    reasons.insert(0, msg)  # board-sized: the reason that matters
                else:
                    reasons.append(f"{mode}: cluster of {counts[k]} points: {e}")
                continue
            score = len(b.points) / (1.0 + b.edge_rms_m / 0.01)
            if best is None or score > best[0]:
                best = (score, b)

    if usable:
        thrs = [cfg.intensity_threshold] if cfg.intensity_threshold is not None else _auto_thresholds(inten)
        for t in thrs:
            consider(inten >= t, "intensity", t)
            if best is not None and best[1].edge_rms_m < 0.008:
                break  # a clean board: the other thresholds cannot do much better
    if best is None:
        if not usable:
            reasons.append(f"{why}: searched by geometry")
        if cfg.use_edges:
            consider(np.ones(len(p), bool), "geometry", None)
        else:
            b = _plane_only_search(p, board, cfg, rng, reasons)
            if b is not None:
                best = (len(b.points), b)
    if best is None:
        uniq = []
        for s in reasons:
            if s not in uniq:
                uniq.append(s)
        raise BoardNotFound("no board in the LiDAR sweep (" + "; ".join(uniq[:4]) +
                            (f"; {len(uniq) - 4} more" if len(uniq) > 4 else "") + ")")
    return best[1]


class StillBoardDetector:
    """Fires once per stop of the board: ``update(stamp_s, centre, normal)``
    returns True the first time the board has stayed within ``tol_m`` and
    ``tol_deg`` of where it was at the start of the still period for
    ``still_time_s``; re-arms when it moves. ``update(stamp, None, None)``
    (board not seen) re-arms too."""

    def __init__(self, still_time_s: float = 1.0, tol_m: float = 0.02, tol_deg: float = 1.5):
        self.still_time_s, self.tol_m, self.tol_deg = still_time_s, tol_m, tol_deg
        self.reset()

    def reset(self) -> None:
        self._ref = None
        self._since = None
        self._fired = False

    def update(self, stamp_s: float, centre, normal) -> bool:
        if centre is None:
            self.reset()
            return False
        c, n = np.asarray(centre, float), np.asarray(normal, float)
        if self._ref is not None:
            c0, n0 = self._ref
            ang = math.degrees(math.acos(min(1.0, abs(float(n @ n0)))))
            if np.linalg.norm(c - c0) <= self.tol_m and ang <= self.tol_deg:
                if not self._fired and stamp_s - self._since >= self.still_time_s:
                    self._fired = True
                    return True
                return False
        self._ref, self._since, self._fired = (c, n), stamp_s, False
        return self.still_time_s <= 0 and not self._fired and self._fire_now()

    def _fire_now(self) -> bool:
        self._fired = True
        return True


__all__ = ["BoardNotFound", "LidarBoard", "LidarDetectConfig", "StillBoardDetector", "cluster_points",
           "detect_board", "fit_rectangle", "intensity_usable", "recover_rings"]
