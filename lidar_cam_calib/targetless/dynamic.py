"""LiDAR ego-motion, metric scale for the SfM, and moving-object removal (ROS-free).

Mask R-CNN / PointPillars weights cannot be used here, so dynamic objects are
found by motion consistency instead:

* :func:`lidar_odometry`: scan-to-scan point-to-plane ICP between consecutive
  sweeps (voxel-subsampled; started from constant velocity, from rest and from
  the neighbouring links, the best-fitting kept), giving the LiDAR pose of
  every sweep in the first sweep's frame. Metric, so it also fixes the SfM
  scale (:func:`metric_scale`).
* :func:`dynamic_points`: after ego-motion compensation, a point of the
  reference sweep whose nearest neighbour in the neighbouring sweep(s) is far
  away (``> dynamic_dist_m``) moved; an object is dynamic when the median of
  its points moved (objects, not single points, so occlusion edges do not
  remove static things).
* The SfM side: tracks that violate the static-scene geometry are dropped by
  the bundle adjustment (:mod:`.sfm`), dense flow tracks that violate it by the
  multi-view re-projection test, and an optional per-image mask (from any
  upstream segmentation node) removes features and dense pixels.

Scale: monocular SfM has none. The LiDAR odometry gives the metric distance
travelled between the stamps of the kept images (interpolated between
sweeps); the SfM camera centres give the same distances in SfM units; the
scale is their least-squares ratio ``sum |dp| |dc| / sum |dc|^2``. The lever
arm between LiDAR and camera changes these distances only by
``|lever| * yaw change`` (millimetres over 8 frames of normal driving).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import CalibError
from ..core.geometry import inv_T, make_T, so3_exp, so3_log
from .align import AlignConfig, estimate_normals, icp_point_to_plane, layered_bev_translation
from .objects import ObjectConfig, facade_mask, voxel_index


def voxel_down(p: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point (the mean) per occupied voxel, the voxels in lexicographic order of their indices."""
    p = np.asarray(p)
    inv, cnt = voxel_index(p, voxel_m)
    if cnt.size == 0:
        return np.zeros((0, 3))
    # per-voxel sums in point order, as np.add.at adds them (the same sums, bit for bit)
    out = np.stack([np.bincount(inv, weights=p[:, k], minlength=cnt.size) for k in range(3)], axis=1)
    return out / cnt[:, None]


def _crop(p: np.ndarray, max_range_m: float, min_range_m: float = 1.5) -> np.ndarray:
    r = np.linalg.norm(p[:, :2], axis=1)
    return p[(r < max_range_m) & (r > min_range_m) & np.all(np.isfinite(p), axis=1)]


def _bev_start(src: np.ndarray, src_n: np.ndarray, tgt: np.ndarray, tgt_n: np.ndarray, radius_m: float = 4.0,
               cell_m: float = 0.2) -> np.ndarray:
    """A start for one link from nothing but the two sweeps: the horizontal shift that best overlays
    their upright surfaces (normals within 45 deg of horizontal: poles, trunks, cars, facades) seen from
    above (:func:`layered_bev_translation` with a single height layer), within ``radius_m`` (a car at
    140 km/h moves 3.9 m per 0.1 s sweep). The ground and its sensor-fixed rings are left out."""
    s, t = src[np.abs(src_n[:, 2]) < 0.7], tgt[np.abs(tgt_n[:, 2]) < 0.7]
    if s.shape[0] < 20 or t.shape[0] < 20:
        return np.eye(4)
    try:
        shift = layered_bev_translation(t, s, 0.0, cell_m=cell_m, radius_m=radius_m, z_range=(-1e3, 1e3),
                                        layer_m=2e3)[0]
    except CalibError:
        return np.eye(4)
    return make_T(np.eye(3), shift)


