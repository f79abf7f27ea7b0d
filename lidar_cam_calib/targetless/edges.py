"""Extrinsic refinement from LiDAR edges against image edges (ROS-free).

A street is nearly degenerate along its axis for cloud-to-cloud registration,
and the SfM camera cloud carries a depth bias correlated through its poses.
The image itself does not: the silhouettes of poles, trunks and kerbs, and the
ends of painted dashes, sit at pixels that move when the camera moves along the
street. This module measures that directly:

* LiDAR edges, per scan line (rings found by clustering the elevation of the
  raw points, each ring ordered by azimuth): the near point of a depth jump
  (silhouette) and the midpoint of an intensity jump on a continuous surface
  (paint on asphalt);
* image edges: Canny on the blurred grey image, then its distance transform;
* the score of a translation offset ``delta`` (camera frame) is the robust
  (truncated) mean distance of the projected LiDAR edges to the nearest image
  edge, over several images of the window, each with its own LiDAR pose from
  the odometry; points hidden from the camera (a z-buffer of all static LiDAR
  points) or outside the image at ``delta = 0`` are left out for every
  ``delta`` so the score compares the same points;
* ``refine_translation`` (the older step): a 1-D coarse-to-fine search along
  one direction (the driving direction), then optionally a small 3-D
  refinement; the spread of the per-image optima gives the uncertainty;
* ``refine_pose`` (the default): all six degrees of freedom, each image with
  the sweep nearest its exposure, Levenberg-Marquardt on smoothed distance
  fields with Cauchy weights, priors on the tilt and height, a covariance
  scaled by the images' dispersion. The calibrator also runs it, yaw and
  translation only, from each coarse translation candidate to rank them.
  A view's LiDAR edges and distance map are computed once (``prepare_view``,
  with the first configuration it is given) and shared by those fits.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.calibrator import cfg_field
from ..core.camera import CameraModel
from ..core.geometry import inv_T, so3_exp, so3_log, transform_points


@dataclasses.dataclass
class EdgeConfig:
    depth_jump_m: float = cfg_field(0.3, "silhouette: the far neighbour on the scan line is at least this farther "
                                         "...", range=(0.05, 10.0))
    depth_jump_rel: float = cfg_field(0.08, "... and this fraction of the near range farther", range=(0.0, 1.0))
    smooth_rel: float = cfg_field(0.02, "a silhouette's near side must be continuous: its other neighbour "
                                        "within this fraction of the range (+5 cm)", range=(0.0, 1.0))
    clutter_window: int = cfg_field(4, "silhouette: depth jumps are counted over this many neighbouring pairs on "
                                       "each side along the scan line (0: no count)", range=(0, 50))
    clutter_max_jumps: int = cfg_field(2, "... and a silhouette with more jumps than this around it (its own "
                                          "included) is left out: foliage, where rays pass through gaps in the "
                                          "crown, jumps at every other point, and its jumps meet no edge in the "
                                          "image (a thin pole brings two)", range=(1, 100))
    intensity_jump: float = cfg_field(0.25, "paint edge: intensity step over the sweep's 95th percentile",
                                      range=(0.01, 10.0))
    paint_ground_m: float = cfg_field(0.2, "paint edges only on the road: both returns within this of the sweep's "
                                           "ground plane (0: anywhere). On KITTI the reflectance steps above the "
                                           "ground (cars, hedges, facades) meet the image's edges at chance, "
                                           "those on the road as often as the silhouettes do", range=(0.0, 10.0))
    intensity_window: int = cfg_field(5, "paint edge: the step is measured between the mean intensities of up "
                                         "to this many points on each side along the scan line (1: the two "
                                         "neighbours alone, which a textured surface trips at every other point)",
                                      range=(1, 20))
    intensity_z: float = cfg_field(3.0, "paint edge: the step relative to the local mean intensity must also be "
                                        "this many sigmas of the texture that the sweep's neighbouring returns "
                                        "show (estimated per sweep, median absolute relative difference)",
                                   range=(0.0, 100.0))
    max_range_m: float = cfg_field(20.0, "LiDAR edges farther than this are left out", range=(2.0, 200.0))
    min_range_m: float = cfg_field(1.5, "LiDAR edges nearer than this are left out", range=(0.0, 50.0))
    truncate_px: float = cfg_field(4.0, "robust score: distances to the image edges truncated here "
                                        "(occlusion, missing edges)", range=(0.5, 100.0))
    coarse_truncate_px: float = cfg_field(10.0, "the same for the coarse search", range=(0.5, 100.0))
    search_m: float = cfg_field(0.5, "1-D search half-width along the driving direction", range=(0.01, 5.0))
    coarse_step_m: float = cfg_field(0.02, "coarse 1-D search step", range=(0.001, 1.0))
    fine_step_m: float = cfg_field(0.004, "fine 1-D search step", range=(0.0005, 0.5))
    max_3d_m: float = cfg_field(0.1, "the 3-D refinement stays within this of the 1-D optimum", range=(0.0, 2.0))
    blur_sigma_px: float = cfg_field(1.0, "Gaussian blur before Canny", range=(0.0, 10.0))
    pose_coarse_blur_px: float = cfg_field(2.0, "6-DoF refinement: blur of the coarse distance field",
                                           range=(0.0, 20.0))
    pose_fine_blur_px: float = cfg_field(1.0, "6-DoF refinement: blur of the fine distance field", range=(0.0, 20.0))
    pose_cauchy_px: float = cfg_field(1.5, "6-DoF refinement: Cauchy scale of the fine stage", range=(0.1, 20.0))
    min_points: int = cfg_field(150, "fewest visible LiDAR edge points (all images)", range=(10, 100000))
    view_min_points: int = cfg_field(30, "an image enters the edge fit with at least this many visible LiDAR "
                                         "edge points (a sparse head's 30-60 per image count; the fit needs "
                                         "150 over all images)", range=(5, 100000))
    pose_max_points: int = cfg_field(2000, "6-DoF refinement: at most this many visible edge points per image, "
                                           "evenly spaced along the scan (a dense LiDAR's 6000 cost 3x the "
                                           "time; the covariance is scaled by the measured dispersion, so "
                                           "thinning does not make it overconfident)", range=(100, 1000000))


@dataclasses.dataclass
class EdgeResult:
    delta: np.ndarray          # (3,) translation offset in the camera frame
    sigma_m: float             # 1-sigma of the offset along the search direction
    cost0: float               # score at delta = 0 (px)
    cost: float                # score at the optimum (px)
    tstat: float               # paired t statistic of the per-point improvement
    n_points: int
    per_image_m: np.ndarray    # per-image optima along the direction (m)
    profile: np.ndarray        # (K,2) offsets (m) and scores of the fine 1-D profile


def _rings(raw: np.ndarray, gap_deg: float = 0.08) -> np.ndarray:
    """Ring label per point from the clustered elevation angles (-1 for stray points)."""
    r = np.linalg.norm(raw, axis=1)
    el = np.degrees(np.arcsin(np.clip(raw[:, 2] / np.maximum(r, 1e-9), -1, 1)))
    order = np.argsort(el)
    es = el[order]
    cut = np.flatnonzero(np.diff(es) > gap_deg)
    lab_sorted = np.zeros(es.size, int)
    lab_sorted[cut + 1] = 1
    lab_sorted = np.cumsum(lab_sorted)
    counts = np.bincount(lab_sorted)
    good = counts[lab_sorted] >= 50
    lab = np.full(raw.shape[0], -1, int)
    lab[order[good]] = lab_sorted[good]
    return lab


def _storage_rings(raw: np.ndarray, min_points: int = 1000) -> np.ndarray | None:
    """Ring label per point when the cloud is stored ring by ring (KITTI's files, organised Ouster clouds
    without a ring field): storage neighbours are then azimuth neighbours of one laser (a column step
    apart, the elevation nearly the same), and the next ring begins where the azimuth has turned a full
    circle (across the gaps where nothing returned) or jumps back. None when the cloud is not stored that
    way (column by column, or shuffled)."""
    n = raw.shape[0]
    if n < min_points:
        return None
    az = np.arctan2(raw[:, 1], raw[:, 0])
    el = np.arctan2(raw[:, 2], np.hypot(raw[:, 0], raw[:, 1]))
    daz = np.angle(np.exp(1j * np.diff(az)))
    step = float(np.median(np.abs(daz)))
    # ring by ring: a column step (well under a degree) between storage neighbours, and the elevation
    # nearly constant (column by column, neighbours are a ring spacing apart: 0.3 deg and more)
    if not (1e-5 < step < math.radians(1.0)) or float(np.median(np.abs(np.diff(el)))) > math.radians(0.1):
        return None
    fwd = daz if np.median(daz) >= 0 else -daz
    back = fwd < -10.0 * step                       # the azimuth jumps back: a new ring
    travel = np.concatenate([[0.0], np.cumsum(np.where(back, 0.0, np.maximum(fwd, 0.0)))])  # at each point
    starts = [0]
    back_at = np.flatnonzero(back) + 1
    while True:
        s0 = starts[-1]
        full = int(np.searchsorted(travel, travel[s0] + 2 * math.pi - 3.0 * step))  # a full turn later
        nxt = back_at[back_at > s0]
        e = min(full, int(nxt[0]) if nxt.size else n)
        if e >= n:
            break
        starts.append(e)
    lab = np.zeros(n, np.int64)
    for k, s0 in enumerate(starts[1:], 1):
        lab[s0:] = k
    return lab


def ring_sequence(raw: np.ndarray, ring: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(order, label): point indices such that consecutive entries with the same label (>= 0) are azimuth
    neighbours on one ring, and the ring label of every point (-1: stray). From the driver's ``ring``
    field when given (renumbered by elevation); else from the storage order when the cloud is stored ring
    by ring (:func:`_storage_rings`: the only way on a real HDL-64 without a ring field, whose lasers do not
    sit at the sensor origin, so that one laser's elevation seen from the origin spreads over degrees at
    short range: 3.5-4 deg interquartile on KITTI); else from the clustered elevation angles
    (:func:`_rings`, exact on simulated heads)."""
    raw = np.asarray(raw, float).reshape(-1, 3)
    az = np.arctan2(raw[:, 1], raw[:, 0])
    if ring is not None and np.asarray(ring).size == raw.shape[0]:
        ring = np.asarray(ring).astype(np.int64).ravel()
        _, inv, cnt = np.unique(ring, return_inverse=True, return_counts=True)
        el = np.arctan2(raw[:, 2], np.hypot(raw[:, 0], raw[:, 1]))
        rank = np.argsort(np.argsort(np.bincount(inv, weights=el) / cnt))  # by mean elevation, ascending
        lab = np.where(cnt[inv] >= 50, rank[inv], -1)
    else:
        lab = _storage_rings(raw)
        if lab is not None:
            return np.arange(raw.shape[0]), lab
        lab = _rings(raw)
    order = np.lexsort((az, lab))
    return order[lab[order] >= 0], lab


