"""Solvers of the board method (ROS-free): epnp, kabsch_3d3d, paper, ours.

All solvers take the same :class:`Observation` list (one per board
placement: the LiDAR board and the corners in every camera that saw it,
already put into one correspondence by :func:`resolve_symmetry`).

* ``epnp``: EPnP on the virtual corners of every placement (paper step 23),
  refined by Levenberg-Marquardt on the reprojection.
* ``kabsch_3d3d``: the corners in the camera frame (per-image PnP) registered
  to the virtual corners (Dhall et al., the paper's reference [41]).
* ``paper``: Algorithm 1 as published: every virtual corner a free 3D point,
  reprojection residuals only, all cameras in one problem, started from EPnP.
  Points seen by one camera can slide along their rays (DESIGN "Known traps").
* ``ours``: one joint problem of every camera's extrinsic and one board pose
  per placement with the known board geometry, keeping the LiDAR measurement
  in it: each board point on the board plane (range noise), each ring end on
  the board outline (azimuth quantisation, plus one beam-divergence shrink per
  placement), each image corner at its projection (pixel noise). The noise of
  each group is estimated from the data (variance components), the gauge is
  the LiDAR frame (no free gauge), the Jacobian is sparse (finite differences
  grouped by its structure), and the covariance of each extrinsic comes from
  the final information matrix.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.camera import CameraModel
from ..core.errors import CalibError
from ..core.geometry import inv_T, make_T, so3_exp, so3_log
from .frame import BoardGeometry
from .image_corners import rotate_180
from .lidar_board import LidarBoard

SOLVERS = ("epnp", "kabsch_3d3d", "paper", "ours")
_RZ = np.diag([-1.0, -1.0, 1.0, 1.0])


class SolveError(CalibError):
    """A solver could not produce an extrinsic; the message says why."""


@dataclasses.dataclass
class Observation:
    """One board placement: the LiDAR board and the image corners per camera."""
    stamp_s: float
    lidar: LidarBoard
    images: dict  # camera name -> ImageCorners


# ----------------------------------------------------------------------------
# small maths
# ----------------------------------------------------------------------------
def _exp_batch(w: np.ndarray) -> np.ndarray:
    """(N,3) rotation vectors -> (N,3,3)."""
    w = np.asarray(w, dtype=float).reshape(-1, 3)
    th = np.linalg.norm(w, axis=1)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(ths) / ths)
    b = np.where(small, 0.5, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _rot_dist_deg(R1, R2) -> float:
    return math.degrees(float(np.linalg.norm(so3_log(R1 @ R2.T))))


def _dist(T1, T2) -> tuple[float, float]:
    return _rot_dist_deg(T1[:3, :3], T2[:3, :3]), float(np.linalg.norm(T1[:3, 3] - T2[:3, 3]))


def kabsch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """T with B ~ T @ A (least squares rigid, no scale)."""
    ca, cb = A.mean(0), B.mean(0)
    H = (A - ca).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return make_T(R, cb - R @ ca)


def _pnp_normalised(P: np.ndarray, xn: np.ndarray, refine: bool = True) -> np.ndarray:
    import cv2
    P = np.ascontiguousarray(P, dtype=np.float64).reshape(-1, 1, 3)
    x = np.ascontiguousarray(xn, dtype=np.float64).reshape(-1, 1, 2)
    # one placement: every point on one plane, where EPnP is unstable (a 1e-13 change of the
    # input flipped it to a 2 m error); IPPE is the planar solver
    sv = np.linalg.svd(P.reshape(-1, 3) - P.reshape(-1, 3).mean(0), compute_uv=False)
    planar = sv[2] < 1e-3 * sv[0]
    ok, rv, tv = cv2.solvePnP(P, x, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_EPNP)
    if not ok:
        raise SolveError("EPnP failed (degenerate corner set)")
    if refine:
        rv, tv = cv2.solvePnPRefineLM(P, x, np.eye(3), None, rv, tv)
    return make_T(cv2.Rodrigues(rv)[0], tv.ravel())


def cameras_seen(obs: list) -> list:
    names = []
    for o in obs:
        for c in o.images:
            if c not in names:
                names.append(c)
    return names


# ----------------------------------------------------------------------------
# correspondence across the board's symmetry
# ----------------------------------------------------------------------------
def resolve_symmetry(obs: list, board: BoardGeometry, min_frames: int = 2,
                     tol_deg: float = 6.0, tol_m: float = 0.3) -> tuple[list, dict, dict]:
    """Put every image's corner order into the LiDAR board's order.

    Per camera and placement there are two assignments (the 180 deg turn
    about the board normal); each gives an extrinsic ``T_cb @ inv(T_lb)``.
    The true one agrees across placements: the candidate with most
    placements agreeing (within ``tol_deg`` / ``tol_m``) is the consensus, each
    placement keeps its assignment nearer to it, and placements whose nearer
    one is still far (moved board, wrong detection) are dropped for that
    camera. Returns (new observations, {cam: consensus T_camera_lidar},
    {cam: reason} for cameras that cannot be resolved)."""
    out = [Observation(o.stamp_s, o.lidar, dict(o.images)) for o in obs]
    init, refused = {}, {}
    fixed = set()  # placements whose LiDAR alternative is already chosen (by an earlier camera)
    names = sorted(cameras_seen(obs), key=lambda c: -sum(c in o.images for o in obs))
    for c in names:
        idx = [i for i, o in enumerate(out) if c in o.images]
        if len(idx) < min_frames:
            refused[c] = (f"camera {c} saw the board in {len(idx)} placement(s) together with the LiDAR; "
                          f"at least {min_frames} are needed to resolve the board's 180 deg symmetry")
            for i in idx:
                del out[i].images[c]
            continue
        cands = []  # per placement: [(T_camera_lidar, flip, lidar alternative index)]
        for i in idx:
            T_cb = out[i].images[c].T_camera_board
            lbs = [(out[i].lidar.T_lidar_board, out[i].lidar.shrink_m)]
            if i not in fixed:
                lbs += list(out[i].lidar.alternatives)
            row = []
            for a, (T_lb, _g) in enumerate(lbs):
                T_bl = inv_T(T_lb)
                row += [(T_cb @ T_bl, False, a), (T_cb @ _RZ @ T_bl, True, a)]
            cands.append(row)

        def score(X, Y):
            d = _dist(X, Y)
            return d, d[0] / tol_deg + d[1] / tol_m
        best, best_score = None, (-1, 0.0)
        for row in cands:
            for X, _f, _a in row:
                cnt, tot = 0, 0.0
                for other in cands:
                    d, sc = min((score(X, Y) for Y, _f2, _a2 in other), key=lambda z: z[1])
                    if d[0] < tol_deg and d[1] < tol_m:
                        cnt += 1
                        tot += sc
                if (cnt, -tot) > (best_score[0], -best_score[1]):
                    best, best_score = X, (cnt, tot)
        if best_score[0] < max(2, min_frames):
            refused[c] = (f"camera {c}: its {len(idx)} placements disagree with the LiDAR about the board "
                          "pose (moving board or wrong detections): no consistent extrinsic")
            for i in idx:
                del out[i].images[c]
            continue
        for i, row in zip(idx, cands):
            (d, _sc), flip, alt = min(((score(best, Y), f, a) for Y, f, a in row), key=lambda z: z[0][1])
            if d[0] > 2 * tol_deg or d[1] > 2 * tol_m:
                del out[i].images[c]
                continue
            if alt > 0:
                T_lb, g = out[i].lidar.alternatives[alt - 1]
                out[i].lidar = out[i].lidar.with_pose(T_lb, g)
            fixed.add(i)
            if flip:
                out[i].images[c] = rotate_180(out[i].images[c], board)
        init[c] = best
    return [o for o in out if o.images], init, refused


def plane_only_start(obs: list, board: BoardGeometry) -> tuple[list, dict]:
    """Start for a LiDAR that gives the board plane only (no ring ends): per camera the
    extrinsic from the plane correspondences (rotation by Kabsch on the normals, translation
    from n_c . t = d_l - d_c), and each placement's board pose taken from the camera through it
    (so no in-plane symmetry has to be resolved). Returns (observations, {cam: T})."""
    init = {}
    for c in cameras_seen(obs):
        nl, nc, dl, dc = [], [], [], []
        for o in obs:
            if c not in o.images:
                continue
            T = o.images[c].T_camera_board
            nc.append(T[:3, 2])
            dc.append(-float(T[:3, 2] @ T[:3, 3]))
            n = o.lidar.normal
            nl.append(n)
            dl.append(-float(n @ o.lidar.centre))
        if len(nl) < 3:
            continue
        nl, nc = np.array(nl), np.array(nc)
        H = nl.T @ nc
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
        R = Vt.T @ D @ U.T
        t = np.linalg.lstsq(nc, np.array(dl) - np.array(dc), rcond=None)[0]
        init[c] = make_T(R, t)
    out = []
    for o in obs:
        cs = [c for c in o.images if c in init]
        if not cs:
            continue
        T_lb = inv_T(init[cs[0]]) @ o.images[cs[0]].T_camera_board
        out.append(Observation(o.stamp_s, o.lidar.with_pose(T_lb, 0.0), {c: o.images[c] for c in cs}))
    return out, init


# ----------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------
def normalized_plane_error_mm(P_cam: np.ndarray, xn: np.ndarray) -> float:
    """Paper eq. 24-25: mean distance on the normalised plane (z = 1 m), in mm."""
    q = P_cam[:, :2] / P_cam[:, 2:3]
    return float(1000 * np.mean(np.linalg.norm(q - xn, axis=1)))


def camera_metrics(obs: list, cam: str, T: np.ndarray, model: CameraModel, board: BoardGeometry,
                   points: dict | None = None) -> dict:
    """Reprojection (px RMS) and eq. 24-25 of the virtual corners through ``T``;
    ``points``: {obs index: (n,3) LiDAR-frame corners} to use instead (the
    paper's own optimised points or our fitted board)."""
    P_all, xn_all, uv_all = [], [], []
    for i, o in enumerate(obs):
        if cam not in o.images:
            continue
        ic = o.images[cam]
        P = points[i] if points is not None and i in points else o.lidar.virtual_corners(board)
        P_all.append(P @ T[:3, :3].T + T[:3, 3])
        xn_all.append(ic.xn)
        uv_all.append(ic.uv)
    if not P_all:
        return {"reprojection_px": math.nan, "normalized_plane_error_mm": math.nan, "frames": 0}
    P, xn, uv = np.concatenate(P_all), np.concatenate(xn_all), np.concatenate(uv_all)
    uvp, _ = model.project(P)
    return {"reprojection_px": float(np.sqrt(np.mean(np.sum((uvp - uv) ** 2, axis=1)))),
            "normalized_plane_error_mm": normalized_plane_error_mm(P, xn), "frames": len(P_all)}


# ----------------------------------------------------------------------------
# epnp and kabsch
# ----------------------------------------------------------------------------
def solve_epnp(obs: list, board: BoardGeometry) -> dict:
    """{cam: T_camera_lidar} from EPnP (+ LM) on all virtual corners."""
    out = {}
    for c in cameras_seen(obs):
        P = [o.lidar.virtual_corners(board) for o in obs if c in o.images]
        x = [o.images[c].xn for o in obs if c in o.images]
        out[c] = _pnp_normalised(np.concatenate(P), np.concatenate(x))
    return out


def solve_kabsch(obs: list, board: BoardGeometry) -> dict:
    """{cam: T_camera_lidar}: 3D-3D registration of camera-frame corners (PnP per image)
    to the virtual corners."""
    out = {}
    Pb = board.inner_corners_board()
    for c in cameras_seen(obs):
        A = [o.lidar.virtual_corners(board) for o in obs if c in o.images]
        B = [Pb @ o.images[c].T_camera_board[:3, :3].T + o.images[c].T_camera_board[:3, 3]
             for o in obs if c in o.images]
        out[c] = kabsch(np.concatenate(A), np.concatenate(B))
    return out


# ----------------------------------------------------------------------------
# grouped finite-difference Jacobian + Levenberg-Marquardt on a manifold
# ----------------------------------------------------------------------------
def _grouped_jacobian(fun, n_params: int, groups: list, r0: np.ndarray, h: float = 1e-6):
    """Sparse Jacobian by finite differences. ``groups``: list of
    (delta vector (n_params,), rows (R,), cols (R,)): perturbing the group's
    parameters together changes row ``rows[i]`` through parameter ``cols[i]`` only."""
    from scipy.sparse import csr_matrix
    R, C, V = [], [], []
    for delta, rows, cols in groups:
        r1 = fun(delta * h)
        R.append(rows)
        C.append(cols)
        V.append((r1[rows] - r0[rows]) / h)
    R, C, V = np.concatenate(R), np.concatenate(C), np.concatenate(V)
    return csr_matrix((V, (R, C)), shape=(len(r0), n_params))


def _blocks(H, nA: int, bs: int):
    """Split a sparse symmetric H = [[A, B], [B^T, D]] with D block-diagonal
    (blocks of ``bs``) into dense A (nA,nA), Bf (F,nA,bs), D (F,bs,bs)."""
    n = H.shape[0]
    F = (n - nA) // bs
    A = H[:nA, :nA].toarray()
    Bf = H[:nA, nA:].toarray().reshape(nA, F, bs).transpose(1, 0, 2)
    Dc = H[nA:, nA:].tocoo()
    keep = (Dc.row // bs) == (Dc.col // bs)
    D = np.zeros((F, bs, bs))
    np.add.at(D, (Dc.row[keep] // bs, Dc.row[keep] % bs, Dc.col[keep] % bs), Dc.data[keep])
    return A, Bf, D


def _inv_small(M: np.ndarray) -> np.ndarray:
    """Inverse of (..., k, k) symmetric blocks, pseudo-inverse where singular."""
    scale = np.maximum(np.abs(np.diagonal(M, axis1=-2, axis2=-1)).max(axis=-1), 1e-300)
    reg = M + (1e-13 * scale)[..., None, None] * np.eye(M.shape[-1])
    try:
        return np.linalg.inv(reg)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(reg)


def _schur(H, nA: int, bs: int):
    """(S^-1, Bf, Dinv): what solving with and inverting H needs (no large dense LAPACK)."""
    A, Bf, D = _blocks(H, nA, bs)
    Dinv = _inv_small(D)
    BD = Bf @ Dinv
    S = A - np.einsum("fab,fcb->ac", BD, Bf)
    return _inv_small(S), Bf, Dinv


def _block_solve(H, g, nA: int, bs: int, damp: float):
    from scipy.sparse import diags
    d = H.diagonal()
    Hd = (H + diags(damp * d + 1e-12 * max(float(d.max()), 1.0))).tocsr()
    Sinv, Bf, Dinv = _schur(Hd, nA, bs)
    F = Bf.shape[0]
    gA, gF = g[:nA], g[nA:].reshape(F, bs)
    BD = Bf @ Dinv
    xA = Sinv @ (gA - np.einsum("fab,fb->a", BD, gF))
    xF = np.einsum("fab,fb->fa", Dinv, gF - np.einsum("fab,a->fb", Bf, xA))
    return np.concatenate([xA, xF.ravel()])


def _inverse_blocks(H, nA: int, bs: int):
    """Blocks of H^-1 that a block-structured H_g touches: (AA, AF (F,nA,bs), FF (F,bs,bs))."""
    Sinv, Bf, Dinv = _schur(H, nA, bs)
    AF = -np.einsum("ab,fbc,fcd->fad", Sinv, Bf, Dinv)
    BtD = np.transpose(Bf, (0, 2, 1))
    FF = Dinv + Dinv @ BtD @ Sinv[None] @ Bf @ Dinv
    return Sinv, AF, FF


def _trace_inv_times(inv_blocks, Hg, nA: int, bs: int) -> float:
    """trace(H^-1 H_g) for H_g with H's block structure."""
    AA, AF, FF = inv_blocks
    A, Bf, D = _blocks(Hg, nA, bs)
    return float(np.sum(AA * A) + 2 * np.sum(AF * Bf) + np.sum(FF * D))


def _lm(residual_at, retract, groups_fn, n_params: int, nA: int, bs: int, max_iter: int = 30,
        tol: float = 1e-10):
    """Levenberg-Marquardt where ``residual_at(dx)`` evaluates at the current
    state perturbed by dx and ``retract(dx)`` moves the state; the normal
    equations are solved by the Schur complement on the block-diagonal part.
    Returns (J, r, iterations) at the final state (dx = 0)."""
    lam = 1e-4
    r = residual_at(np.zeros(n_params))
    cost = float(r @ r)
    it = 0
    for it in range(max_iter):  # noqa: B007 -- the count is returned
        J = _grouped_jacobian(residual_at, n_params, groups_fn(), r)
        H = (J.T @ J).tocsr()
        g = -(J.T @ r)
        improved = False
        rel = 0.0
        for _ in range(12):
            dx = _block_solve(H, g, nA, bs, lam)
            r_new = residual_at(dx)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                retract(dx)
                rel = (cost - c_new) / max(cost, 1e-300)
                r, cost = residual_at(np.zeros(n_params)), c_new
                lam = max(lam / 5, 1e-9)
                improved = True
                break
            lam *= 8
        if not improved or rel < tol or float(np.max(np.abs(dx))) < 1e-12:
            break
    J = _grouped_jacobian(residual_at, n_params, groups_fn(), r)
    return J, r, it + 1


# ----------------------------------------------------------------------------
# paper: free points
# ----------------------------------------------------------------------------
def solve_paper(obs: list, board: BoardGeometry, init: dict, max_iter: int = 30) -> tuple[dict, dict]:
    """Algorithm 1: minimise the reprojection over every extrinsic and every
    corner point. Returns ({cam: T}, {obs index: optimised (n,3) points})."""
    cams = [c for c in cameras_seen(obs) if c in init]
    ci = {c: k for k, c in enumerate(cams)}
    V = [o.lidar.virtual_corners(board) for o in obs]
    n_corner = board.n_corners
    pts = np.concatenate(V)  # (F*n, 3)
    rows_pt, rows_cam, xn = [], [], []
    for i, o in enumerate(obs):
        for c, ic in o.images.items():
            if c not in ci:
                continue
            rows_pt.append(i * n_corner + np.arange(n_corner))
            rows_cam.append(np.full(n_corner, ci[c]))
            xn.append(ic.xn)
    rows_pt, rows_cam, xn = np.concatenate(rows_pt), np.concatenate(rows_cam), np.concatenate(xn)
    nC = len(cams)
    state = {"R": np.array([init[c][:3, :3] for c in cams]), "t": np.array([init[c][:3, 3] for c in cams]),
             "P": pts.copy()}
    n_params = 6 * nC + 3 * len(pts)
    scale = 1000.0  # residuals in mm on the normalised plane

    def unpack(dx):
        dc = dx[:6 * nC].reshape(nC, 6)
        dp = dx[6 * nC:].reshape(-1, 3)
        R = _exp_batch(dc[:, :3]) @ state["R"]
        return R, state["t"] + dc[:, 3:], state["P"] + dp

    def residual_at(dx):
        R, t, P = unpack(dx)
        pc = np.einsum("nij,nj->ni", R[rows_cam], P[rows_pt]) + t[rows_cam]
        return (scale * (pc[:, :2] / pc[:, 2:3] - xn)).ravel()

    def retract(dx):
        state["R"], state["t"], state["P"] = unpack(dx)

    nres = 2 * len(rows_pt)
    rr = np.arange(nres)
    cam_of_row = np.repeat(rows_cam, 2)
    pt_of_row = np.repeat(rows_pt, 2)

    def groups_fn():
        gs = []
        for j in range(6):
            d = np.zeros(n_params)
            d[j:6 * nC:6] = 1.0
            gs.append((d, rr, 6 * cam_of_row + j))
        for k in range(3):
            d = np.zeros(n_params)
            d[6 * nC + k::3] = 1.0
            gs.append((d, rr, 6 * nC + 3 * pt_of_row + k))
        return gs

    _lm(residual_at, retract, groups_fn, n_params, 6 * nC, 3, max_iter=max_iter)
    Ts = {c: make_T(state["R"][k], state["t"][k]) for c, k in ci.items()}
    P = state["P"].reshape(len(obs), n_corner, 3)
    return Ts, {i: P[i] for i in range(len(obs))}


# ----------------------------------------------------------------------------
# ours
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class OursOptions:
    """Noise priors (the fit re-estimates them from the data) and limits."""
    pixel_sigma_px: float = 0.3
    range_sigma_m: float = 0.02
    edge_sigma_m: float = 0.005
    shrink_sigma_m: float = 0.01
    max_plane_points: int = 300
    variance_rounds: int = 3
    max_iter: int = 25
    outlier_factor: float = 4.0
    asymmetry_sigma_m: float = 0.003  # prior of the growth difference between where rings enter and leave
    robust_covariance: bool = True  # also the cluster-robust (per placement) covariance, the larger wins
    use_edges: bool = True  # ring ends on the outline (False: the LiDAR gives the board plane only)
    ring_bias_sigma_m: float = 0.005  # prior of each ring's range offset (0: no ring-bias parameters)
    fixed_pixel_sigma: dict | None = None  # {cam: sigma px} instead of pixel_sigma_px (e.g. for a bound)
    # per placement, the LiDAR's board pose may differ from the cameras' one by a small offset
    # (in the board frame: tilt, spin, in-plane shift, shift along the normal) common to all of
    # the placement's LiDAR points; these are its prior sigmas, re-estimated from the data
    # (variance components). None: no offsets (the LiDAR board pose is exact up to its noise); a 0
    # entry leaves that group out. Tilt and spin are off by default: over the family their
    # re-estimated sigmas always ended at the floor, and they cost a third of the fit time.
    placement_offset_sigma: tuple | None = (0.0, 0.0, 1e-3, 5e-4)  # tilt rad, spin rad, in-plane m, normal m
    placement_offset_floor: tuple = (2e-5, 2e-5, 5e-5, 5e-5)  # lower limits of the re-estimated sigmas


@dataclasses.dataclass
class OursSolution:
    T: dict                 # cam -> T_camera_lidar
    covariance: dict        # cam -> 6x6
    joint_covariance: np.ndarray  # (6C, 6C) in ``cams`` order
    cams: list
    board_poses: list       # T_lidar_board per observation (fitted)
    shrink_m: np.ndarray
    noise: dict             # estimated sigmas
    metrics: dict
    dropped: dict           # cam -> [obs indices dropped as outliers]


def _prepare_ours(obs, board, cams, opt, rng):
    ci = {c: k for k, c in enumerate(cams)}
    Pb = board.inner_corners_board()
    n = board.n_corners
    img = {"f": [], "c": [], "k": [], "xn": [], "fpx": []}
    for i, o in enumerate(obs):
        for c, ic in o.images.items():
            if c not in ci:
                continue
            img["f"].append(np.full(n, i))
            img["c"].append(np.full(n, ci[c]))
            img["k"].append(np.arange(n))
            img["xn"].append(ic.xn)
    pl = {"f": [], "p": [], "w": [], "ring": []}
    ed = {"f": [], "e": [], "dir": [], "step": [], "side": []}
    for i, o in enumerate(obs):
        P = o.lidar.points
        rg = o.lidar.point_ring if o.lidar.point_ring is not None else np.full(len(P), -1)
        if len(P) > opt.max_plane_points:
            sel = rng.choice(len(P), opt.max_plane_points, replace=False)
            P, rg = P[sel], rg[sel]
        pl["ring"].append(rg)
        ray = P / np.linalg.norm(P, axis=1, keepdims=True)
        cosinc = np.abs(ray @ o.lidar.normal)
        pl["f"].append(np.full(len(P), i))
        pl["p"].append(P)
        pl["w"].append(np.clip(cosinc, 0.2, 1.0))
        ed["f"].append(np.full(len(o.lidar.edge_points), i))
        ed["e"].append(o.lidar.edge_points)
        ed["dir"].append(o.lidar.edge_dir)
        ed["step"].append(o.lidar.edge_step_m)
        ed["side"].append(o.lidar.edge_side if o.lidar.edge_side is not None else np.zeros(len(o.lidar.edge_points)))
    cat = lambda d: {k: np.concatenate(v) if v else np.zeros(0) for k, v in d.items()}
    img, pl, ed = cat(img), cat(pl), cat(ed)
    img["Pb"] = Pb[img["k"].astype(int)]
    for d in (img, pl, ed):
        d["f"] = d["f"].astype(int)
    pl["ring"] = pl["ring"].astype(int)
    img["c"] = img["c"].astype(int)
    return ci, img, pl, ed


def solve_ours(obs: list, board: BoardGeometry, cameras: dict, init: dict, options: OursOptions | None = None,
               seed: int = 0) -> OursSolution:
    """Joint fit of every camera's extrinsic and every placement's board pose."""
    opt = options or OursOptions()
    rng = np.random.default_rng(seed)
    cams = [c for c in cameras_seen(obs) if c in init]
    if not cams:
        raise SolveError("no camera has observations to fit")
    F = len(obs)
    nC = len(cams)
    a_half, b_half = board.size_m[0] / 2, board.size_m[1] / 2
    ci, img, pl, ed = _prepare_ours(obs, board, cams, opt, rng)
    focal = np.array([0.5 * (cameras[c].fx + cameras[c].fy) for c in cams])
    state = {"Rc": np.array([init[c][:3, :3] for c in cams]), "tc": np.array([init[c][:3, 3] for c in cams]),
             "Rf": np.array([o.lidar.T_lidar_board[:3, :3] for o in obs]),
             "tf": np.array([o.lidar.T_lidar_board[:3, 3] for o in obs]),
             "s": np.array([o.lidar.shrink_m for o in obs], dtype=float), "a": np.zeros(len(obs)),
             "d": np.zeros((len(obs), 6))}
    sig = {"px": np.array([float((opt.fixed_pixel_sigma or {}).get(c, opt.pixel_sigma_px)) for c in cams]),
           "range": opt.range_sigma_m, "edge": opt.edge_sigma_m}
    use_off = bool(opt.placement_offset_sigma) and any(opt.placement_offset_sigma) and F >= 3 and opt.use_edges
    off_sig = np.array(opt.placement_offset_sigma if use_off else (1.0, 1.0, 1.0, 1.0), dtype=float)
    off_comp = np.array([0, 0, 1, 2, 2, 3])  # offset component -> its sigma group
    off_idx = np.nonzero(off_sig[off_comp] > 0)[0] if use_off else np.zeros(0, int)  # offset components fitted
    nO = len(off_idx)
    active = np.ones(len(img["f"]), bool)  # image rows in use
    # one range offset per ring id (a spinning LiDAR's per-laser calibration error)
    ring_ids = np.unique(pl["ring"][pl["ring"] >= 0]) if opt.ring_bias_sigma_m > 0 else np.zeros(0, int)
    nR = len(ring_ids)
    pl_ri = np.searchsorted(ring_ids, pl["ring"]) if nR else np.zeros(len(pl["f"]), int)
    pl_has = (pl["ring"] >= 0) & (nR > 0)
    if nR:
        pl_ri = np.where(pl_has, np.minimum(pl_ri, nR - 1), 0)
    pl_u = pl["p"] / np.linalg.norm(pl["p"], axis=1, keepdims=True)
    state["beta"] = np.zeros(nR)
    nA = 6 * nC + nR
    BS = 8 + nO  # per placement: rotation 3, translation 3, growth, asymmetry[, LiDAR offset components]
    n_params = nA + BS * F

    # edge assignment and quantisation sigma from the initial board poses
    def lidar_pose(Rf, tf, d):
        """The board pose the LiDAR measured: the cameras' one moved by the offset (board frame)."""
        if not use_off:
            return Rf, tf
        return Rf @ _exp_batch(d[:, :3]), tf + np.einsum("nij,nj->ni", Rf, d[:, 3:])

    def edge_setup():
        RL, tL = lidar_pose(state["Rf"], state["tf"], state["d"])
        Rf, tf = RL[ed["f"]], tL[ed["f"]]
        q = np.einsum("nji,nj->ni", Rf, ed["e"] - state["s"][ed["f"]][:, None] * ed["dir"] - tf)
        dx, dy = np.abs(q[:, 0]) - a_half, np.abs(q[:, 1]) - b_half
        axis = np.where(np.abs(dx) < np.abs(dy), 0, 1)
        d_loc = np.einsum("nji,nj->ni", Rf, ed["dir"])
        perp = np.abs(np.where(axis == 0, d_loc[:, 0], d_loc[:, 1]))
        quant = ed["step"] * perp / math.sqrt(12.0)
        ok = (np.minimum(np.abs(dx), np.abs(dy)) < 0.05) & opt.use_edges
        return axis, quant, ok
    ed_axis, ed_quant, ed_ok = edge_setup()

    def unpack(dx):
        dc = dx[:6 * nC].reshape(nC, 6)
        df = dx[nA:].reshape(F, BS)
        Rc = _exp_batch(dc[:, :3]) @ state["Rc"]
        Rf = _exp_batch(df[:, :3]) @ state["Rf"]
        d = state["d"]
        if nO:
            d = d.copy()
            d[:, off_idx] += df[:, 8:]
        return (Rc, state["tc"] + dc[:, 3:], Rf, state["tf"] + df[:, 3:6], state["s"] + df[:, 6],
                state["beta"] + dx[6 * nC:nA], state["a"] + df[:, 7], d)

    def residual_at(dx):
        Rc, tc, Rf, tf, s, beta, asym, doff = unpack(dx)
        # image
        f, c = img["f"], img["c"]
        pl_ = np.einsum("nij,nj->ni", Rf[f], img["Pb"]) + tf[f]
        pc = np.einsum("nij,nj->ni", Rc[c], pl_) + tc[c]
        w = (focal[c] / sig["px"][c] * active)[:, None]
        r_img = ((pc[:, :2] / pc[:, 2:3] - img["xn"]) * w).ravel()
        # LiDAR residuals at the LiDAR's board pose
        Rf, tf = lidar_pose(Rf, tf, doff)
        # plane
        fp = pl["f"]
        nrm = Rf[fp][:, :, 2]
        pp = pl["p"] - (beta[pl_ri] * pl_has)[:, None] * pl_u if nR else pl["p"]
        r_pl = (np.einsum("ni,ni->n", nrm, pp - tf[fp])) / (sig["range"] * pl["w"])
        # edges
        fe = ed["f"]
        g = s[fe] + asym[fe] * ed["side"]
        q = np.einsum("nji,nj->ni", Rf[fe], ed["e"] - g[:, None] * ed["dir"] - tf[fe])
        half = np.where(ed_axis == 0, a_half, b_half)
        r_ed = (np.abs(np.where(ed_axis == 0, q[:, 0], q[:, 1])) - half) / np.sqrt(ed_quant ** 2 + sig["edge"] ** 2)
        r_ed = r_ed * ed_ok
        r_s = (s - np.median(state["s"])) / opt.shrink_sigma_m
        r_b = beta / opt.ring_bias_sigma_m if nR else np.zeros(0)
        r_a = asym / opt.asymmetry_sigma_m
        r_d = (doff[:, off_idx] / off_sig[off_comp[off_idx]]).ravel() if nO else np.zeros(0)
        return np.concatenate([r_img, r_pl, r_ed, r_s, r_a, r_b, r_d])

    def retract(dx):
        (state["Rc"], state["tc"], state["Rf"], state["tf"], state["s"], state["beta"], state["a"],
         state["d"]) = unpack(dx)

    n_img = 2 * len(img["f"])
    n_pl, n_ed = len(pl["f"]), len(ed["f"])
    rows_img = np.arange(n_img)
    rows_pl = n_img + np.arange(n_pl)
    rows_ed = n_img + n_pl + np.arange(n_ed)
    rows_b = n_img + n_pl + n_ed + 2 * F + np.arange(nR)
    cam_of_img = np.repeat(img["c"], 2)
    frame_of_row = np.concatenate([np.repeat(img["f"], 2), pl["f"], ed["f"], np.arange(F), np.arange(F)])
    rows_d = n_img + n_pl + n_ed + 2 * F + nR + np.arange(nO * F)
    all_rows = np.concatenate([np.arange(len(frame_of_row)), rows_d])
    frame_rows = np.concatenate([frame_of_row, np.repeat(np.arange(F), nO)])
    pl_rows_b = rows_pl[pl_has]

    def groups_fn():
        gs = []
        for j in range(6):
            d = np.zeros(n_params)
            d[j:6 * nC:6] = 1.0
            gs.append((d, rows_img, 6 * cam_of_img + j))
        if nR:
            d = np.zeros(n_params)
            d[6 * nC:nA] = 1.0
            gs.append((d, np.concatenate([pl_rows_b, rows_b]),
                       6 * nC + np.concatenate([pl_ri[pl_has], np.arange(nR)])))
        for k in range(BS):
            d = np.zeros(n_params)
            d[nA + k::BS] = 1.0
            gs.append((d, all_rows, nA + BS * frame_rows + k))
        return gs

    dropped = {c: [] for c in cams}
    J = r = None
    for rnd in range(opt.variance_rounds + 1):
        if rnd > 0:
            ed_axis, ed_quant, ed_ok = edge_setup()  # edges re-assigned at the refined board poses
        J, r, _ = _lm(residual_at, retract, groups_fn, n_params, nA, BS, max_iter=opt.max_iter)
        # per-placement image outliers (board moved between sweep and image, wrong detection)
        changed = False
        if rnd == 0 and opt.max_iter > 0:
            ri = r[:n_img].reshape(-1, 2)
            keys = img["f"] * nC + img["c"]
            per = {int(k): float(np.sqrt(np.mean(np.sum(ri[keys == k] ** 2, axis=1)))) for k in np.unique(keys)}
            for k, e in per.items():
                cam_med = float(np.median([v for k2, v in per.items() if k2 % nC == k % nC]))
                if e > opt.outlier_factor * max(cam_med, 1.0) and e > 3.0:
                    active[keys == k] = False
                    dropped[cams[k % nC]].append(k // nC)
                    changed = True
        if rnd == opt.variance_rounds:
            break
        # variance components: group factor = chi2 / redundancy, redundancy = n_g - tr(H^-1 H_g)
        H = (J.T @ J).tocsr()
        invb = _inverse_blocks(H, nA, BS)
        Jc = J.tocsr()
        facs = {}

        def factor(rows, Jc=Jc, invb=invb, r=r):
            Jg = Jc[rows]
            red = len(rows) - _trace_inv_times(invb, (Jg.T @ Jg).tocsr(), nA, BS)
            return float(r[rows] @ r[rows]) / max(red, 1.0)
        for k, c in enumerate(cams):
            rows = np.repeat(active & (img["c"] == k), 2).nonzero()[0]
            if len(rows) > 20:
                facs[f"px_{c}"] = factor(rows)
                sig["px"][k] *= math.sqrt(facs[f"px_{c}"])
        if n_pl > 10:
            facs["range"] = factor(rows_pl)
            sig["range"] *= math.sqrt(facs["range"])
        ok_rows = rows_ed[ed_ok]
        if len(ok_rows) > 10:
            # edges: re-estimate the noise floor so the group chi2 matches its redundancy
            f_e = factor(ok_rows)
            q2 = float(np.mean(ed_quant[ed_ok] ** 2))
            sig["edge"] = math.sqrt(max((q2 + sig["edge"] ** 2) * f_e - q2, (0.2 * sig["edge"]) ** 2, 1e-8))
            facs["edge"] = f_e
        if use_off:
            comp_of_row = np.tile(off_comp[off_idx], F)
            for g in np.unique(off_comp[off_idx]):
                f_o = factor(rows_d[comp_of_row == g])
                off_sig[g] = max(off_sig[g] * math.sqrt(f_o), opt.placement_offset_floor[g])
                facs[f"offset_{g}"] = f_o
        if not changed and all(abs(v - 1) < 0.05 for v in facs.values()):
            break

    H = (J.T @ J).tocsr()
    Sinv = _schur(H, nA, BS)[0]
    cov_model = Sinv[:6 * nC, :6 * nC]
    if opt.robust_covariance:
        cov_c, inflation = _cluster_robust(J, r, frame_of_row, F, nA, Sinv, cov_model, 6 * nC)
    else:
        cov_c, inflation = cov_model, 1.0
    Ts, covs = {}, {}
    for c, k in ci.items():
        Ts[c] = make_T(state["Rc"][k], state["tc"][k])
        covs[c] = cov_c[6 * k:6 * k + 6, 6 * k:6 * k + 6].copy()
    poses = [make_T(state["Rf"][i], state["tf"][i]) for i in range(F)]
    ri = r[:n_img].reshape(-1, 2) * (sig["px"][img["c"]] / focal[img["c"]])[:, None]
    metrics = {"residual_rms_px": {c: float(np.sqrt(np.mean(np.sum(
        (ri[active & (img["c"] == k)] * focal[k]) ** 2, axis=1)))) for c, k in ci.items()},
        "plane_rms_mm": float(1000 * np.sqrt(np.mean((r[rows_pl] * sig["range"] * pl["w"]) ** 2)))
        if n_pl else math.nan,
        "edge_points": int(ed_ok.sum()), "shrink_median_mm": float(1000 * np.median(state["s"])),
        "covariance_inflation": inflation, "ring_bias_mm": [float(1000 * b) for b in state["beta"]]}
    noise = {"pixel_sigma_px": {c: float(sig["px"][k]) for c, k in ci.items()},
             "range_sigma_m": float(sig["range"]), "edge_sigma_m": float(sig["edge"])}
    if use_off:
        vals = {"tilt_deg": float(np.degrees(off_sig[0])), "spin_deg": float(np.degrees(off_sig[1])),
                "in_plane_mm": float(1000 * off_sig[2]), "normal_mm": float(1000 * off_sig[3])}
        fitted = set(off_comp[off_idx].tolist())
        noise["placement_offset_sigma"] = {k: v for g, (k, v) in enumerate(vals.items()) if g in fitted}
    return OursSolution(Ts, covs, cov_c, cams, poses, state["s"].copy(), noise, metrics, dropped)


def _cluster_robust(J, r, frame_of_row, F: int, nA: int, Sinv, cov_model, nc: int):
    """Covariance of the camera block that also holds what the placements themselves say.

    The model covariance trusts the noise model point by point; errors that are common to one
    placement (the board's edges seen differently by the beam, a mixed pixel, a corner
    detector bias over one image) are not in it. The cluster-robust (sandwich) covariance with
    one cluster per placement, ``S^-1 (sum_f g_f g_f^T) S^-1`` with ``g_f`` the score of the
    placement's residuals on the global parameters, sees them. The result is the larger of the
    two in every direction. Returns (covariance, largest variance ratio)."""
    from scipy.sparse import csr_matrix
    if F < 4:
        return cov_model, 1.0
    n_rows = len(frame_of_row)
    JA = J[:n_rows, :nA].tocsr()
    contrib = JA.multiply(r[:n_rows][:, None]).tocsr()
    M = csr_matrix((np.ones(n_rows), (frame_of_row, np.arange(n_rows))), shape=(F, n_rows))
    g = np.asarray((M @ contrib).todense())
    G = g.T @ g * (F / (F - 1.0))
    sw = (Sinv @ G @ Sinv)[:nc, :nc]
    try:
        L = np.linalg.cholesky(cov_model)
    except np.linalg.LinAlgError:
        return cov_model, 1.0
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(Li @ sw @ Li.T)
    lam = np.maximum(lam, 1.0)
    cov = L @ (V * lam) @ V.T @ L.T
    return 0.5 * (cov + cov.T), float(lam.max())


def relative_transform(T_a: np.ndarray, T_b: np.ndarray, cov_ab: np.ndarray | None = None):
    """T_b_a = T_b @ inv(T_a) (camera a -> camera b) and its 6x6 covariance
    from the 12x12 joint covariance of (a, b) (same perturbation convention)."""
    T_ba = T_b @ inv_T(T_a)
    if cov_ab is None:
        return T_ba, None
    J = np.zeros((6, 12))
    h = 1e-7
    for k in range(12):
        d = np.zeros(12)
        d[k] = h
        Ta = make_T(so3_exp(d[:3]) @ T_a[:3, :3], T_a[:3, 3] + d[3:6])
        Tb = make_T(so3_exp(d[6:9]) @ T_b[:3, :3], T_b[:3, 3] + d[9:12])
        T2 = Tb @ inv_T(Ta)
        J[:3, k] = so3_log(T2[:3, :3] @ T_ba[:3, :3].T) / h
        J[3:, k] = (T2[:3, 3] - T_ba[:3, 3]) / h
    return T_ba, J @ cov_ab @ J.T


# ----------------------------------------------------------------------------
# observability and advice
# ----------------------------------------------------------------------------
def placement_coverage(obs: list, cam: str, model: CameraModel, T_cl: np.ndarray | None = None) -> dict:
    """Where the board has been in this camera: image regions, distance, tilt."""
    us, vs, dist, tilt_h, tilt_v = [], [], [], [], []
    for o in obs:
        if cam not in o.images:
            continue
        ic = o.images[cam]
        c = ic.uv.mean(axis=0)
        us.append(c[0] / model.width)
        vs.append(c[1] / model.height)
        T = ic.T_camera_board
        dist.append(float(np.linalg.norm(T[:3, 3])))
        n = T[:3, 2]
        view = -T[:3, 3] / np.linalg.norm(T[:3, 3])
        # tilt of the normal against the viewing ray, split left-right / up-down
        tilt_h.append(math.degrees(math.atan2(n[0] - view[0] * (n @ view), abs(n @ view))))
        tilt_v.append(math.degrees(math.atan2(n[1] - view[1] * (n @ view), abs(n @ view))))
    if not us:
        return {"frames": 0}
    return {"frames": len(us), "u": us, "v": vs, "distance_m": dist, "tilt_h_deg": tilt_h, "tilt_v_deg": tilt_v}


def missing_placements(cov: dict, cam: str) -> list:
    """Placement advice for one camera from its coverage."""
    if cov.get("frames", 0) == 0:
        return [f"show the board to camera {cam} (it has not seen it together with the LiDAR)"]
    out = []
    u, v = np.array(cov["u"]), np.array(cov["v"])
    d = np.array(cov["distance_m"])
    th, tv = np.array(cov["tilt_h_deg"]), np.array(cov["tilt_v_deg"])
    if not np.any(u < 0.4):
        out.append(f"place the board to the left of camera {cam}'s image")
    if not np.any(u > 0.6):
        out.append(f"place the board to the right of camera {cam}'s image")
    if not np.any(v < 0.4):
        out.append(f"place the board in the top part of camera {cam}'s image")
    if not np.any(v > 0.6):
        out.append(f"place the board in the bottom part of camera {cam}'s image")
    if d.max() < 1.4 * d.min():
        out.append(f"vary the distance to camera {cam} more (now {d.min():.1f}-{d.max():.1f} m): "
                   "bring the board nearer and take it farther")
    if not (np.any(th > 12) and np.any(th < -12)):
        out.append(f"tilt the board more left and right (turn it about its vertical axis) for camera {cam}")
    if not (np.any(tv > 12) and np.any(tv < -12)):
        out.append(f"tilt the board more forwards and backwards for camera {cam}")
    return out


def observability(cov6: np.ndarray, max_sigma_deg: float, max_sigma_mm: float) -> dict:
    """Verdict from the covariance: weakest direction and whether it meets the limits."""
    sr = np.degrees(np.sqrt(np.clip(np.diag(cov6)[:3], 0, None)))
    st = 1000 * np.sqrt(np.clip(np.diag(cov6)[3:], 0, None))
    names = ["roll (about x)", "pitch (about y)", "yaw (about z)", "x", "y", "z"]
    rel = np.concatenate([sr / max_sigma_deg, st / max_sigma_mm])
    k = int(np.argmax(rel))
    ok = bool(np.all(np.isfinite(rel)) and rel.max() <= 1.0)
    return {"verdict": "observable" if ok else "weak", "weakest_direction": names[k],
            "sigma_rotation_deg": [float(v) for v in sr], "sigma_translation_mm": [float(v) for v in st]}


__all__ = ["OursOptions", "OursSolution", "Observation", "SOLVERS", "SolveError", "camera_metrics",
           "cameras_seen", "kabsch", "missing_placements", "normalized_plane_error_mm", "observability",
           "placement_coverage", "plane_only_start", "relative_transform", "resolve_symmetry", "solve_epnp",
           "solve_kabsch", "solve_ours", "solve_paper"]