def _link_fit(src: np.ndarray, tgt: np.ndarray, tree: cKDTree, nrm: np.ndarray, T0: np.ndarray, cfg: AlignConfig,
              inlier_m: float):
    """ICP of one odometry link from ``T0``, continued from its own result (the correspondence radius
    reset) while it still moves by more than 5 cm: the radius shrinks every 5 iterations, so one run
    from a start 1-2 m off stops half way. Returns (IcpResult, score: source points within ``inlier_m``
    of the target's upright surfaces (normals within 45 deg of horizontal; nearest neighbour within 1 m)
    at the result), or (None, -1). The ground does not score: its rings move with the sensor, so at rest
    they meet their previous selves while at the true motion the far rings fall between the previous
    ones."""
    best, T = None, T0
    for _ in range(4):
        try:
            r = icp_point_to_plane(src, tgt, T, cfg, dst_tree=tree, dst_normals=nrm)
        except CalibError:
            break
        moved = float(np.linalg.norm(r.T[:3, 3] - T[:3, 3]))
        best, T = r, r.T
        if moved < 0.05:
            break
    if best is None:
        return None, -1
    q = src @ best.T[:3, :3].T + best.T[:3, 3]
    d, nn = tree.query(q, k=1, distance_upper_bound=1.0, workers=-1)
    ok = np.isfinite(d)
    ok[ok] = np.abs(nrm[nn[ok], 2]) < 0.7
    pl = np.abs(np.einsum("ij,ij->i", q[ok] - tgt[nn[ok]], nrm[nn[ok]]))
    return best, int((pl < inlier_m).sum())