def lidar_edges(raw: np.ndarray, pts: np.ndarray, intensity: np.ndarray | None, cfg: EdgeConfig,
                keep: np.ndarray | None = None, ring: np.ndarray | None = None,
                ground: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(edge points (M,3) in the frame of ``pts``, kind (M,): 0 silhouette, 1 intensity).
    ``raw``: the points as measured, ``pts``: the same points de-skewed; ``keep``: points allowed to form
    an edge (static); ``ring``: the driver's ring field, if any (else :func:`ring_sequence` finds the
    rings); ``ground``: points on the road, the only ones that form intensity edges (None: any)."""
    order, ring = ring_sequence(raw, ring)
    rng = np.linalg.norm(raw, axis=1)
    az = np.arctan2(raw[:, 1], raw[:, 0])
    a, b = order[:-1], order[1:]
    same = ring[a] == ring[b]
    daz = np.abs(np.angle(np.exp(1j * (az[b] - az[a]))))
    step = np.median(daz[same]) if same.any() else 0.0
    adj = same & (daz < 3.0 * max(step, 1e-5))
    if keep is not None:
        adj &= keep[a] & keep[b]
    ra, rb = rng[a], rng[b]
    near = np.minimum(ra, rb)
    jump = np.abs(ra - rb) > np.maximum(cfg.depth_jump_m, cfg.depth_jump_rel * near)
    inr = (near >= cfg.min_range_m) & (near <= cfg.max_range_m)
    # the near side must be a continuous surface (its other neighbour at about the same range): leaves
    # out foliage and other range noise
    cont = adj & (np.abs(ra - rb) < cfg.smooth_rel * near + 0.05)
    prev_ok = np.concatenate([[False], cont[:-1]])  # pair j-1 continuous: a's far side
    next_ok = np.concatenate([cont[1:], [False]])   # pair j+1 continuous: b's far side
    a_near = ra < rb
    sil = adj & jump & inr & np.where(a_near, prev_ok, next_ok)
    if cfg.clutter_window > 0 and sil.any():
        # depth jumps among the neighbouring pairs along the ring (a pair across a ring break is not adjacent;
        # within w pairs of a ring's ends the next ring's first pairs are counted too)
        w = int(cfg.clutter_window)
        n_jumps = np.convolve((adj & jump).astype(float), np.ones(2 * w + 1), mode="same")
        sil &= n_jumps <= cfg.clutter_max_jumps + 0.5
    idx = np.where(a_near[sil], a[sil], b[sil])
    # the silhouette lies between the two rays: put it on the mean ray at the near range (the near point
    # alone sits inside the object by up to one azimuth step), moved as the near point was de-skewed
    ua = raw[a[sil]] / ra[sil, None]
    ub = raw[b[sil]] / rb[sil, None]
    um = ua + ub
    um /= np.maximum(np.linalg.norm(um, axis=1, keepdims=True), 1e-12)
    out = [pts[idx] + um * near[sil, None] - raw[idx]]
    kind = [np.zeros(idx.size, int)]
    if intensity is not None and intensity.size == raw.shape[0]:
        on = adj & (np.abs(ra - rb) < 0.05 * near + 0.05)
        if ground is not None:
            on &= ground[a] & ground[b]
        pt = intensity_steps(np.asarray(intensity, float)[order], on, cfg) & inr
        out.append(0.5 * (pts[a[pt]] + pts[b[pt]]))
        kind.append(np.ones(int(pt.sum()), int))
    return np.concatenate(out), np.concatenate(kind)


def intensity_steps(inten: np.ndarray, cont: np.ndarray, cfg: EdgeConfig) -> np.ndarray:
    """Which pairs (j, j+1) of the intensities ``inten`` (in scan order) are paint edges; ``cont`` (one per
    pair): its two points are neighbours on one continuous surface. The step is the difference of the mean
    intensities of up to ``intensity_window`` points each side within the same continuous run; it must exceed
    ``intensity_jump`` times the sweep's 95th percentile, and, relative to the two means' average,
    ``intensity_z`` sigmas of the texture (the median relative difference of neighbouring returns on
    continuous surfaces, over 0.6745 sqrt 2: the per-return scatter a camera pixel averages away), and be a
    local maximum along the run (one edge, one point). A window of 1 is the plain neighbour difference."""
    n_p = inten.size - 1
    pt = np.zeros(max(n_p, 0), bool)
    if n_p < 1 or not cont.any():
        return pt
    scale = max(float(np.percentile(inten, 95)), 1e-9)
    ia, ib = inten[:-1], inten[1:]
    rel = np.abs(ia - ib) / np.maximum(0.5 * (ia + ib), 1e-9 * scale)
    sig = float(np.median(rel[cont])) / (0.6745 * math.sqrt(2.0))
    k = int(cfg.intensity_window)
    j = np.arange(n_p)
    # continuous runs of points: a point starts a new run where the pair before it is not continuous
    run = np.concatenate([[0], np.cumsum(~cont)])
    first = np.searchsorted(run, run, side="left")      # first point of each point's run
    last = np.searchsorted(run, run, side="right") - 1   # last point of it
    lo = np.maximum(j - k + 1, first[j])
    hi = np.minimum(j + k, last[j + 1])
    nL, nR = j + 1 - lo, hi - j
    c = np.concatenate([[0.0], np.cumsum(inten)])
    mL = (c[j + 1] - c[lo]) / nL
    mR = (c[hi + 1] - c[j + 1]) / nR
    D = np.abs(mR - mL)
    ok = cont & (D > cfg.intensity_jump * scale)
    if cfg.intensity_z > 0 and k > 1:
        n_eff = np.minimum(nL, nR)
        ok &= D / np.maximum(0.5 * (mL + mR), 1e-9 * scale) > cfg.intensity_z * sig * np.sqrt(2.0 / n_eff)
    if k > 1:
        # a local maximum along the run (the windowed step ramps up over the window towards a true step: its
        # neighbours are smaller; two sides of a stripe a few points wide both stay)
        Dm = np.where(cont, D, -1.0)
        ok[1:] &= Dm[1:] > Dm[:-1]
        ok[:-1] &= Dm[:-1] >= Dm[1:]
    return ok


def image_distance(image: np.ndarray, cfg: EdgeConfig) -> np.ndarray:
    """Distance (px, float32) of every pixel to the nearest Canny edge."""
    import cv2
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if cfg.blur_sigma_px > 0:
        g = cv2.GaussianBlur(g, (0, 0), cfg.blur_sigma_px)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1)
    mag = np.hypot(gx, gy)
    hi = float(np.percentile(mag, 90))
    e = cv2.Canny(g, 0.4 * hi, hi, L2gradient=True)
    return cv2.distanceTransform(255 - e, cv2.DIST_L2, 5).astype(np.float32)


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``img`` (H,W) or (H,W,C) at (N,2) pixels (clamped inside the image): (N,) or
    (N,C). One gather per corner, however many channels."""
    return _sample_split([img], uv, np.zeros(0, np.intp))


