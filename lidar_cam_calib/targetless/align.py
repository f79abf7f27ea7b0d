"""Object-level 4D Hough alignment and ICP (paper 001, Section 3.2.2; ROS-free).

Both clouds are levelled first (z up, ground at z = 0), so the unknown between
them is a yaw about z and a 3D translation: ``a = Rz(yaw) @ b + t`` maps the
source objects ``b`` (LiDAR) onto the target objects ``a`` (SfM). Every
compatible pair (same shape class, bounding box side ratios within
``[ratio_lo, ratio_hi]``) votes, for each yaw bin, for the translation bin
``a - Rz(yaw) b``; the accumulator is sparse (unique keys), yaw over the full
circle, so no initial guess is used.

``hough_align(..., verify=True)`` (ours) re-scores the ``verify_top`` best
bins by one-to-one centroid matches within ``match_radius_m`` and refines the
winner by least squares over its matches; ``verify=False`` is the paper's
arg-max. ICP is point-to-plane on a cKDTree of the target with trimmed
correspondences; ``with_scale=True`` also estimates a scale (SfM scale error).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..core.calibrator import cfg_field
from ..core.errors import CalibError
from ..core.geometry import make_T, so3_exp
from .objects import ObjectSet


@dataclasses.dataclass
class AlignConfig:
    yaw_step_deg: float = cfg_field(0.25, "Hough yaw bin (paper: 0.25 deg)", range=(0.05, 10.0))
    trans_step_m: float = cfg_field(0.2, "Hough translation bin (paper: 0.2 m)", range=(0.02, 2.0))
    search_radius_m: float = cfg_field(15.0, "Hough translation search radius (paper: 15 m)", range=(0.5, 100.0))
    ratio_lo: float = cfg_field(0.7, "compatible objects: smallest bounding box side ratio", range=(0.0, 1.0))
    ratio_hi: float = cfg_field(1.4, "compatible objects: largest bounding box side ratio", range=(1.0, 100.0))
    use_z_ratio: bool = cfg_field(True, "compare the vertical extent too (the paper does; an SfM cloud cut "
                                        "by the image top makes poles shorter)")
    yaw_window_deg: float = cfg_field(180.0, "Hough yaws within this of yaw_center (180: the whole circle, "
                                             "no guess)", range=(0.1, 180.0))
    verify: bool = cfg_field(True, "re-score the best Hough bins by one-to-one matches (ours)")
    verify_top: int = cfg_field(40, "how many Hough bins to re-score", range=(1, 10000))
    match_radius_m: float = cfg_field(0.6, "centroid match radius after alignment", range=(0.05, 5.0))
    min_matches: int = cfg_field(4, "fewest matched objects for an alignment", range=(3, 1000))
    icp_iterations: int = cfg_field(30, "ICP iterations", range=(1, 500))
    icp_max_dist_m: float = cfg_field(1.0, "ICP first correspondence distance (halves down to icp_min_dist_m)",
                                      range=(0.05, 10.0))
    icp_min_dist_m: float = cfg_field(0.25, "ICP final correspondence distance", range=(0.01, 5.0))


@dataclasses.dataclass
class HoughResult:
    yaw_rad: float
    t: np.ndarray
    votes: int
    matches: np.ndarray  # (K,2) index pairs (target, source)
    T: np.ndarray        # 4x4 source -> target

    @property
    def n_matches(self) -> int:
        return int(self.matches.shape[0])


def rz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def compatible_pairs(A: ObjectSet, B: ObjectSet, cfg: AlignConfig) -> np.ndarray:
    """(M,2) index pairs (i in A, j in B) that may be the same object."""
    if len(A) == 0 or len(B) == 0:
        return np.zeros((0, 2), np.int64)
    ea = np.maximum(A.sides if A.sides is not None else A.extents, cfg.trans_step_m)
    eb = np.maximum(B.sides if B.sides is not None else B.extents, cfg.trans_step_m)
    # horizontal sides: the yaw is unknown, so compare yaw-invariant (long, short) sides
    r = ea[:, None, :2] / eb[None, :, :2]
    ok = np.all((r >= cfg.ratio_lo) & (r <= cfg.ratio_hi), axis=2)
    if cfg.use_z_ratio:
        rzr = ea[:, None, 2] / eb[None, :, 2]
        ok &= (rzr >= cfg.ratio_lo) & (rzr <= cfg.ratio_hi)
    ok &= A.shape[:, None] == B.shape[None, :]
    return np.argwhere(ok)


def _match(a: np.ndarray, b_moved: np.ndarray, pairs_ok: np.ndarray | None, radius: float) -> np.ndarray:
    """Greedy one-to-one nearest matches within radius; (K,2) (i in a, j in b)."""
    if a.shape[0] == 0 or b_moved.shape[0] == 0:
        return np.zeros((0, 2), np.int64)
    d = np.linalg.norm(a[:, None, :] - b_moved[None, :, :], axis=2)
    if pairs_ok is not None:
        d = np.where(pairs_ok, d, np.inf)
    out = []
    cand = np.argwhere(d <= radius)
    if cand.size == 0:
        return np.zeros((0, 2), np.int64)
    cand = cand[np.argsort(d[cand[:, 0], cand[:, 1]])]
    used_a, used_b = set(), set()
    for i, j in cand:
        if i in used_a or j in used_b:
            continue
        used_a.add(int(i))
        used_b.add(int(j))
        out.append((int(i), int(j)))
    return np.array(out, np.int64).reshape(-1, 2)


def fit_yaw_translation(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Least-squares yaw and translation with a ~ Rz(yaw) b + t."""
    w = np.ones(a.shape[0]) if w is None else w
    ma = (w[:, None] * a).sum(0) / w.sum()
    mb = (w[:, None] * b).sum(0) / w.sum()
    da, db = a - ma, b - mb
    s = np.sum(w * (db[:, 0] * da[:, 1] - db[:, 1] * da[:, 0]))
    c = np.sum(w * (db[:, 0] * da[:, 0] + db[:, 1] * da[:, 1]))
    yaw = float(np.arctan2(s, c))
    return yaw, ma - rz(yaw) @ mb