def lidar_odometry(clouds: list, voxel_m: float = 0.4, max_range_m: float = 30.0, iterations: int = 20,
                   min_dist_m: float = 0.3, raw_points: int = 0, inlier_m: float = 0.1, steady_m: float = 0.1,
                   steady_score: float = 0.9, init_links: list | None = None,
                   warm_iterations: int = 20) -> tuple[np.ndarray, list]:
    """Poses (K,4,4) ``T_first_k`` of every sweep and the per-link ICP results.

    Each link is fitted from the constant-velocity start, from rest and from the horizontal shift that
    overlays the two sweeps' upright surfaces seen from above (:func:`_bev_start`), then (a backward and
    a forward pass) from both neighbouring links' results; the fit with the most source points within
    ``inlier_m`` of the target's upright surfaces is kept. At speed (1-2 m per sweep) the first link, which has no
    velocity to start from, otherwise stops in the street's along-track valley near rest and every later
    pose, the metric scale and the de-skew inherit it. A link whose constant-velocity fit stayed within
    ``steady_m`` of the previous link's motion and scores at least ``steady_score`` times its inliers is
    kept without the other starts (a car does not change its motion by 10 cm in one sweep; at slow speed
    the start from rest only found the same fit again, at twice the cost).

    ``raw_points > 0``: no voxel means (a fixed voxel grid in each sweep's own frame aliases the moving
    ring pattern and biases the travelled distance by up to ~1 %); the target is the raw sweep and the
    source a random subset of ``raw_points`` raw points.

    ``init_links`` (one 4x4 per link): each link is fitted from that start alone, without the other starts
    and the neighbours' passes (a refit on sweeps de-skewed with a first estimate's links, which moves
    each link by centimetres), with the correspondence radius at ``min_dist_m`` from the start and at most
    ``warm_iterations`` ICP iterations."""
    if len(clouds) < 2:
        raise CalibError(f"LiDAR odometry needs at least 2 sweeps, got {len(clouds)}")
    cfg = AlignConfig(icp_iterations=iterations, icp_max_dist_m=1.5, icp_min_dist_m=min_dist_m)
    if raw_points > 0:
        rng = np.random.default_rng(0)
        down = [_crop(np.asarray(c, float), max_range_m) for c in clouds]
        subs = [d[rng.choice(d.shape[0], min(raw_points, d.shape[0]), replace=False)] for d in down]
    else:
        down = [voxel_down(_crop(np.asarray(c, float), max_range_m), voxel_m) for c in clouds]
        subs = down
    trees, normals = [], []
    for k, d in enumerate(down):
        if d.shape[0] < 100 or subs[k].shape[0] < 100:
            raise CalibError(f"LiDAR odometry: sweep {k} has only {subs[k].shape[0]} usable points")
        tree = cKDTree(d)
        trees.append(tree)
        normals.append(estimate_normals(d, tree)[0])
    if init_links is not None:
        if len(init_links) != len(clouds) - 1:
            raise CalibError(f"LiDAR odometry: {len(init_links)} starts for {len(clouds) - 1} links")
        # started centimetres from the answer: the correspondence radius starts where the cold fit's ends
        cfg_w = AlignConfig(icp_iterations=warm_iterations, icp_max_dist_m=min_dist_m, icp_min_dist_m=min_dist_m)
        links = []
        for k in range(1, len(clouds)):
            r, _ = _link_fit(subs[k], down[k - 1], trees[k - 1], normals[k - 1], np.asarray(init_links[k - 1]),
                             cfg_w, inlier_m)
            if r is None:
                raise CalibError(f"LiDAR odometry failed between sweeps {k - 1} and {k}: the scans do not overlap")
            links.append(r)
        return _chain_poses(links), links
    links, scores = [], []
    vel = np.eye(4)
    for k in range(1, len(clouds)):
        tree, nrm = trees[k - 1], normals[k - 1]
        best, score = _link_fit(subs[k], down[k - 1], tree, nrm, vel, cfg, inlier_m)
        # a car's motion changes little in one sweep: a fit that stayed within steady_m of the previous
        # link's motion and meets the surfaces as well as it did needs no other start
        steady = (k >= 2 and best is not None and np.linalg.norm(best.T[:3, 3] - vel[:3, 3]) < steady_m
                  and score >= steady_score * scores[-1])
        if not steady:
            starts = [np.eye(4)] if k >= 2 else []  # (the first link's velocity start is rest)
            Tb = _bev_start(down[k], normals[k], down[k - 1], nrm)
            if min(np.linalg.norm(Tb[:3, 3] - T0[:3, 3]) for T0 in starts + [vel]) > 0.3:
                starts.append(Tb)
            for T0 in starts:
                r, sc = _link_fit(subs[k], down[k - 1], tree, nrm, T0, cfg, inlier_m)
                if sc > score:
                    best, score = r, sc
        if best is None:
            raise CalibError(f"LiDAR odometry failed between sweeps {k - 1} and {k}: the scans do not overlap")
        links.append(best)
        scores.append(score)
        vel = best.T
    # the neighbours' motion as a start (backward, then forward): a link stuck near rest between two that
    # moved is refitted from their motion
    n = len(links)
    for order, nb in ((range(n - 2, -1, -1), 1), (range(1, n), -1)):
        for k in order:
            T0 = links[k + nb].T
            if np.linalg.norm(T0[:3, 3] - links[k].T[:3, 3]) < 0.05:
                continue
            r, sc = _link_fit(subs[k + 1], down[k], trees[k], normals[k], T0, cfg, inlier_m)
            if r is not None and sc > scores[k]:
                links[k], scores[k] = r, sc
    return _chain_poses(links), links


def _chain_poses(links: list) -> np.ndarray:
    """(K,4,4) poses ``T_first_k`` chained from the links (``T_prev_cur`` each)."""
    poses = [np.eye(4)]
    for r in links:
        poses.append(poses[-1] @ r.T)
    return np.array(poses)


def interpolate_pose(stamps: np.ndarray, poses: np.ndarray, t: float) -> np.ndarray:
    """Pose at time t (linear in translation, geodesic in rotation; clamped extrapolation by one link)."""
    stamps = np.asarray(stamps, float)
    if stamps.size == 1:
        return poses[0]
    i = int(np.clip(np.searchsorted(stamps, t) - 1, 0, stamps.size - 2))
    a = (t - stamps[i]) / max(stamps[i + 1] - stamps[i], 1e-9)
    a = float(np.clip(a, -1.0, 2.0))
    d = inv_T(poses[i]) @ poses[i + 1]
    w = so3_log(d[:3, :3])
    return poses[i] @ make_T(so3_exp(a * w), a * d[:3, 3])


