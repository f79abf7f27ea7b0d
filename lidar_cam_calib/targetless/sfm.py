"""Structure from motion from N frames of one moving camera (paper 001, Section 3.1; ROS-free).

Steps (OpenCV + scipy, two cores, no GPU):

1. Pixels are undistorted once (the camera model, any ROS distortion) into an
   ideal pinhole image with the same K; every later step works there.
2. SIFT on each frame (the optional dynamic mask removes features on moving
   objects), L2 matching with Lowe's ratio test and a mutual check between
   frames up to ``match_window`` apart, each pair verified by an essential
   matrix RANSAC.
3. Tracks: union-find over the verified matches; a track that meets one image
   twice is dropped. Each 3D point keeps its track (frame, pixel) list.
4. Incremental reconstruction: the best-conditioned pair (inliers x parallax)
   starts it (essential matrix, cheirality), the other frames are added one by
   one by PnP RANSAC on the tracks already triangulated, new tracks are
   triangulated from all their registered views, and a bundle adjustment
   (scipy ``least_squares``, sparse Jacobian, Huber loss) refines poses and
   points after each addition. Observations with a residual above
   ``outlier_px`` are dropped: a moving object violates the static-scene
   epipolar geometry and its tracks go here (motion consistency across SfM
   frames).
5. The gauge: the world frame is the reference camera's optical frame; the
   unit of length is arbitrary until :func:`apply_scale` sets it.
6. ``T1``: EPnP on ``pnp_points`` (paper: 45) well spread 3D-2D pairs of the
   reference frame; ``reprojection_px`` is the mean re-projection error of all
   tracks (the paper continues only below 2 px).

Densification (:func:`densify`). The paper used OpenMVS PatchMatch. A
forward-driving car puts the epipole inside the image, where rectified
two-view stereo breaks down (the rectifying homographies blow up near the
epipole and disparity goes to zero there). We therefore do not rectify: dense
DIS optical flow from the reference frame to every other frame (checked
forward-backward) gives for each pixel of a grid a track through all frames,
and each track is triangulated by the multi-view midpoint method with the
bundle-adjusted poses. A point is kept only if its re-projection is below
``dense_reproj_px`` in every view used and its largest triangulation angle is
above ``dense_min_angle_deg``: near the epipole the angle is tiny and the
point is dropped instead of being triangulated badly, while flow keeps long
baselines (frame 0 to 7) where two-view stereo would only use neighbours.
It is cheap (DIS flow is a few ms per pair) and needs no rectification.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.calibrator import cfg_field
from ..core.camera import CameraModel
from ..core.errors import CalibError
from ..core.geometry import inv_T, make_T, so3_exp, so3_log


@dataclasses.dataclass
class SfmConfig:
    n_features: int = cfg_field(3000, "SIFT features per frame", range=(200, 50000))
    ratio: float = cfg_field(0.8, "Lowe ratio test", range=(0.3, 1.0))
    match_window: int = cfg_field(3, "frames matched with each frame ahead", range=(1, 20))
    ransac_px: float = cfg_field(1.5, "RANSAC threshold of the essential matrix and PnP", range=(0.2, 20.0))
    outlier_px: float = cfg_field(3.0, "bundle-adjustment observations above this are dropped",
                                  range=(0.5, 50.0))
    min_track_angle_deg: float = cfg_field(0.5, "a sparse point needs this triangulation angle",
                                           range=(0.0, 30.0))
    init_parallax_cap_px: float = cfg_field(40.0, "initial pair score: inliers x min(median parallax, this)",
                                            range=(1.0, 10000.0))
    ba_solver: str = cfg_field("scipy", "bundle adjustment: 'schur' (exact LM normal equations, points "
                                        "eliminated) or 'scipy' (least_squares trf with LSMR steps)",
                                choices=("schur", "scipy"))
    klt_tracks: int = cfg_field(0, "ours: corners per frame tracked by pyramidal KLT through the consecutive "
                                   "frames (sub-pixel, long tracks) and added to the SIFT tracks; 0: SIFT only "
                                   "(the paper)", range=(0, 20000))
    klt_fb_px: float = cfg_field(0.3, "KLT forward-backward consistency limit", range=(0.01, 10.0))
    pnp_points: int = cfg_field(45, "3D-2D pairs of the reference frame for EPnP T1 (paper: 45)",
                                range=(6, 10000))
    dense_step_px: int = cfg_field(3, "densification grid step", range=(1, 64))
    dense_reproj_px: float = cfg_field(1.0, "dense point re-projection limit in every view", range=(0.1, 20.0))
    dense_min_angle_deg: float = cfg_field(2.0, "dense point smallest largest-triangulation angle",
                                           range=(0.0, 45.0))
    dense_fb_px: float = cfg_field(0.7, "forward-backward flow consistency limit", range=(0.05, 20.0))
    dense_flow: str = cfg_field("medium", "DIS optical flow preset of the densification",
                                choices=("ultrafast", "fast", "medium"))
    dense_max_depth: float = cfg_field(60.0, "dense points further than this many mean frame spacings "
                                             "from the reference camera are dropped",
                                       range=(1.0, 1e6))


@dataclasses.dataclass
class SfmResult:
    """``poses``: (N,4,4) T_cam_i_world (world = reference camera);
    ``points`` (P,3); ``tracks`` (P, N, 2): each point's pixel in every frame
    of the ideal (undistorted) image, NaN where not seen; ``reprojection_px``: mean over all observations;
    ``T1``: EPnP pose of the reference frame; ``unit_m``: metres per unit."""
    poses: np.ndarray
    points: np.ndarray
    tracks: np.ndarray
    reprojection_px: float
    ref: int
    T1: np.ndarray
    t1_reprojection_px: float
    n_observations: int
    unit_m: float = 1.0
    dense: np.ndarray | None = None
    dense_colour: np.ndarray | None = None
    grays: list | None = dataclasses.field(default=None, repr=False)  # the ideal grey images (densify)

    def centres(self) -> np.ndarray:
        return np.array([inv_T(T)[:3, 3] for T in self.poses])


_UNDISTORT_MAPS: dict = {}  # camera -> (mx, my): a window undistorts its images about 20 times


def ideal_image(img: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Undistorted image with the same K (identity when the camera has no distortion)."""
    if not camera.is_distorted:
        return img
    import cv2
    key = (camera.width, camera.height, camera.distortion_model, camera.K.tobytes(), camera.D.tobytes())
    maps = _UNDISTORT_MAPS.get(key)
    if maps is None:
        v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
        rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy], 1)
        d = camera.distort(rays)
        mx = (d[:, 0] * camera.fx + camera.cx).reshape(camera.height, camera.width).astype(np.float32)
        my = (d[:, 1] * camera.fy + camera.cy).reshape(camera.height, camera.width).astype(np.float32)
        if len(_UNDISTORT_MAPS) >= 4:
            _UNDISTORT_MAPS.clear()
        maps = _UNDISTORT_MAPS[key] = (mx, my)
    return cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR)