def hough_align(A: ObjectSet, B: ObjectSet, cfg: AlignConfig | None = None, yaw_center_rad: float = 0.0
                ) -> HoughResult:
    """Yaw + translation taking source objects B onto target objects A, no initial guess
    (with ``cfg.yaw_window_deg < 180`` only yaws near ``yaw_center_rad`` are voted for)."""
    cfg = cfg or AlignConfig()
    pairs = compatible_pairs(A, B, cfg)
    if pairs.shape[0] < cfg.min_matches:
        raise CalibError(f"object alignment: only {pairs.shape[0]} compatible object pairs between the "
                         f"camera cloud ({len(A)} objects) and the LiDAR cloud ({len(B)} objects); need at "
                         f"least {cfg.min_matches}: drive where poles, trunks or signs are in view")
    nyaw = int(round(360.0 / cfg.yaw_step_deg))
    yaws = (np.arange(nyaw) + 0.5) * (2 * np.pi / nyaw)
    if cfg.yaw_window_deg < 180.0:
        near = np.abs(np.angle(np.exp(1j * (yaws - yaw_center_rad)))) <= np.radians(cfg.yaw_window_deg)
        yaws = yaws[near]
        nyaw = yaws.size
    c, s = np.cos(yaws), np.sin(yaws)
    a = A.centroids[pairs[:, 0]]
    b = B.centroids[pairs[:, 1]]
    step = cfg.trans_step_m
    nb = int(np.ceil(cfg.search_radius_m / step))
    span = 2 * nb + 1
    keys_all = []
    chunk = max(1, 4_000_000 // nyaw)
    for s0 in range(0, pairs.shape[0], chunk):
        aa, bb = a[s0:s0 + chunk], b[s0:s0 + chunk]
        tx = aa[:, None, 0] - (c[None] * bb[:, None, 0] - s[None] * bb[:, None, 1])
        ty = aa[:, None, 1] - (s[None] * bb[:, None, 0] + c[None] * bb[:, None, 1])
        tz = np.broadcast_to(aa[:, None, 2] - bb[:, None, 2], tx.shape)
        ix = np.floor(tx / step + 0.5).astype(np.int64)
        iy = np.floor(ty / step + 0.5).astype(np.int64)
        iz = np.floor(tz / step + 0.5).astype(np.int64)
        inside = (ix * ix + iy * iy <= nb * nb) & (np.abs(iz) <= nb)
        k = np.broadcast_to(np.arange(nyaw)[None], tx.shape)
        key = ((k * span + ix + nb) * span + iy + nb) * span + iz + nb
        keys_all.append(key[inside])
    keys = np.concatenate(keys_all)
    if keys.size == 0:
        raise CalibError("object alignment: no vote fell inside the translation search radius")
    uk, cnt = np.unique(keys, return_counts=True)
    order = np.argsort(-cnt, kind="stable")
    top = order[:cfg.verify_top if cfg.verify else 1]

    def decode(key):
        iz = key % span - nb
        r = key // span
        iy = r % span - nb
        r //= span
        ix = r % span - nb
        k = r // span
        return yaws[k], np.array([ix * step, iy * step, iz * step])

    pair_ok = np.zeros((len(A), len(B)), bool)
    pair_ok[pairs[:, 0], pairs[:, 1]] = True
    best = None
    for idx in top:
        yaw, t = decode(int(uk[idx]))
        for _ in range(3):  # match, refit, rematch
            moved = B.centroids @ rz(yaw).T + t
            m = _match(A.centroids, moved, pair_ok, cfg.match_radius_m)
            if m.shape[0] < 2 or not cfg.verify:
                break
            yaw, t = fit_yaw_translation(A.centroids[m[:, 0]], B.centroids[m[:, 1]])
        moved = B.centroids @ rz(yaw).T + t
        m = _match(A.centroids, moved, pair_ok, cfg.match_radius_m)
        res = float(np.mean(np.linalg.norm(A.centroids[m[:, 0]] - moved[m[:, 1]], axis=1))) if m.size else np.inf
        score = (m.shape[0], -res)
        if best is None or score > best[0]:
            best = (score, yaw, t, int(cnt[idx]), m)
    _, yaw, t, votes, m = best
    if m.shape[0] < cfg.min_matches:
        raise CalibError(f"object alignment: the best Hough cell matches only {m.shape[0]} objects "
                         f"(need {cfg.min_matches}); the scene has too few distinctive static objects")
    return HoughResult(float(yaw), np.asarray(t, float), votes, m, make_T(rz(yaw), t))


def estimate_normals(pts: np.ndarray, tree: cKDTree, k: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and planarity-based weights (N,) from k-neighbour PCA."""
    k = min(k, pts.shape[0])
    _, nn = tree.query(pts, k=k, workers=-1)
    nb = pts[nn]
    d = nb - nb.mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", d, d) / k
    w, v = np.linalg.eigh(C)
    n = v[:, :, 0]
    flat = 1.0 - w[:, 0] / np.maximum(w[:, 1], 1e-12)
    return n, np.clip(flat, 0.0, 1.0)


@dataclasses.dataclass
class IcpResult:
    T: np.ndarray          # 4x4 source -> target (rotation + translation)
    scale: float           # target ~ scale * (T source) if with_scale
    rms_m: float
    n_corr: int
    H: np.ndarray          # 6x6 (or 7x7) normal matrix of the last iteration
    residual_sigma_m: float


def icp_point_to_plane(src: np.ndarray, dst: np.ndarray, T0: np.ndarray, cfg: AlignConfig | None = None,
                       with_scale: bool = False, dst_tree: cKDTree | None = None,
                       dst_normals: np.ndarray | None = None, dst_weights: np.ndarray | None = None,
                       fix_rotation: bool = False) -> IcpResult:
    """Point-to-plane ICP of ``src`` onto ``dst`` from ``T0``; trimmed by distance.

    With ``with_scale`` the model is ``dst ~ (1 + s) (R src + t)`` about the
    target origin, the scale returned as ``scale`` (applied after T). ``dst_weights``: per target
    point weight (e.g. inverse triangulation variance) times the robust weight. ``fix_rotation``:
    only the translation is estimated (``H`` is then 3x3)."""
    cfg = cfg or AlignConfig()
    tree = dst_tree or cKDTree(dst)
    if dst_normals is None:
        dst_normals, _ = estimate_normals(dst, tree)
    R, t = T0[:3, :3].copy(), T0[:3, 3].copy()
    scale = 1.0
    nit = cfg.icp_iterations
    dmax = cfg.icp_max_dist_m
    H = np.eye(7 if with_scale else 6)
    rms, ncorr, sig = np.inf, 0, np.inf
    for it in range(nit):
        p = scale * (src @ R.T + t)
        dist, nn = tree.query(p, k=1, distance_upper_bound=dmax, workers=-1)
        ok = np.isfinite(dist)
        ncorr = int(ok.sum())
        if ncorr < 10:
            raise CalibError(f"ICP: only {ncorr} correspondences within {dmax:.2f} m; the clouds do not overlap "
                             "after object alignment")
        pp, qq, nn_ = p[ok], dst[nn[ok]], dst_normals[nn[ok]]
        r = np.einsum("ij,ij->i", qq - pp, nn_)
        mad = np.median(np.abs(r)) * 1.4826 + 1e-4
        w = 1.0 / np.maximum(1.0, np.abs(r) / (2.0 * mad))  # Huber-like
        if dst_weights is not None:
            w = w * dst_weights[nn[ok]]
        J = nn_ if fix_rotation else np.concatenate([np.cross(pp, nn_), nn_], axis=1)
        if with_scale and not fix_rotation:
            J = np.concatenate([J, np.einsum("ij,ij->i", pp, nn_)[:, None]], axis=1)
        Jw = J * w[:, None]
        H = Jw.T @ J
        g = Jw.T @ r
        try:
            x = np.linalg.solve(H + 1e-9 * np.eye(H.shape[0]), g)
        except np.linalg.LinAlgError as e:
            raise CalibError("ICP: degenerate geometry (the overlapping clouds constrain no pose)") from e
        if fix_rotation:
            x = np.concatenate([np.zeros(3), x])
        dR = so3_exp(x[:3])
        # p' = dR p + dt (in target space), with p = scale (R src + t)
        ds = 1.0 + (x[6] if with_scale and not fix_rotation else 0.0)
        R = dR @ R
        t = dR @ t + x[3:6] / (scale * ds)
        scale = scale * ds
        rms = float(np.sqrt(np.mean(r ** 2)))
        sig = float(mad)
        if np.linalg.norm(x[:6]) < 1e-6 and dmax <= cfg.icp_min_dist_m:
            break
        if it % 5 == 4:
            dmax = max(cfg.icp_min_dist_m, dmax * 0.5)
    return IcpResult(make_T(R, t), float(scale), rms, ncorr, H, sig)


__all__ = ["AlignConfig", "HoughResult", "IcpResult", "compatible_pairs", "estimate_normals",
           "fit_yaw_translation", "hough_align", "icp_point_to_plane", "icp_translation", "layered_bev_translation",
           "rz", "wahba"]


def layered_bev_translation(target: np.ndarray, source: np.ndarray, yaw: float, cell_m: float = 0.1,
                            radius_m: float = 6.0, z_range: tuple = (0.3, 5.0), layer_m: float = 0.3,
                            extent_m: float = 30.0, dilate: int = 1, n_peaks: int = 1,
                            centre: np.ndarray | None = None) -> tuple[np.ndarray, float, float, list]:
    """Horizontal translation of ``Rz(yaw) source`` onto ``target`` (levelled clouds, ground at z = 0)
    by FFT cross-correlation of bird's-eye occupancy grids per height layer, summed over the layers
    (a 3D correlation with no vertical shift: both clouds stand on the same ground). The target grid
    is dilated by ``dilate`` cells (its points are sparse rings), the source is binary occupancy. The
    search covers ``radius_m`` about ``centre`` (horizontal, default the origin).
    Returns (t (3,), the fraction of occupied source cells that hit, peak ratio: best score over the
    best score farther than 1 m from the peak, the list of up to ``n_peaks`` local peaks [(t (3,), score
    over the best score)], best first, each farther than 1 m from the others (for a caller that ranks
    them by other evidence; the first is ``t``))."""
    n = int(np.ceil(2 * extent_m / cell_m))
    nz = int(np.ceil((z_range[1] - z_range[0]) / layer_m))

    def grids(p, dil):
        m = (p[:, 2] > z_range[0]) & (p[:, 2] < z_range[1]) & (np.abs(p[:, 0]) < extent_m) & \
            (np.abs(p[:, 1]) < extent_m)
        ij = np.floor((p[m, :2] + extent_m) / cell_m).astype(int)
        kz = np.clip(((p[m, 2] - z_range[0]) / layer_m).astype(int), 0, nz - 1)
        g = np.zeros((nz, n, n), np.float32)
        g[kz, ij[:, 0], ij[:, 1]] = 1.0
        if dil:
            from scipy import ndimage
            g = ndimage.grey_dilation(g, size=(1, 2 * dil + 1, 2 * dil + 1))
        return g

    G_t = grids(target, dilate)
    G_s = grids(source @ rz(yaw).T, 0)
    tot = float(G_s.sum())
    if tot < 20:
        raise CalibError("translation search: fewer than 20 occupied cells above the ground in the camera cloud")
    # scipy's FFT on both cores (numpy's float32 rfft2 is ten times slower); the correlation of occupancy
    # grids counts cells, an integer: rounded, equal scores are equal and the first peak wins
    import scipy.fft
    F = scipy.fft.rfft2(G_t, s=(2 * n, 2 * n), workers=-1) * np.conj(scipy.fft.rfft2(G_s, s=(2 * n, 2 * n),
                                                                                      workers=-1))
    corr = np.rint(scipy.fft.irfft2(F.sum(axis=0), s=(2 * n, 2 * n), workers=-1))
    r = int(np.ceil(radius_m / cell_m))
    c0 = np.zeros(2) if centre is None else np.asarray(centre, float)[:2]
    ci, cj = (int(round(c0[0] / cell_m)), int(round(c0[1] / cell_m)))
    sh_i, sh_j = ci + np.arange(-r, r + 1), cj + np.arange(-r, r + 1)
    sub = corr[np.ix_(sh_i % (2 * n), sh_j % (2 * n))]
    i, j = np.unravel_index(int(np.argmax(sub)), sub.shape)
    best = float(sub[i, j])
    mask = np.ones_like(sub, bool)
    k = int(np.ceil(1.0 / cell_m))
    mask[max(0, i - k):i + k + 1, max(0, j - k):j + k + 1] = False
    second = float(sub[mask].max()) if np.any(mask) else 0.0
    t = np.array([sh_i[i] * cell_m, sh_j[j] * cell_m, 0.0])
    peaks = []
    rest = sub.copy()
    for _ in range(max(n_peaks, 1)):
        a, b = np.unravel_index(int(np.argmax(rest)), rest.shape)
        if not np.isfinite(rest[a, b]) or rest[a, b] <= 0:
            break
        peaks.append((np.array([sh_i[a] * cell_m, sh_j[b] * cell_m, 0.0]), float(rest[a, b]) / max(best, 1e-9)))
        rest[max(0, a - k):a + k + 1, max(0, b - k):b + k + 1] = -np.inf
    return t, best / tot, best / max(second, 1e-9), peaks


def wahba(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum w_i |a_i - R b_i|^2 over unit vectors (SVD)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    B = (w[:, None, None] * a[:, :, None] * b[:, None, :]).sum(0)
    U, _, Vt = np.linalg.svd(B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    return U @ D @ Vt


def icp_translation(cam: np.ndarray, cam_normals: np.ndarray, lidar_rot: np.ndarray, t0: np.ndarray,
                    cfg: AlignConfig | None = None, cam_weights: np.ndarray | None = None,
                    info_scale: float = 1.0) -> IcpResult:
    """Translation-only point-to-plane ICP with the camera cloud as the *source*: ``cam ~ lidar_rot + t``
    (``lidar_rot``: the LiDAR cloud already rotated into the camera's levelled frame). Each camera point
    is matched to its nearest LiDAR point and the residual is measured along the camera point's own
    normal. The camera cloud covers only part of each surface: with it as the target, LiDAR points past
    the edge of a camera patch pull towards the edge and bias the translation along the street by
    5-10 cm; with it as the source every residual has a real counterpart. ``H`` is 3x3, multiplied by
    ``info_scale`` (a caller that passes a subset: the information of the cloud it stands for)."""
    cfg = cfg or AlignConfig()
    tree = cKDTree(lidar_rot)
    t = np.asarray(t0, float).copy()
    dmax = cfg.icp_max_dist_m
    wext = np.ones(cam.shape[0]) if cam_weights is None else cam_weights
    H, rms, sig, ncorr = np.eye(3), np.inf, np.inf, 0
    for it in range(cfg.icp_iterations):
        dist, nn = tree.query(cam - t, k=1, distance_upper_bound=dmax, workers=-1)
        ok = np.isfinite(dist)
        ncorr = int(ok.sum())
        if ncorr < 10:
            raise CalibError(f"ICP: only {ncorr} correspondences within {dmax:.2f} m; the clouds do not overlap "
                             "after the coarse alignment")
        n = cam_normals[ok]
        r = np.einsum("ij,ij->i", lidar_rot[nn[ok]] + t - cam[ok], n)
        mad = np.median(np.abs(r)) * 1.4826 + 1e-4
        w = wext[ok] / np.maximum(1.0, np.abs(r) / (2.0 * mad))
        H = (n * w[:, None]).T @ n
        g = (n * w[:, None]).T @ r
        dt = -np.linalg.solve(H + 1e-9 * np.eye(3), g)
        t = t + dt
        rms = float(np.sqrt(np.mean(r ** 2)))
        sig = float(mad)
        if np.linalg.norm(dt) < 1e-5 and dmax <= cfg.icp_min_dist_m:
            break
        if it % 5 == 4:
            dmax = max(cfg.icp_min_dist_m, dmax * 0.5)
    return IcpResult(make_T(np.eye(3), t), 1.0, rms, ncorr, H * info_scale, sig)