def metric_scale(cam_centres: np.ndarray, lidar_positions: np.ndarray) -> tuple[float, float]:
    """Metres per SfM unit and its relative 1-sigma from the consecutive distances."""
    dc = np.linalg.norm(np.diff(cam_centres, axis=0), axis=1)
    dp = np.linalg.norm(np.diff(lidar_positions, axis=0), axis=1)
    if np.sum(dp) < 0.2:
        raise CalibError(f"the LiDAR moved only {np.sum(dp):.2f} m over the kept frames: no metric scale "
                         "(drive at least a few metres)")
    s = float(np.sum(dp * dc) / np.sum(dc * dc))
    r = dp - s * dc
    rel = float(np.sqrt(np.sum(r ** 2) / max(dc.size - 1, 1)) / np.sqrt(np.sum(dc * dc) * s * s) + 1e-4)
    return s, rel


def point_motion(ref_cloud: np.ndarray, other_clouds: list, T_ref_others: list) -> np.ndarray:
    """Per point of ``ref_cloud``: the smallest nearest-neighbour distance to the
    ego-motion-compensated neighbouring sweeps (m)."""
    d = np.full(ref_cloud.shape[0], np.inf)
    for c, T in zip(other_clouds, T_ref_others):
        q = np.asarray(c, float) @ T[:3, :3].T + T[:3, 3]
        dist, _ = cKDTree(q).query(ref_cloud, k=1, distance_upper_bound=5.0, workers=-1)
        d = np.minimum(d, np.where(np.isfinite(dist), dist, 5.0))
    return d


def _bev_shift(P: np.ndarray, Q: np.ndarray, cell_m: float, reach_m: float) -> tuple[np.ndarray, float, float]:
    """(horizontal shift that best lays the footprint of ``P`` on that of ``Q`` seen from above, the overlap
    there, the overlap at no shift): both rasterised at ``cell_m`` (each point's cell and its 8 neighbours,
    tolerant of ring sampling) and cross-correlated over shifts within ``reach_m``."""
    from scipy.signal import correlate
    lo = P[:, :2].min(axis=0) - reach_m - 2 * cell_m
    hi = P[:, :2].max(axis=0) + reach_m + 2 * cell_m
    shape = tuple(np.ceil((hi - lo) / cell_m).astype(int) + 1)

    def raster(X):
        g = np.zeros(shape, np.float32)
        ij = np.floor((X[:, :2] - lo) / cell_m).astype(int)
        ok = np.all((ij >= 1) & (ij < np.array(shape) - 1), axis=1)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                g[ij[ok, 0] + di, ij[ok, 1] + dj] = 1.0
        return g
    A, B = raster(P), raster(Q)
    z = correlate(B, A, mode="full", method="fft")   # z[k] = sum A(x) B(x + k - (shape - 1))
    c = np.array(shape) - 1
    k = int(np.ceil(reach_m / cell_m))
    win = z[c[0] - k:c[0] + k + 1, c[1] - k:c[1] + k + 1]
    a, b = np.unravel_index(int(np.argmax(win)), win.shape)
    return np.array([a - k, b - k], float) * cell_m, float(win[a, b]), float(z[c[0], c[1]])