def _sample_split(imgs: list, uv: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """:func:`_sample` of each image of ``imgs`` (all the same shape) at its own run of ``uv`` (``uv`` cut at
    ``cuts``), concatenated: the clamping and the bilinear weights are computed once for all images (the
    refinement samples 8 images per evaluation; 4 gathers per image remain)."""
    h, w = imgs[0].shape[:2]
    chan = imgs[0].ndim > 2
    x = np.clip(uv[:, 0], 0, w - 1.001)
    y = np.clip(uv[:, 1], 0, h - 1.001)
    x0, y0 = x.astype(np.intp), y.astype(np.intp)
    fx, fy = x - x0, y - y0
    flats = [f.reshape(-1, f.shape[-1] if chan else 1) for f in imgs]
    runs = np.split(y0 * w + x0, cuts)
    a, b = (1 - fx) * (1 - fy), fx * (1 - fy)
    c, d = (1 - fx) * fy, fx * fy

    def corner(o):
        return np.concatenate([np.take(f, i + o, axis=0) for f, i in zip(flats, runs)])
    out = corner(0) * a[:, None] + corner(1) * b[:, None] + corner(w) * c[:, None] + corner(w + 1) * d[:, None]
    return out if chan else out[:, 0]


def _visible(cam: CameraModel, T: np.ndarray, edges: np.ndarray, cloud: np.ndarray, cell_px: int = 4,
             margin_px: float = 8.0) -> np.ndarray:
    """Edge points inside the image (with a margin) and not hidden behind other LiDAR points."""
    q = transform_points(T, edges)
    uv, ok = cam.project(q)
    ok &= (uv[:, 0] > margin_px) & (uv[:, 0] < cam.width - margin_px) & \
          (uv[:, 1] > margin_px) & (uv[:, 1] < cam.height - margin_px) & (q[:, 2] > 1.0)
    qc = transform_points(T, cloud)
    qc = qc[qc[:, 2] > 0.5]  # (behind the camera: most of a spinning LiDAR's sweep, not projected)
    uvc, okc = cam.project(qc)
    gw, gh = cam.width // cell_px + 1, cam.height // cell_px + 1
    zb = np.full(gw * gh, np.inf)
    cc = (uvc[okc] / cell_px).astype(int)
    np.minimum.at(zb, cc[:, 1] * gw + cc[:, 0], qc[okc, 2])
    zb = zb.reshape(gh, gw)
    # a point hidden by any nearer point in its 3x3 cells
    zpad = np.pad(zb, 1, constant_values=np.inf)
    zmin = zpad[1:gh + 1, 1:gw + 1].copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            np.minimum(zmin, zpad[1 + dy:gh + 1 + dy, 1 + dx:gw + 1 + dx], out=zmin)
    ce = np.clip((uv / cell_px).astype(int), 0, [gw - 1, gh - 1]) if uv.size else np.zeros((0, 2), int)
    zcell = zmin[ce[:, 1], ce[:, 0]]
    ok &= q[:, 2] <= zcell + 0.3 + 0.05 * q[:, 2]
    return ok


def refine_translation(images: list, cam: CameraModel, raw: np.ndarray, pts: np.ndarray,
                       intensity: np.ndarray | None, static: np.ndarray, X: np.ndarray,
                       T_sweep_imgs: list, direction: np.ndarray, cfg: EdgeConfig | None = None,
                       full: bool = False, ring: np.ndarray | None = None) -> EdgeResult | None:
    """Offset of the translation of the extrinsic ``X`` (camera <- LiDAR at exposure 0) that best puts
    the LiDAR edges of one sweep on the image edges. ``pts``: de-skewed sweep points (sweep frame),
    ``raw``: as measured, ``static``: points that did not move; ``T_sweep_imgs[k]``: the LiDAR at the
    sweep stamp <- the LiDAR at exposure k (odometry), one per image; ``direction``: unit vector (camera
    frame) of the 1-D search. ``full``: then a small 3-D refinement; ``ring``: the driver's ring field, if
    any. None when too few edges are seen."""
    cfg = cfg or EdgeConfig()
    d = np.asarray(direction, float)
    d = d / max(np.linalg.norm(d), 1e-12)
    E, _kind = lidar_edges(raw, pts, intensity, cfg, keep=static, ring=ring)
    if E.shape[0] < cfg.min_points:
        return None
    cloud = pts[static][::2]
    views = []
    for img, Tsi in zip(images, T_sweep_imgs):
        Tk = X @ inv_T(Tsi)  # camera k <- sweep
        vis = _visible(cam, Tk, E, cloud)
        if vis.sum() < cfg.view_min_points:
            continue
        views.append((image_distance(img, cfg), Tk, E[vis]))
    n = sum(v[2].shape[0] for v in views)
    if n < cfg.min_points:
        return None

    def point_costs(delta: np.ndarray, trunc: float) -> list:
        out = []
        for dt, Tk, Ek in views:
            uv, _ = cam.project(Ek @ Tk[:3, :3].T + Tk[:3, 3] + delta)
            out.append(np.minimum(_sample(dt, uv), trunc))
        return out

    def costs(delta: np.ndarray, trunc: float) -> tuple[float, np.ndarray]:
        v = point_costs(delta, trunc)
        return float(np.concatenate(v).mean()), np.array([x.mean() for x in v])

    def line(c: float, half: float, step: float, trunc: float):
        s = np.arange(c - half, c + half + 0.5 * step, step)
        res = [costs(si * d, trunc) for si in s]
        return s, np.array([r[0] for r in res]), np.array([r[1] for r in res])

    cost0, _ = costs(np.zeros(3), cfg.truncate_px)
    s, f, _ = line(0.0, cfg.search_m, cfg.coarse_step_m, cfg.coarse_truncate_px)
    ic = int(np.argmin(f))
    if ic in (0, len(s) - 1):  # no minimum inside the search range: the edges do not constrain it
        return None
    c = float(s[ic])
    s, f, per = line(c, 4 * cfg.coarse_step_m, cfg.fine_step_m, cfg.truncate_px)
    i = int(np.argmin(f))
    best = float(s[i])
    if 0 < i < len(s) - 1:  # parabola through the three lowest
        den = f[i - 1] - 2 * f[i] + f[i + 1]
        if den > 0:
            best += 0.5 * (f[i - 1] - f[i + 1]) / den * (s[1] - s[0])
    per_img = s[np.argmin(per, axis=0)]
    delta = best * d
    if full:
        delta = _refine3(costs, delta, cfg)
    cost, _ = costs(delta, cfg.truncate_px)
    # significance of the improvement: paired per-point differences (t statistic)
    diff = np.concatenate(point_costs(np.zeros(3), cfg.truncate_px)) - \
        np.concatenate(point_costs(delta, cfg.truncate_px))
    tstat = float(diff.mean() / max(diff.std(ddof=1) / np.sqrt(diff.size), 1e-12))
    k = len(per_img)
    spread = float(np.std(per_img, ddof=1) / np.sqrt(k)) if k >= 2 else cfg.search_m
    return EdgeResult(delta=delta, sigma_m=spread, cost0=cost0, cost=cost, tstat=tstat, n_points=n,
                      per_image_m=per_img, profile=np.stack([s, f], axis=1))


def _refine3(costs, delta: np.ndarray, cfg: EdgeConfig) -> np.ndarray:
    """Small 3-D coordinate descent around ``delta`` (camera axes), halving steps."""
    x0 = delta.copy()
    x = delta.copy()
    fx, _ = costs(x, cfg.truncate_px)
    step = 0.02
    while step >= cfg.fine_step_m / 2:
        moved = False
        for ax in range(3):
            for sg in (-1.0, 1.0):
                y = x.copy()
                y[ax] += sg * step
                if np.linalg.norm(y - x0) > cfg.max_3d_m:
                    continue
                fy, _ = costs(y, cfg.truncate_px)
                if fy < fx:
                    x, fx, moved = y, fy, True
        if not moved:
            step /= 2
    return x


@dataclasses.dataclass
class EdgeView:
    """One image of the window with the LiDAR sweep nearest its exposure."""
    image: np.ndarray
    raw: np.ndarray                 # (N,3) the sweep as measured
    pts: np.ndarray                 # (N,3) the same points de-skewed to the sweep stamp
    intensity: np.ndarray | None
    static: np.ndarray              # (N,) bool: points that did not move between sweeps
    T_sweep_img: np.ndarray         # LiDAR at the sweep stamp <- LiDAR at this exposure
    ring: np.ndarray | None = None   # (N,) the driver's ring field, if any
    ground: np.ndarray | None = None  # (N,) bool: on the road (paint edges only there); None: anywhere
    edges: np.ndarray | None = None  # (M,3) its LiDAR edges (de-skewed), filled by prepare_view
    kinds: np.ndarray | None = None  # (M,) 0 silhouette, 1 intensity (paint), filled by prepare_view
    dist: np.ndarray | None = None   # the image's edge-distance map, filled by prepare_view
    fields: dict = dataclasses.field(default_factory=dict, repr=False)  # filled by view_field
    occl: np.ndarray | None = None   # every other static point (the visibility test's occluders), by occluders
    sweep_stamp_s: float | None = None  # the sweep's stamp (LiDAR clock), if known
    image_index: int = -1            # the image's index in its window (-1: unknown)
    time_s: np.ndarray | None = None  # (N,) each raw point's time after the sweep's stamp, if known
    deskew_rate: np.ndarray | None = None  # (3,) the rotation rate (rad/s, LiDAR axes) the de-skew used


def occluders(v: EdgeView) -> np.ndarray:
    """The view's static points, every other one: what may hide its edges (taken once per view)."""
    if v.occl is None:
        v.occl = v.pts[v.static][::2]
    return v.occl


def prepare_view(v: EdgeView, cfg: EdgeConfig) -> EdgeView:
    """Fill the view's LiDAR edges and image edge-distance map once (both do not depend on the
    extrinsic)."""
    if v.edges is None:
        v.edges, v.kinds = lidar_edges(v.raw, v.pts, v.intensity, cfg, keep=v.static, ring=v.ring, ground=v.ground)
    if v.dist is None:
        v.dist = image_distance(v.image, cfg)
    return v


def edge_kind_inliers(views: list, cam: CameraModel, X: np.ndarray, cfg: EdgeConfig,
                      tol_px: float = 1.5) -> dict:
    """At the extrinsic ``X``: the share of the visible silhouette and paint (intensity) edge points within
    ``tol_px`` of an image edge (``silhouette``, ``paint``, with their counts ``n_silhouette``,
    ``n_paint``), and ``chance``: the share of the images' pixels that close to an edge, which points
    thrown anywhere would reach. Edges that do not meet the image more often than chance carry no
    information about the extrinsic, only pull on it."""
    hit = {0: [0, 0], 1: [0, 0]}
    near = []
    for v in views:
        prepare_view(v, cfg)
        near.append(float(np.mean(v.dist <= tol_px)))
        if v.edges.shape[0] == 0:
            continue
        Tk = X @ inv_T(v.T_sweep_img)
        vis = _visible(cam, Tk, v.edges, occluders(v))
        if not vis.any():
            continue
        uv, _ = cam.project(transform_points(Tk, v.edges[vis]))
        d = _sample(v.dist, uv)
        kinds = v.kinds[vis]
        for k in (0, 1):
            m = kinds == k
            hit[k][0] += int(np.sum(d[m] <= tol_px))
            hit[k][1] += int(m.sum())
    share = {k: hit[k][0] / hit[k][1] if hit[k][1] else float("nan") for k in hit}
    return {"silhouette": share[0], "paint": share[1], "n_silhouette": hit[0][1], "n_paint": hit[1][1],
            "chance": float(np.mean(near)) if near else float("nan")}


def of_kind(views: list, cfg: EdgeConfig, kind: int) -> list:
    """The views with their edges of one kind only (0 silhouettes, 1 paint; the image and its distance
    fields are shared)."""
    out = []
    for v in views:
        prepare_view(v, cfg)
        m = v.kinds == kind
        out.append(dataclasses.replace(v, edges=v.edges[m], kinds=v.kinds[m]))
    return out


def without_paint(views: list, cfg: EdgeConfig) -> list:
    """The views with their silhouettes only (the image and its distance fields are shared)."""
    return of_kind(views, cfg, 0)


def yaw_about_edges(views: list, X: np.ndarray, up: np.ndarray, deg: float) -> np.ndarray:
    """The extrinsic ``X`` turned by ``deg`` about the camera-frame ``up`` axis through the median of the
    views' LiDAR edges (camera frame, from ``prepare_view``): the bulk of the edges stays put while near
    and far ones move apart. A yaw and a lateral shift trade off along that valley of the edge fit, so
    starts along it reach minima a single start misses."""
    q = [transform_points(X @ inv_T(v.T_sweep_img), v.edges) for v in views if v.edges is not None]
    c0 = np.median(np.concatenate(q), axis=0) if q else np.zeros(3)
    u = np.asarray(up, float) / max(np.linalg.norm(up), 1e-12)
    D = np.eye(4)
    D[:3, :3] = so3_exp(np.radians(deg) * u)
    D[:3, 3] = c0 - D[:3, :3] @ c0
    return D @ X


def azimuth_step_rad(points: np.ndarray, n_queries: int = 20000) -> float:
    """The spinning LiDAR's column step (rad) from one sweep, with no ring field needed: in (azimuth,
    elevation) about the sensor, each point's nearest neighbour, with elevation differences weighed 50x so
    that only a point of the same ring (the same elevation) can be nearest, lies one column away; the
    median over ``n_queries`` points drawn evenly at random (the tree holds them all: thinning the cloud
    would widen the gaps). NaN for fewer than 100 points."""
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    p = p[np.linalg.norm(p, axis=1) > 0.5]
    if p.shape[0] < 100:
        return float("nan")
    from scipy.spatial import cKDTree
    az = np.arctan2(p[:, 1], p[:, 0])
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    q = np.column_stack([az, 50.0 * el])
    sel = np.random.default_rng(0).choice(q.shape[0], min(n_queries, q.shape[0]), replace=False)
    d, _ = cKDTree(q).query(q[sel], k=2)
    d = d[:, 1]
    d = d[d > 1e-7]                 # duplicated returns
    return float(np.median(d)) if d.size >= 50 else float("nan")


def ring_spacing_deg(points: np.ndarray, ring: np.ndarray | None = None) -> tuple[int, float]:
    """(rings seen, median elevation gap between neighbouring rings in degrees) of a spinning LiDAR's
    sweep, from its points as measured and the driver's ``ring`` field if any (:func:`ring_sequence`). A
    ring that sees nothing (sky) is not counted, and the median gap is not widened by it unless most rings
    are missing. (0, NaN) for fewer than 100 points, NaN spacing for fewer than 2 rings."""
    p = np.asarray(points, float).reshape(-1, 3)
    good = np.isfinite(p).all(axis=1)
    good[good] = np.linalg.norm(p[good], axis=1) > 0.5
    if good.sum() < 100:
        return 0, float("nan")
    r = None if ring is None or np.asarray(ring).size != p.shape[0] else np.asarray(ring).ravel()[good]
    p = p[good]
    _, lab = ring_sequence(p, r)
    ok = lab >= 0
    if not ok.any():
        return 0, float("nan")
    el = np.degrees(np.arctan2(p[ok, 2], np.hypot(p[ok, 0], p[ok, 1])))
    lk = lab[ok]
    # each ring's median elevation (a real head's lasers sit apart: seen from the origin, near points
    # spread one laser's elevation over degrees; the median stays with the far ones)
    srt = np.lexsort((el, lk))
    lk, el = lk[srt], el[srt]
    first = np.flatnonzero(np.concatenate([[True], lk[1:] != lk[:-1]]))
    cnt = np.diff(np.concatenate([first, [lk.size]]))
    big = cnt >= 0.25 * np.median(cnt)     # not the sliver of a ring that the storage order cut off
    centres = np.sort(el[(first + cnt // 2)[big]])
    if centres.size < 2:
        return int(centres.size), float("nan")
    return int(centres.size), float(np.median(np.diff(centres)))


@dataclasses.dataclass
class PoseEdgeResult:
    T: np.ndarray                   # refined extrinsic (camera <- LiDAR at the exposure)
    xi: np.ndarray                  # (6,) left perturbation (rotation vector, translation) from the start
    cov: np.ndarray                 # (6,6) its covariance (camera frame), dispersion-scaled
    cost0: float                    # mean truncated edge distance at the start (px)
    cost: float                     # ... at the optimum
    inliers0: float                 # fraction of edge points within 1.5 px of an image edge at the start
    inliers: float                  # ... at the optimum
    n_points: int
    n_views: int
    dispersion: float               # scatter of the per-image optima over what their information predicts
    # (6,6) the fit's information at the optimum (Cauchy-weighted J^T J plus the priors, in the residual's own
    # units: cov = pinv(info) * the dispersion-scaled residual variance); a group's own information at the fit
    # (edge_group_information) against it is that group's leverage in the jackknifes
    info: np.ndarray | None = None


def _field(dist: np.ndarray, trunc: float, blur: float) -> np.ndarray:
    """Truncated, smoothed edge-distance field (from ``image_distance``) with its gradient (px per px),
    stacked as (H,W,3) so that one bilinear gather samples all three."""
    import cv2
    f = np.minimum(dist, trunc).astype(np.float32)
    if blur > 0:
        f = cv2.GaussianBlur(f, (0, 0), blur)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.ascontiguousarray(np.stack([f, gx, gy], axis=2))


def view_field(v: EdgeView, trunc: float, blur: float, grad: bool = True) -> np.ndarray:
    """The view's ``_field`` at (``trunc``, ``blur``) (``grad`` False: the truncated distance alone, (H,W)),
    computed once per view: a window's fits (the coarse ranking, the restarts, the basin starts, the
    jackknife) all sample the same few fields."""
    key = (float(trunc), float(blur), bool(grad))
    f = v.fields.get(key)
    if f is None:
        f = _field(v.dist, trunc, blur) if grad else np.minimum(v.dist, trunc).astype(np.float32)
        v.fields[key] = f
    return f


def proj_jacobian(K: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N,2,6) d(pixel)/d(left perturbation: rotation vector, translation) of camera points ``q``
    (pinhole part; distortion changes it by far less than the fit needs)."""
    n = q.shape[0]
    out = np.empty((n, 2, 6))
    for row in (0, 1):
        g = np.zeros((n, 2))
        g[:, row] = 1.0
        out[:, row] = field_jacobian(K, q, g)
    return out


def field_jacobian(K: np.ndarray, q: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(N,6) d(field value)/d(left perturbation) of camera points ``q`` whose field has the image
    gradient ``g`` (N,2): the gradient pushed through the pinhole projection. The translation part is
    t = d(field)/dq; the rotation part, for dq = w x q, is q x t."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    a = g[:, 0] * float(K[0, 0]) / z
    b = g[:, 1] * float(K[1, 1]) / z
    t = np.stack([a, b, -(a * x + b * y) / z], axis=1)
    return np.concatenate([np.cross(q, t), t], axis=1)


def _stats(rj: list, c: float):
    """Per-image information and gradient of the Cauchy-weighted fit, and its residual variance."""
    Hs, gs = [], []
    for r, J in rj:
        w = 1.0 / (1.0 + (r / c) ** 2)
        Hs.append(J.T @ (J * w[:, None]))
        gs.append(J.T @ (w * r))
    rr = np.concatenate([r for r, _ in rj])
    ww = 1.0 / (1.0 + (rr / c) ** 2)
    naive = float(np.sum(ww * rr ** 2) / max(np.sum(ww) - Hs[0].shape[0], 1.0))
    return Hs, gs, naive


def _scale(Hs: list, gs: list, naive: float, m: int) -> float:
    """Residual variance that makes the images' linearised optima about the joint one scatter as their
    own information predicts (each image's step, damped where it alone sees nothing, and its squared
    Mahalanobis length under that image's information average m * (K-1) / K); never below the naive
    residual variance. An image with no information (every point on the truncated plateau of its field, no
    gradient: it sees no edge near any of its points) has no optimum of its own and is left out."""
    m2 = []
    for Hk, gk in zip(Hs, gs):
        tr = float(np.trace(Hk))
        if not np.isfinite(tr) or tr <= 0.0:
            continue
        try:
            dk = -np.linalg.solve(Hk + 1e-6 * tr * np.eye(m), gk)
        except np.linalg.LinAlgError:
            continue
        m2.append(float(dk @ Hk @ dk))
    k = len(m2)
    return max(float(np.sum(m2) / (m * max(k - 1, 1))), naive)


def _fit_points(v: EdgeView, cam: CameraModel, X: np.ndarray, cfg: EdgeConfig) -> np.ndarray | None:
    """The view's edge points that the 6-DoF fit uses at the extrinsic ``X``, in the camera frame at its
    exposure: the visible ones, evenly thinned to ``pose_max_points`` (the edges come in scan order);
    None when fewer than ``view_min_points`` are seen."""
    E = prepare_view(v, cfg).edges
    if E.shape[0] < cfg.view_min_points:
        return None
    Tk = X @ inv_T(v.T_sweep_img)      # camera at this exposure <- sweep
    vis = _visible(cam, Tk, E, occluders(v))
    if vis.sum() < cfg.view_min_points:
        return None
    idx = np.flatnonzero(vis)
    if idx.size > cfg.pose_max_points:
        idx = idx[np.linspace(0, idx.size - 1, cfg.pose_max_points).astype(int)]
    return transform_points(Tk, E[idx])


def refine_pose(views: list, cam: CameraModel, X: np.ndarray, cfg: EdgeConfig | None = None,
                direction: np.ndarray | None = None, up: np.ndarray | None = None,
                tilt_prior_deg: float = 0.0, height_prior_m: float = 0.0,
                prior_centre: np.ndarray | None = None,
                height_pivot: np.ndarray | None = None) -> PoseEdgeResult | None:
    """All six degrees of freedom of the extrinsic ``X`` (camera <- LiDAR at the exposure) from the
    LiDAR edges of each view's own sweep against that view's image edges.

    Each view brings its nearest sweep, so neither the odometry's drift nor one sweep's edge errors
    are shared by all images. Steps: an optional 1-D search along ``direction`` (the driving
    direction, which the clouds leave least certain), then Levenberg-Marquardt on the smoothed,
    truncated distance fields (coarse, then fine) with Cauchy weights. The covariance is the inverse of
    the joint information scaled by the measured dispersion: each image's linearised optimum about the
    joint one, weighed by that image's own information, must scatter as its information predicts; the
    scale that makes it so (neighbouring edge points share their errors) multiplies the joint inverse.
    None when too few edges are seen.

    ``up`` (camera frame): with ``tilt_prior_deg`` > 0, priors on the two rotations about the horizontal
    axes (and with ``height_prior_m`` > 0 on the translation along ``up``) around ``prior_centre`` (an
    extrinsic; default the start ``X``: a restart from a fit's own result must keep the prior where the
    ground planes put it, or each restart lets the tilt drift by another prior width); with
    ``tilt_prior_deg`` = 0, only the yaw about ``up`` and the translation are fitted (4 DoF).
    ``height_pivot`` (camera frame): the point where the ground planes fix the height (the registered
    overlap's centroid); the height prior holds there, not at the camera, so that a tilt within its prior
    moves the camera's height by the tilt times the lever arm (default: the camera's origin)."""
    cfg = cfg or EdgeConfig()
    K = cam.K
    V = []
    for v in views:
        q = _fit_points(v, cam, X, cfg)
        if q is not None:  # the edge points in the camera frame at X (perturbed on the left from here on)
            V.append({"q": q, "view": v})
    n = sum(v["q"].shape[0] for v in V)
    if len(V) < 2 or n < cfg.min_points:
        return None
    # all views at once: their points stacked, each sampling its own image's field
    Q = np.concatenate([v["q"] for v in V])
    sizes = [v["q"].shape[0] for v in V]
    cuts = np.cumsum(sizes)[:-1]

    def fields(trunc: float, blur: float, grad: bool = True) -> list:
        return [view_field(v["view"], trunc, blur, grad) for v in V]

    def sample(fld: list, uv: np.ndarray) -> np.ndarray:
        """The views' points each sampled in its own image's field: (N,3) field, gx, gy, or (N,)."""
        if all(f.shape == fld[0].shape for f in fld):
            return _sample_split(fld, uv, cuts)
        return np.concatenate([_sample(f, p) for f, p in zip(fld, np.split(uv, cuts))])

    def per_view(rJ):
        r, J = rJ
        return list(zip(np.split(r, cuts), np.split(J, cuts)))

    u = None if up is None else np.asarray(up, float) / max(np.linalg.norm(up), 1e-12)
    if u is None or tilt_prior_deg > 0:
        B = np.eye(6)
    else:  # yaw about the up axis (camera frame) and the translation: the tilt stays the caller's
        B = np.zeros((6, 4))
        B[:3, 0] = u
        B[3:, 1:] = np.eye(3)
    m = B.shape[1]
    # optional prior on the tilt (the two rotations about the horizontal axes, from the ground planes);
    # its weight is in units of the edge residual variance, set after a first pass without it
    Pt = np.zeros((6, 6))
    if u is not None and tilt_prior_deg > 0 and m == 6:
        Pt[:3, :3] = (np.eye(3) - np.outer(u, u)) / np.radians(tilt_prior_deg) ** 2
        if height_prior_m > 0:  # the height along the up axis (silhouettes are vertical: they do not see it)
            # at the pivot p0: a left perturbation (w, t) moves it up by u.(w x p0 + t) = (p0 x u).w + u.t
            p0 = np.zeros(3) if height_pivot is None else np.asarray(height_pivot, float)
            a = np.concatenate([np.cross(p0, u), u])
            Pt += np.outer(a, a) / height_prior_m ** 2
    P = np.zeros((6, 6))
    xc = np.zeros(6)  # the prior's centre as a left perturbation of X
    if prior_centre is not None:
        Rc = prior_centre[:3, :3] @ X[:3, :3].T
        xc = np.concatenate([so3_log(Rc), prior_centre[:3, 3] - Rc @ X[:3, 3]])

    def apply(xi, q):
        R = so3_exp(xi[:3])
        return q @ R.T + xi[3:]

    def residuals(xi, fld, with_jac=False):
        """The views' field values at xi (N,), with their Jacobian (N,m): f, gx, gy in one gather."""
        q = apply(xi, Q)
        uv, _ = cam.project(q)
        s3 = sample(fld, uv)
        if not with_jac:
            return s3 if s3.ndim == 1 else s3[:, 0]
        J = field_jacobian(K, q, s3[:, 1:])
        return s3[:, 0], (J if m == 6 else J @ B)

    def cost(xi, r, c):  # Cauchy loss of the residuals plus the prior
        return float(0.5 * c * c * np.sum(np.log1p((r / c) ** 2)) + 0.5 * (xi - xc) @ P @ (xi - xc))

    def lm(xi, fld, c, iters=25):
        lam = 1e-3
        for _ in range(iters):
            r, J = residuals(xi, fld, True)
            w = 1.0 / (1.0 + (r / c) ** 2)
            Pm = B.T @ P @ B
            H = J.T @ (J * w[:, None]) + Pm
            g = J.T @ (w * r) + B.T @ (P @ (xi - xc))
            f0 = cost(xi, r, c)
            improved = False
            for _ in range(8):
                A = H + lam * np.diag(np.diag(H) + 1e-9)
                try:
                    step = -np.linalg.solve(A, g)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                xn = xi + B @ step
                if cost(xn, residuals(xn, fld), c) < f0:
                    xi, lam, improved = xn, max(lam / 3, 1e-6), True
                    break
                lam *= 10
            st6 = B @ step
            # converged: a step under 1e-5 rad and 0.1 mm moves an edge point by about 0.01 px (f ~ 1000 px,
            # points 5 m away and beyond); the Cauchy-weighted steps dither below that for many iterations
            if not improved or np.linalg.norm(st6[:3]) < 1e-5 and np.linalg.norm(st6[3:]) < 1e-4:
                break
        return xi

    xi = np.zeros(6)
    coarse = fields(cfg.coarse_truncate_px, cfg.pose_coarse_blur_px)
    if direction is not None:
        d = np.asarray(direction, float)
        d = d / max(np.linalg.norm(d), 1e-12)
        s = np.arange(-cfg.search_m, cfg.search_m + 0.5 * cfg.coarse_step_m, cfg.coarse_step_m)
        f = [float(residuals(np.concatenate([np.zeros(3), si * d]), coarse).mean()) for si in s]
        i = int(np.argmin(f))
        if 0 < i < len(s) - 1:
            xi[3:] = s[i] * d
    xi = lm(xi, coarse, 3.0)
    fine = fields(cfg.truncate_px, cfg.pose_fine_blur_px)
    c = cfg.pose_cauchy_px
    xi = lm(xi, fine, c)
    if np.any(Pt):
        # the prior's weight: the residual variance of this fit (dispersion-scaled below)
        H_, g_, var_ = _stats(per_view(residuals(xi, fine, True)), c)
        P = Pt * _scale(H_, g_, var_, m)
        xi = lm(xi, fine, c)
    # statistics at the optimum
    raw_f = fields(cfg.truncate_px, 0.0, grad=False)
    r0 = residuals(np.zeros(6), raw_f)
    r1 = residuals(xi, raw_f)
    Hs, gs, naive = _stats(per_view(residuals(xi, fine, True)), c)
    scale = _scale(Hs, gs, naive, m)
    H = sum(Hs) + B.T @ P @ B
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    T = X.copy()
    T[:3, :3] = so3_exp(xi[:3]) @ X[:3, :3]
    T[:3, 3] = so3_exp(xi[:3]) @ X[:3, 3] + xi[3:]
    return PoseEdgeResult(T=T, xi=xi, cov=B @ Hinv @ B.T * scale, cost0=float(r0.mean()), cost=float(r1.mean()),
                          inliers0=float(np.mean(r0 < 1.5)), inliers=float(np.mean(r1 < 1.5)), n_points=n,
                          n_views=len(V), dispersion=scale / max(naive, 1e-12), info=B @ H @ B.T)


def edge_group_information(views: list, cam: CameraModel, X: np.ndarray, cfg: EdgeConfig,
                           n_bands: int = 0) -> np.ndarray:
    """The information (Gauss-Newton, Cauchy-weighted, unscaled: the units of ``PoseEdgeResult.info``) of
    the fine edge objective of :func:`refine_pose` at ``X`` (its points, :func:`_fit_points`), split by
    group: (n_groups, 6, 6), one group per view (``n_bands`` 0; views with too few visible edges get
    zeros) or per band of image columns (``n_bands`` bands of equal width). What each group contributes
    to the fit's information at its optimum, which a leave-one-group-out refit elsewhere cannot say."""
    c = cfg.pose_cauchy_px
    out = np.zeros((n_bands if n_bands > 0 else len(views), 6, 6))
    for i, v in enumerate(views):
        q = _fit_points(v, cam, X, cfg)
        if q is None:
            continue
        uv, _ = cam.project(q)
        s3 = _sample(view_field(v, cfg.truncate_px, cfg.pose_fine_blur_px), uv)
        J = field_jacobian(cam.K, q, s3[:, 1:])
        J *= np.sqrt(1.0 / (1.0 + (s3[:, 0] / c) ** 2))[:, None]
        if n_bands <= 0:
            out[i] = J.T @ J
            continue
        band = np.clip(np.floor(uv[:, 0] / cam.width * n_bands), 0, n_bands - 1).astype(int)
        for b in range(n_bands):
            out[b] += J[band == b].T @ J[band == b]
    return out


__all__ = ["EdgeConfig", "EdgeResult", "EdgeView", "PoseEdgeResult", "azimuth_step_rad", "edge_group_information",
           "edge_kind_inliers", "image_distance", "lidar_edges", "prepare_view", "proj_jacobian", "refine_pose",
           "refine_translation", "of_kind", "without_paint", "yaw_about_edges"]