def _gray(img: np.ndarray) -> np.ndarray:
    import cv2
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _project(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    uv = Xc[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None] @ K[:2, :2].T + K[:2, 2]
    return uv, z


def triangulate_tracks(K: np.ndarray, poses: list, obs: np.ndarray, use: np.ndarray, checks: bool = True
                       ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Multi-view midpoint triangulation of tracks ``obs`` (P, n, 2) over the
    views ``use`` (P, n) bool. Returns points (P,3), the largest re-projection
    error (px, inf when behind a camera) and the largest triangulation angle (deg);
    ``checks`` False: the points alone (None, None), for a caller that measures its own errors."""
    Kinv = np.linalg.inv(K)
    P = obs.shape[0]
    # the normal equations sum_k (I - q_k q_k^T) X = sum_k (I - q_k q_k^T) c_k (q_k: unit ray, c_k: centre)
    # per track, kept as the six sums of the symmetric q q^T, the count of views and the right side, and
    # solved in closed form (the adjugate): a third faster than building and solving P 3x3 systems
    qq = np.zeros((P, 6))  # xx, yy, zz, xy, xz, yz
    b = np.zeros((P, 3))
    nv = np.zeros(P)
    cens = {}
    for k in range(obs.shape[1]):
        ok = use[:, k]
        if not np.any(ok):
            continue
        T = poses[k]
        Rw = T[:3, :3].T
        c = -Rw @ T[:3, 3]
        cens[k] = c
        M = Rw @ Kinv
        q = obs[ok, k] @ M[:, :2].T + M[:, 2]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        qq[ok] += q[:, [0, 1, 2, 0, 0, 1]] * q[:, [0, 1, 2, 1, 2, 2]]
        b[ok] += c - q * (q @ c)[:, None]
        nv[ok] += 1.0
    eps = 1e-12  # (a track seen once: its system is singular; kept finite as before)
    a00, a11, a22 = nv - qq[:, 0] + eps, nv - qq[:, 1] + eps, nv - qq[:, 2] + eps
    a01, a02, a12 = -qq[:, 3], -qq[:, 4], -qq[:, 5]
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    X = np.stack([c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2],
                  c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2],
                  c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2]], 1) / det[:, None]
    if not checks:
        return X, None, None
    err = np.zeros(P)
    rays = np.full((obs.shape[1], P, 3), np.nan)
    for k, c in cens.items():
        ok = use[:, k]
        pr, z = _project(K, poses[k], X[ok])
        e = np.where(z > 0, np.linalg.norm(pr - obs[ok, k], axis=1), np.inf)
        err[ok] = np.maximum(err[ok], e)
        r = X[ok] - c
        rays[k, ok] = r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    ang = np.zeros(P)
    ks = list(cens)
    for a_ in range(len(ks)):
        for b_ in range(a_ + 1, len(ks)):
            cosang = np.einsum("ij,ij->i", rays[ks[a_]], rays[ks[b_]])
            okp = np.isfinite(cosang)
            ang[okp] = np.maximum(ang[okp], np.degrees(np.arccos(np.clip(cosang[okp], -1, 1))))
    return X, err, ang


def _ba(K, poses, points, cam_idx, pt_idx, uv, fixed: int, max_nfev: int = 40):
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix
    n_cam, n_pt = len(poses), points.shape[0]
    x0 = np.concatenate([np.concatenate([so3_log(T[:3, :3]), T[:3, 3]]) for T in poses] + [points.ravel()])
    free_cam = np.array([c != fixed for c in range(n_cam)])

    def unpack(x):
        cams = x[:6 * n_cam].reshape(n_cam, 6)
        return cams, x[6 * n_cam:].reshape(n_pt, 3)

    def rotate(rv, X):
        th = np.linalg.norm(rv, axis=1, keepdims=True)
        k = rv / np.maximum(th, 1e-12)
        c, s = np.cos(th), np.sin(th)
        return X * c + np.cross(k, X) * s + k * np.sum(k * X, axis=1, keepdims=True) * (1 - c)

    def fun(x):
        cams, X = unpack(x)
        cams = cams.copy()
        cams[fixed] = x0[6 * fixed:6 * fixed + 6]
        Xc = rotate(cams[cam_idx, :3], X[pt_idx]) + cams[cam_idx, 3:]
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        p = Xc[:, :2] / z[:, None]
        proj = p @ K[:2, :2].T + K[:2, 2]
        return (proj - uv).ravel()

    m = uv.shape[0] * 2
    S = lil_matrix((m, x0.size), dtype=int)
    rows = np.arange(uv.shape[0])
    for k in range(6):
        ok = free_cam[cam_idx]
        S[2 * rows[ok], 6 * cam_idx[ok] + k] = 1
        S[2 * rows[ok] + 1, 6 * cam_idx[ok] + k] = 1
    for k in range(3):
        S[2 * rows, 6 * n_cam + 3 * pt_idx + k] = 1
        S[2 * rows + 1, 6 * n_cam + 3 * pt_idx + k] = 1
    res = least_squares(fun, x0, jac_sparsity=S, loss="huber", f_scale=1.0, method="trf",
                        x_scale="jac", max_nfev=max_nfev, xtol=1e-8, ftol=1e-6)
    cams, X = unpack(res.x)
    out = []
    for c in range(n_cam):
        if c == fixed:
            out.append(poses[c].copy())
        else:
            out.append(make_T(so3_exp(cams[c, :3]), cams[c, 3:]))
    r = res.fun.reshape(-1, 2)
    return out, X, np.linalg.norm(r, axis=1)


def _sum_by(idx: np.ndarray, vals: np.ndarray, n: int) -> np.ndarray:
    """``out[i] = sum of vals[idx == i]`` for i < n (np.add.at, by one bincount)."""
    m = vals.shape[0]
    k = int(np.prod(vals.shape[1:], dtype=np.int64))
    flat = (np.asarray(idx, np.int64)[:, None] * k + np.arange(k)).ravel()
    return np.bincount(flat, weights=vals.reshape(m, k).ravel(), minlength=n * k).reshape((n,) + vals.shape[1:])


def _ba_schur(K, poses, points, cam_idx, pt_idx, uv, fixed: int, max_iter: int = 40, huber_px: float = 1.0):
    """Bundle adjustment by Levenberg-Marquardt on the exact normal equations, the points eliminated
    by the Schur complement (a camera system of 6 x n_cams unknowns). Forward motion makes the
    rotation-translation coupling (bas-relief) a long flat valley that an inexact (LSMR) trust-region
    step crawls along; the exact reduced system walks it in a few steps. Huber weights by IRLS;
    camera ``fixed`` is held. Same returns as :func:`_ba`."""
    n_cam, n_pt = len(poses), points.shape[0]
    R = np.array([T[:3, :3] for T in poses])
    t = np.array([T[:3, 3] for T in poses])
    X = points.copy()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    free = np.array([c != fixed for c in range(n_cam)])
    fidx = np.full(n_cam, -1)
    fidx[free] = np.arange(int(free.sum()))
    nf = int(free.sum())

    def residuals(R, t, X):
        Xc = np.einsum("nij,nj->ni", R[cam_idx], X[pt_idx]) + t[cam_idx]
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        pr = np.stack([fx * Xc[:, 0] / z + cx, fy * Xc[:, 1] / z + cy], 1)
        return pr - uv, Xc, z

    def robust_cost(r):
        e = np.linalg.norm(r, axis=1)
        return float(np.sum(np.where(e <= huber_px, 0.5 * e ** 2, huber_px * (e - 0.5 * huber_px))))

    r, Xc, z = residuals(R, t, X)
    cost = robust_cost(r)
    lam = 1e-3
    for _ in range(max_iter):
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
        Jp = np.zeros((uv.shape[0], 2, 3))
        Jp[:, 0, 0] = fx / z
        Jp[:, 0, 2] = -fx * Xc[:, 0] / z ** 2
        Jp[:, 1, 1] = fy / z
        Jp[:, 1, 2] = -fy * Xc[:, 1] / z ** 2
        Sx = np.zeros((uv.shape[0], 3, 3))
        Sx[:, 0, 1], Sx[:, 0, 2], Sx[:, 1, 2] = Xc[:, 2], -Xc[:, 1], Xc[:, 0]
        Sx[:, 1, 0], Sx[:, 2, 0], Sx[:, 2, 1] = -Xc[:, 2], Xc[:, 1], -Xc[:, 0]   # -[Xc]x
        Jc = np.concatenate([Jp @ Sx, Jp], axis=2)                 # (m,2,6)
        Jx = Jp @ R[cam_idx]                                       # (m,2,3)
        # the per-observation blocks as batched matrix products (einsum over three operands does not
        # use BLAS and took most of the SfM's time)
        JcwT = (Jc * w[:, None, None]).transpose(0, 2, 1)          # (m,6,2)
        JxwT = (Jx * w[:, None, None]).transpose(0, 2, 1)          # (m,3,2)
        U = JcwT @ Jc
        Wm = JcwT @ Jx                                             # (m,6,3)
        Vm = JxwT @ Jx
        gc = -(JcwT @ r[:, :, None])[:, :, 0]
        gx = -(JxwT @ r[:, :, None])[:, :, 0]
        V = _sum_by(pt_idx, Vm, n_pt)
        Gx = _sum_by(pt_idx, gx, n_pt)
        Uc = _sum_by(cam_idx, U, n_cam)
        Gc = _sum_by(cam_idx, gc, n_cam)
        Wp = np.zeros((n_pt, n_cam, 6, 3))
        Wp[pt_idx, cam_idx] = Wm
        Wflat = Wp.reshape(n_pt, n_cam * 6, 3)                     # (p, 6c, 3)
        Wmat = Wflat.transpose(1, 0, 2).reshape(n_cam * 6, n_pt * 3)
        improved, rel = False, 0.0
        for _try in range(8):
            Vd = V + lam * np.einsum("nii->ni", V)[:, :, None] * np.eye(3)[None] + 1e-9 * np.eye(3)[None]
            Vinv = np.linalg.inv(Vd)
            Y = Wflat @ Vinv                                         # (p, 6c, 3)
            Ymat = Y.transpose(1, 0, 2).reshape(n_cam * 6, n_pt * 3)
            Sblk = -(Ymat @ Wmat.T).reshape(n_cam, 6, n_cam, 6).transpose(0, 2, 1, 3)  # (c,c,6,6)
            Ud = Uc + lam * np.einsum("nii->ni", Uc)[:, :, None] * np.eye(6)[None] + 1e-9 * np.eye(6)[None]
            for c in range(n_cam):
                Sblk[c, c] += Ud[c]
            rhs = Gc - (Ymat @ Gx.ravel()).reshape(n_cam, 6)
            S = Sblk[free][:, free].transpose(0, 2, 1, 3).reshape(6 * nf, 6 * nf)
            try:
                dc_f = np.linalg.solve(S, rhs[free].ravel()).reshape(nf, 6)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dc = np.zeros((n_cam, 6))
            dc[free] = dc_f
            dx = (Vinv @ (Gx - (dc.ravel() @ Wmat).reshape(n_pt, 3))[:, :, None])[:, :, 0]
            Rn = np.array([so3_exp(dc[c, :3]) @ R[c] for c in range(n_cam)])
            tn = np.array([so3_exp(dc[c, :3]) @ t[c] + dc[c, 3:] for c in range(n_cam)])
            Xn = X + dx
            rn, Xcn, zn = residuals(Rn, tn, Xn)
            cn = robust_cost(rn)
            if np.isfinite(cn) and cn < cost:
                rel = (cost - cn) / max(cost, 1e-12)
                R, t, X, r, Xc, z, cost = Rn, tn, Xn, rn, Xcn, zn, cn
                lam = max(lam / 5, 1e-7)
                improved = True
                break
            lam *= 10
        if not improved or rel < 1e-7:
            break
    out = [make_T(R[c], t[c]) if c != fixed else poses[c].copy() for c in range(n_cam)]
    return out, X, np.linalg.norm(r, axis=1)


def run_sfm(images: list, camera: CameraModel, masks: list | None = None, ref: int = 0,
            cfg: SfmConfig | None = None) -> SfmResult:
    """Sparse SfM of ``images`` (list of HxW[x3] uint8); ``masks``: optional list
    of HxW bool, True = dynamic (no features there). Raises :class:`CalibError`."""
    import cv2
    cfg = cfg or SfmConfig()
    n = len(images)
    if n < 3:
        raise CalibError(f"SfM needs at least 3 frames, got {n}")
    K = camera.K.copy()
    # OpenCV's RANSAC (essential matrix, PnP) draws from one process-wide generator: seed it so that a
    # window gives the same result whatever the process computed before
    cv2.setRNGSeed(0)
    sift = cv2.SIFT_create(nfeatures=cfg.n_features)
    kps, descs, grays = [], [], []
    for i, im in enumerate(images):
        g = _gray(ideal_image(im, camera))
        grays.append(g)
        m = None
        if masks is not None and masks[i] is not None:
            m = (~np.asarray(masks[i], bool)).astype(np.uint8) * 255
        kp, de = sift.detectAndCompute(g, m)
        if de is None or len(kp) < 50:
            raise CalibError(f"SfM: frame {i} has only {0 if de is None else len(kp)} SIFT features; the "
                             "image is too dark, blurred or textureless")
        kps.append(np.array([k.pt for k in kp], np.float64))
        descs.append(de)
    offs = np.concatenate([[0], np.cumsum([k.shape[0] for k in kps])])
    bf = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 48})
    pair_inl = {}
    ua, ub = [], []
    for i in range(n):
        for j in range(i + 1, min(n, i + 1 + cfg.match_window)):
            m12 = bf.knnMatch(descs[i], descs[j], k=2)
            m21 = bf.match(descs[j], descs[i])
            back = np.full(kps[j].shape[0], -1)
            for mm in m21:
                back[mm.queryIdx] = mm.trainIdx
            qi, tj = [], []
            for mm in m12:
                if (len(mm) == 2 and mm[0].distance < cfg.ratio * mm[1].distance
                        and back[mm[0].trainIdx] == mm[0].queryIdx):
                    qi.append(mm[0].queryIdx)
                    tj.append(mm[0].trainIdx)
            if len(qi) < 30:
                continue
            qi, tj = np.array(qi), np.array(tj)
            E, inl = cv2.findEssentialMat(kps[i][qi], kps[j][tj], K, cv2.RANSAC, 0.999, cfg.ransac_px)
            if E is None:
                continue
            inl = inl.ravel().astype(bool)
            if inl.sum() < 30:
                continue
            qi, tj = qi[inl], tj[inl]
            par = np.median(np.linalg.norm(kps[i][qi] - kps[j][tj], axis=1))
            pair_inl[(i, j)] = (qi, tj, E, par)
            ua.append(offs[i] + qi)
            ub.append(offs[j] + tj)
    if not pair_inl:
        raise CalibError("SfM: no two frames share enough verified SIFT matches; the frames are too far "
                         "apart or the scene is textureless")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    ea, eb = np.concatenate(ua), np.concatenate(ub)
    nn = int(offs[-1])
    graph = coo_matrix((np.ones(ea.size), (ea, eb)), shape=(nn, nn))
    _, comp = connected_components(graph, directed=False)
    used = np.unique(np.concatenate([ea, eb]))
    roots = comp[used]
    # tracks: root -> list of nodes
    order = np.argsort(roots, kind="stable")
    r_sorted, n_sorted = roots[order], used[order]
    splits = np.nonzero(np.diff(r_sorted))[0] + 1
    groups = np.split(n_sorted, splits)
    img_of = np.searchsorted(offs, np.arange(offs[-1]), side="right") - 1
    obs_list = []
    for gnodes in groups:
        if gnodes.size < 2:
            continue
        fr = img_of[gnodes]
        if np.unique(fr).size != fr.size:
            continue
        o = np.full((n, 2), np.nan)
        o[fr] = np.array([kps[f][nd - offs[f]] for f, nd in zip(fr, gnodes)])
        obs_list.append(o)
    if cfg.klt_tracks > 0:
        obs_list.extend(klt_tracks(grays, masks, cfg))
    if len(obs_list) < 50:
        raise CalibError(f"SfM: only {len(obs_list)} feature tracks; need at least 50")
    obs = np.array(obs_list)  # (n_tracks, n_frames, 2), NaN = not seen
    seen = np.isfinite(obs[:, :, 0])
    # initial pair: most inliers x parallax (capped)
    best = max(pair_inl.items(), key=lambda kv: kv[1][0].size * min(kv[1][3], cfg.init_parallax_cap_px))
    (i0, j0), (qi, tj, E, par) = best
    if par < 2.0:
        raise CalibError(f"SfM: the camera barely moved (median parallax {par:.1f} px between the best "
                         "frame pair); drive faster or keep frames further apart")
    _, R, t, _ = cv2.recoverPose(E, kps[i0][qi], kps[j0][tj], K)
    poses = [None] * n
    poses[i0] = np.eye(4)
    poses[j0] = make_T(R, t.ravel())
    n_tr = obs.shape[0]
    X = np.full((n_tr, 3), np.nan)

    def registered():
        return np.array([p is not None for p in poses])

    def triangulate_new():
        reg = registered()
        cand = ~np.isfinite(X[:, 0]) & ((seen & reg[None]).sum(1) >= 2)
        if not np.any(cand):
            return
        use = seen[cand] & reg[None]
        P, err, ang = triangulate_tracks(K, poses, obs[cand], use)
        ok = (err <= cfg.outlier_px) & (ang >= cfg.min_track_angle_deg)
        idx = np.nonzero(cand)[0]
        X[idx[ok]] = P[ok]

    def observations():
        reg = registered()
        m = seen & reg[None] & np.isfinite(X[:, :1])
        pi, ci = np.nonzero(m)
        return ci, pi, obs[pi, ci]

    def bundle(max_nfev=30):
        ci, pi, uvs = observations()
        reg = [k for k in range(n) if poses[k] is not None]
        remap = np.full(n, -1)
        remap[reg] = np.arange(len(reg))
        live = np.unique(pi)
        pmap = np.full(n_tr, -1)
        pmap[live] = np.arange(live.size)
        if cfg.ba_solver == "schur":
            new_p, newX, res = _ba_schur(K, [poses[k] for k in reg], X[live], remap[ci],
                                         pmap[pi], uvs, fixed=int(remap[i0]), max_iter=max_nfev)
        else:
            new_p, newX, res = _ba(K, [poses[k] for k in reg], X[live], remap[ci],
                                   pmap[pi], uvs, fixed=int(remap[i0]), max_nfev=max_nfev)
        for k, T in zip(reg, new_p):
            poses[k] = T
        X[live] = newX
        bad_pts = np.unique(pi[res > cfg.outlier_px])
        X[bad_pts] = np.nan  # an outlier observation discards its point (moving objects)
        return res[~np.isin(pi, bad_pts)]

    triangulate_new()
    bundle(15)
    while not np.all(registered()):
        reg = registered()
        have = np.isfinite(X[:, 0])
        counts = np.where(reg, -1, (seen & have[:, None]).sum(0))
        k = int(np.argmax(counts))
        sel = seen[:, k] & have
        P3, P2 = X[sel], obs[sel, k]
        if P3.shape[0] < 12:
            raise CalibError(f"SfM: frame {k} sees only {P3.shape[0]} reconstructed points; the frames do "
                             "not overlap enough")
        ok, rv, tv, inl = cv2.solvePnPRansac(P3, P2, K, None, iterationsCount=300,
                                             reprojectionError=cfg.ransac_px * 2, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < 10:
            raise CalibError(f"SfM: frame {k} could not be registered (PnP RANSAC failed)")
        inl = inl.ravel()
        rv, tv = cv2.solvePnPRefineLM(P3[inl], P2[inl], K, None, rv, tv)
        poses[k] = make_T(cv2.Rodrigues(rv)[0], tv.ravel())
        triangulate_new()
        bundle(8)
    triangulate_new()
    bundle(30)
    res = bundle(30)
    # gauge: world = reference camera frame; unit = mean spacing of consecutive centres
    G = poses[ref].copy()
    Ginv = inv_T(G)
    poses = [T @ Ginv for T in poses]
    good = np.isfinite(X[:, 0])
    Xw = X[good] @ G[:3, :3].T + G[:3, 3]
    cen = np.array([inv_T(T)[:3, 3] for T in poses])
    unit = float(np.mean(np.linalg.norm(np.diff(cen, axis=0), axis=1)))
    if unit <= 0:
        raise CalibError("SfM: the camera did not move")
    poses = [make_T(T[:3, :3], T[:3, 3] / unit) for T in poses]
    Xw /= unit
    trk = obs[good]
    # T1: EPnP on M well-spread points of the reference frame
    inref = np.isfinite(trk[:, ref, 0])
    p3, p2 = Xw[inref], trk[inref, ref]
    if p3.shape[0] < 6:
        raise CalibError(f"SfM: the reference frame sees only {p3.shape[0]} reconstructed points")
    sel = _spread(p2, cfg.pnp_points)
    ok, rv, tv = cv2.solvePnP(p3[sel], p2[sel], K, None, flags=cv2.SOLVEPNP_EPNP)
    T1 = make_T(cv2.Rodrigues(rv)[0], tv.ravel()) if ok else np.eye(4)
    pr, _ = _project(K, T1, p3)
    t1_err = float(np.mean(np.linalg.norm(pr - p2, axis=1)))
    return SfmResult(np.array(poses), Xw, trk, float(np.mean(res)), ref, T1, t1_err, int(res.size), grays=grays)


def klt_tracks(grays: list, masks: list | None, cfg: SfmConfig) -> list:
    """Corner tracks (list of (n_frames, 2) arrays, NaN where not seen): corners
    detected in every frame away from live tracks, followed frame to frame by
    pyramidal Lucas-Kanade with a forward-backward check of ``klt_fb_px``."""
    import cv2
    n = len(grays)
    H, W = grays[0].shape
    out = []
    live = []  # (track array, current point)
    lk = {"winSize": (15, 15), "maxLevel": 3,
          "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
    for k in range(n):
        if k > 0 and live:
            p0 = np.array([c for _, c in live], np.float32).reshape(-1, 1, 2)
            p1, st, _ = cv2.calcOpticalFlowPyrLK(grays[k - 1], grays[k], p0, None, **lk)
            pb, st2, _ = cv2.calcOpticalFlowPyrLK(grays[k], grays[k - 1], p1, None, **lk)
            fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
            p1 = p1.reshape(-1, 2)
            ok = (st.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.klt_fb_px) & \
                (p1[:, 0] >= 0) & (p1[:, 0] < W - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < H - 1)
            if masks is not None and masks[k] is not None:
                mk = np.asarray(masks[k], bool)
                ok[ok] &= ~mk[p1[ok, 1].astype(int), p1[ok, 0].astype(int)]
            nl = []
            for (tr, _), good, q in zip(live, ok, p1):
                if good:
                    tr[k] = q
                    nl.append((tr, q.astype(np.float64)))
                else:
                    out.append(tr)
            live = nl
        if k == n - 1:
            break
        m = np.full((H, W), 255, np.uint8)
        if masks is not None and masks[k] is not None:
            m[np.asarray(masks[k], bool)] = 0
        for _, c in live:
            cv2.circle(m, (int(c[0]), int(c[1])), 6, 0, -1)
        want = cfg.klt_tracks - len(live)
        if want > 20:
            pts = cv2.goodFeaturesToTrack(grays[k], want, 0.005, 6, mask=m, blockSize=5)
            if pts is not None:
                pts = cv2.cornerSubPix(grays[k], pts.astype(np.float32), (3, 3), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
                for q in pts.reshape(-1, 2):
                    tr = np.full((n, 2), np.nan)
                    tr[k] = q
                    live.append((tr, q.astype(np.float64)))
    out.extend(tr for tr, _ in live)
    return [t for t in out if np.isfinite(t[:, 0]).sum() >= 3]


def _spread(uv: np.ndarray, m: int) -> np.ndarray:
    """Indices of up to m points spread over the image (farthest-point sampling)."""
    n = uv.shape[0]
    if n <= m:
        return np.arange(n)
    sel = [int(np.argmin(np.linalg.norm(uv - uv.mean(0), axis=1)))]
    d = np.linalg.norm(uv - uv[sel[0]], axis=1)
    for _ in range(m - 1):
        k = int(np.argmax(d))
        sel.append(k)
        d = np.minimum(d, np.linalg.norm(uv - uv[k], axis=1))
    return np.array(sel)


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x0 = np.clip(np.floor(x).astype(int), 0, img.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, img.shape[0] - 2)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    # one flat gather per corner (a 2-D fancy index over (H,W,2) is several times slower)
    w = img.shape[1]
    flat = img.reshape(-1, img.shape[2])
    i = y0 * w + x0
    v = (np.take(flat, i, axis=0) * (1 - ax) * (1 - ay) + np.take(flat, i + 1, axis=0) * ax * (1 - ay)
         + np.take(flat, i + w, axis=0) * (1 - ax) * ay + np.take(flat, i + w + 1, axis=0) * ax * ay)
    return v[:, 0], v[:, 1]


def apply_scale(res: SfmResult, metres_per_unit: float) -> SfmResult:
    """The same reconstruction in metres (poses, points, dense, T1)."""
    s = float(metres_per_unit)
    poses = np.array([make_T(T[:3, :3], T[:3, 3] * s) for T in res.poses])
    T1 = make_T(res.T1[:3, :3], res.T1[:3, 3] * s)
    return dataclasses.replace(res, poses=poses, points=res.points * s, T1=T1, unit_m=res.unit_m * s,
                               dense=None if res.dense is None else res.dense * s)


def densify(images: list, camera: CameraModel, res: SfmResult, masks: list | None = None,
            cfg: SfmConfig | None = None, refs: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dense points (D,3) in the world (reference camera) frame and their BGR
    colours, by multi-view triangulation of dense optical-flow tracks from each
    frame in ``refs`` (default all) (see the module docstring for why not rectified stereo)."""
    import cv2
    cfg = cfg or SfmConfig()
    gi = res.grays if res.grays is not None and len(res.grays) == len(images) else \
        [_gray(ideal_image(im, camera)) for im in images]
    H, W = gi[0].shape
    n = len(images)
    dis = cv2.DISOpticalFlow_create({"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                                     "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                                     "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[cfg.dense_flow])
    fwd = [dis.calc(gi[k], gi[k + 1], None) for k in range(n - 1)]
    bwd = [dis.calc(gi[k + 1], gi[k], None) for k in range(n - 1)]
    refs = range(n) if refs is None else refs
    pts, cols = [], []
    for r in refs:
        p, c = _densify_from(images, camera, res, masks, cfg, r, gi, fwd, bwd)
        pts.append(p)
        cols.append(c)
    return np.concatenate(pts), np.concatenate(cols)


def depth_sigma(points: np.ndarray, centres: np.ndarray, f_px: float, sigma_px: float) -> np.ndarray:
    """First-order 1-sigma position error along the viewing ray of triangulated points:
    ``range * sigma_px / (f * sin(largest triangulation angle))`` over the given camera centres."""
    best = np.zeros(points.shape[0])
    rays = []
    for c in centres:
        r = points - c
        rays.append(r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12))
    for a in range(len(rays)):
        for b in range(a + 1, len(rays)):
            s = np.linalg.norm(np.cross(rays[a], rays[b]), axis=1)
            best = np.maximum(best, s)
    rng = np.linalg.norm(points - centres[0], axis=1)
    return rng * sigma_px / (f_px * np.maximum(best, 1e-6))


def _densify_from(images, camera, res, masks, cfg, ref, gi, fwd, bwd):
    K = camera.K
    H, W = gi[ref].shape
    n = len(images)
    st = cfg.dense_step_px
    v, u = np.mgrid[st // 2:H:st, st // 2:W:st]
    u, v = u.ravel().astype(np.float64), v.ravel().astype(np.float64)
    keep = np.ones(u.size, bool)
    if masks is not None and masks[ref] is not None:
        keep &= ~np.asarray(masks[ref], bool)[v.astype(int), u.astype(int)]
    views_uv = np.full((n, u.size, 2), np.nan)
    views_uv[ref] = np.stack([u, v], 1)
    # chain consecutive flows outwards from the reference frame (each link checked forward-backward):
    # direct flow to a frame 7 steps away fails on half the pixels, short links do not
    for direction in (1, -1):
        cu, cv = u.copy(), v.copy()
        alive = keep.copy()
        k = ref
        while 0 <= k + direction < n and np.any(alive):
            k2 = k + direction
            f, b = (fwd[k], bwd[k]) if direction > 0 else (bwd[k2], fwd[k2])
            fx, fy = _bilinear(f, cu, cv)
            nu, nv = cu + fx, cv + fy
            inside = (nu >= 0) & (nu < W - 1) & (nv >= 0) & (nv < H - 1)
            bx, by = _bilinear(b, np.where(inside, nu, 0), np.where(inside, nv, 0))
            fb = np.hypot(nu + bx - cu, nv + by - cv)
            alive &= inside & (fb < cfg.dense_fb_px)
            if masks is not None and masks[k2] is not None:
                mk = np.asarray(masks[k2], bool)
                alive[alive] &= ~mk[nv[alive].astype(int), nu[alive].astype(int)]
            cu, cv = np.where(alive, nu, 0.0), np.where(alive, nv, 0.0)
            views_uv[k2, alive] = np.stack([cu[alive], cv[alive]], 1)
            k = k2
    # multi-view midpoint over all flow views; drop views that disagree, re-triangulate once
    obs = np.transpose(views_uv, (1, 0, 2))
    use = np.isfinite(obs[:, :, 0]) & keep[:, None]
    good = use.sum(1) >= 3
    Xd = np.full((u.size, 3), np.nan)
    for _ in range(2):
        Xd[good] = triangulate_tracks(K, list(res.poses), obs[good], use[good], checks=False)[0]
        for k in range(n):
            ok = good & use[:, k]
            pr, z = _project(K, res.poses[k], Xd[ok])
            e = np.where(z > 0, np.linalg.norm(pr - obs[ok, k], axis=1), np.inf)
            idx = np.nonzero(ok)[0]
            use[idx[e > cfg.dense_reproj_px], k] = False
        good &= use[:, ref] & (use.sum(1) >= 3)
    Xd[good], err, ang = triangulate_tracks(K, list(res.poses), obs[good], use[good])
    gi_ = np.nonzero(good)[0]
    good[gi_[(err > cfg.dense_reproj_px) | (ang < cfg.dense_min_angle_deg)]] = False
    cens = res.centres()
    spacing = float(np.mean(np.linalg.norm(np.diff(cens, axis=0), axis=1)))
    depth = np.linalg.norm(np.where(good[:, None], Xd, 0.0) - cens[ref], axis=1)
    good &= depth <= cfg.dense_max_depth * spacing
    img = images[ref] if images[ref].ndim == 3 else np.repeat(images[ref][:, :, None], 3, 2)
    col = ideal_image(img, camera)[v[good].astype(int), u[good].astype(int)]
    return Xd[good], col


__all__ = ["SfmConfig", "SfmResult", "apply_scale", "densify", "depth_sigma", "ideal_image", "klt_tracks", "run_sfm"]