def moving_clusters(ref: np.ndarray, ref_above: np.ndarray, others: list, others_above: list,
                    T_ref_others: list, dt_s: list, speed_mps: float = 0.5, cell_m: float = 0.2,
                    min_points: int = 8, max_extent_m: float = 8.0, max_range_m: float = 40.0,
                    reach_m: float = 1.5, min_gain: float = 1.2) -> np.ndarray:
    """(N,) bool: points of ``ref`` on an above-ground cluster that moved faster than ``speed_mps``.

    The point test (:func:`point_motion`) misses people walking: a body 0.4 m wide that walks 0.3 m
    between the compared sweeps still has a compensated neighbour within 0.3 m on its sides, which are
    where its silhouettes are. Here each cluster of above-ground points off the facades (connected
    ``cell_m`` pillars seen from above, at most ``max_extent_m`` across) has its footprint seen from
    above laid on the above-ground points of each neighbouring sweep (ego-motion compensated) at every
    shift within ``reach_m`` (:func:`_bev_shift`, 0.1 m cells). It moved when, for every neighbouring
    sweep, the best shift is farther than ``speed_mps`` times their time apart and overlaps ``min_gain``
    times more than no shift. ``dt_s``: each neighbouring sweep's time from the reference one (s)."""
    from scipy import ndimage
    out = np.zeros(ref.shape[0], bool)
    r = np.linalg.norm(ref[:, :2], axis=1)
    cand = ref_above & np.all(np.isfinite(ref), axis=1) & (r <= max_range_m)
    # facades first: a person walking along one would join its cluster, which is never tested
    cand = np.flatnonzero(cand & ~facade_mask(ref, cand, ObjectConfig()))
    if cand.size < min_points or not others:
        return out
    qs = []
    for c, a, T in zip(others, others_above, T_ref_others):
        q = np.asarray(c, float)[a] @ T[:3, :3].T + T[:3, 3]
        qs.append(q[np.all(np.isfinite(q), axis=1)])
    trees = [cKDTree(q[:, :2]) if q.shape[0] else None for q in qs]
    ij = np.floor(ref[cand, :2] / cell_m).astype(np.int64)
    ij -= ij.min(axis=0)
    occ = np.zeros(tuple(ij.max(axis=0) + 1), bool)
    occ[ij[:, 0], ij[:, 1]] = True
    lab, _ = ndimage.label(occ, structure=np.ones((3, 3), bool))
    pl = lab[ij[:, 0], ij[:, 1]]
    order = np.argsort(pl, kind="stable")
    for grp in np.split(order, np.flatnonzero(np.diff(pl[order])) + 1):
        if grp.size < min_points:
            continue
        P = ref[cand[grp]]
        centre = 0.5 * (P[:, :2].max(axis=0) + P[:, :2].min(axis=0))
        half = 0.5 * np.max(P[:, :2].max(axis=0) - P[:, :2].min(axis=0))
        if 2 * half > max_extent_m:
            continue
        n_moved = 0
        for q, tree, dt in zip(qs, trees, dt_s):
            if tree is None:
                break
            near = q[tree.query_ball_point(centre, half * np.sqrt(2) + reach_m + cell_m)]
            if near.shape[0] < 3:
                break   # gone from view or occluded: cannot tell
            shift, best, zero = _bev_shift(P, near, 0.1, reach_m)
            if not (np.linalg.norm(shift) > speed_mps * abs(dt) and best > min_gain * zero):
                break
            n_moved += 1
        # every neighbouring sweep says it moved (not asked: the same velocity before and after, which
        # lost a fifth to a half of the people walking, whose neighbours' footprints match elsewhere)
        if n_moved == len(dt_s):
            out[cand[grp]] = True
    return out


def dynamic_objects(labels: np.ndarray, motion_m: np.ndarray, n_objects: int, dist_m: float) -> np.ndarray:
    """(K,) bool: objects whose median point motion exceeds ``dist_m``."""
    out = np.zeros(n_objects, bool)
    for k in range(n_objects):
        m = motion_m[labels == k]
        if m.size:
            out[k] = float(np.median(m)) > dist_m
    return out


__all__ = ["dynamic_objects", "interpolate_pose", "lidar_odometry", "metric_scale", "moving_clusters",
           "point_motion", "voxel_down"]
