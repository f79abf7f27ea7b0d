"""Solvers for the 2D-laser / depth-camera extrinsic (paper 003), ROS-free.

Unknown: ``T_camera_laser`` (``p_camera = R p_laser + t``), laser frame x
forward, y left, z up (scan plane z = 0); camera optical frame.

One observation (:class:`LrfObservation`) of the folded board holds
* the laser corners F, G, H (laser xy, metres) and the laser inlier points of
  the three faces the scan line crosses: base (segments EF and HI), FG
  (triangle ABC), GH (triangle ACD);
* the camera planes ``(n, d)`` of base (plane 1), ABC (plane 2), ACD (plane 3)
  with the statistics of their fits (for the uncertainty of each plane).
  F lies on AB = plane1 & plane2, G on AC = plane2 & plane3, H on AD =
  plane3 & plane1 (paper eqs. 6-10).

Solvers
* :func:`solve_paper` -- exactly eqs. 10/11: linear least squares in
  ``X = [r11 r12 t1 r21 r22 t2 r31 r32 t3]``, ``r3 = r1 x r2``.
* :func:`paper_adaptive` -- Algorithm 1 (add observations until the eq. 12
  error of the current solution on the new observation drops below a threshold).
* :func:`solve_ours` -- SE(3) refinement of every laser face point onto the
  camera plane of its face (weighted by laser range noise and camera plane
  uncertainty, soft-L1 robust loss) plus corner-on-line terms, with
  covariance and an observability verdict.
"""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.optimize import least_squares

from ..core.fitting import FitError, intersect_planes
from ..core.geometry import make_T, project_to_so3, so3_exp, so3_log

# Face order everywhere: 0 = base (plane 1, PBDQ), 1 = ABC (plane 2), 2 = ACD (plane 3).
FACE_NAMES = ("base", "ABC", "ACD")
# Corner i lies on the line where planes CORNER_PLANES[i] meet (F: 1&2, G: 2&3, H: 3&1).
CORNER_PLANES = ((0, 1), (1, 2), (2, 0))
CORNER_NAMES = ("F", "G", "H")


@dataclasses.dataclass
class PlaneStats:
    """Statistics of a (weighted) camera plane fit, camera frame, metres.

    ``centroid`` (3,) weighted centroid, ``axes`` (2,3) in-plane principal
    directions, ``spread`` (2,) weighted sums of squared in-plane coordinates
    along ``axes``, ``weight_sum`` sum of point weights (1/sigma_i^2 scaled,
    or the point count for unit weights), ``variance_factor`` = weighted
    residual sum of squares / (M - 3), ``count`` points, ``rms_m`` plain RMS
    perpendicular residual (for reports)."""
    centroid: np.ndarray
    axes: np.ndarray
    spread: np.ndarray
    weight_sum: float
    variance_factor: float
    count: int
    rms_m: float

    @classmethod
    def from_points(cls, pts: np.ndarray, n: np.ndarray, d: float,
                    weights: np.ndarray | None = None) -> PlaneStats:
        pts = np.asarray(pts, dtype=float)
        w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=float)
        ws = float(w.sum())
        c = (w[:, None] * pts).sum(axis=0) / ws
        q = pts - c
        S = (w[:, None] * q).T @ q
        ev, V = np.linalg.eigh(S)
        axes = V[:, 1:].T  # two largest = in-plane
        spread = np.maximum(ev[1:], 1e-12)
        r = pts @ n + d
        vf = float((w * r * r).sum() / max(len(pts) - 3, 1))
        return cls(c, axes, spread, ws, vf, len(pts), float(np.sqrt(np.mean(r * r))))

    def offset_variance(self, p: np.ndarray, floor_m: float = 0.0) -> np.ndarray:
        """Variance (m^2) of the fitted plane's position along its normal at
        points ``p`` (N,3), for independent per-point noise: the centroid term
        plus the tilt term growing with the distance from the centroid."""
        q = np.atleast_2d(p) - self.centroid
        a = q @ self.axes.T
        v = self.variance_factor * (1.0 / self.weight_sum + (a ** 2 / self.spread).sum(axis=1))
        return v + floor_m ** 2


@dataclasses.dataclass
class LrfObservation:
    """One simultaneous laser + depth-camera observation of the board.

    ``corners_laser_m`` (3,2): F, G, H in laser xy. ``planes_cam`` (3,4): rows
    ``[nx, ny, nz, d]`` of planes 1 (base), 2 (ABC), 3 (ACD) in the camera frame.
    ``face_points_laser_m``: three (Ni,2) arrays, laser inlier points of the
    base (EF and HI), FG and GH segments. ``plane_stats``: optional
    :class:`PlaneStats` per plane (None -> ``default_plane_sigma_m``).
    ``corner_cov_laser``: optional (3,2,2) covariance of F, G, H (m^2)."""
    corners_laser_m: np.ndarray
    planes_cam: np.ndarray
    face_points_laser_m: tuple = ()
    plane_stats: tuple = ()
    corner_cov_laser: np.ndarray | None = None
    stamp_s: float = 0.0
    laser_sigma_m: float = 0.0125
    depth_noise: object = None  # features.DepthNoise the plane weights came from (reports, bounds)

    def __post_init__(self) -> None:
        self.corners_laser_m = np.asarray(self.corners_laser_m, dtype=float).reshape(3, 2)
        self.planes_cam = np.asarray(self.planes_cam, dtype=float).reshape(3, 4)

    def lines_cam(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Lines AB, AC, AD in the camera frame as (point, unit_dir)."""
        P = self.planes_cam
        return [intersect_planes((P[i, :3], P[i, 3]), (P[j, :3], P[j, 3])) for i, j in CORNER_PLANES]

    def swapped(self) -> LrfObservation:
        """The same observation with the two camera triangles exchanged
        (ABC <-> ACD): the alternative laser/camera face correspondence."""
        P = self.planes_cam[[0, 2, 1]]
        st = tuple(self.plane_stats[k] for k in (0, 2, 1)) if len(self.plane_stats) == 3 else ()
        return dataclasses.replace(self, planes_cam=P, plane_stats=st)


# ----------------------------------------------------------------------------
# Paper: eqs. 10-12 and Algorithm 1
# ----------------------------------------------------------------------------
def paper_rows(obs: LrfObservation) -> tuple[np.ndarray, np.ndarray]:
    """The 6 rows of eq. 10 for one observation: (A (6,9), b (6,)).

    Row k pairs corner i with plane j: F-1, F-2, G-2, G-3, H-3, H-1."""
    pairs = ((0, 0), (0, 1), (1, 1), (1, 2), (2, 2), (2, 0))
    A = np.zeros((6, 9))
    b = np.zeros(6)
    for k, (ci, pj) in enumerate(pairs):
        x, y = obs.corners_laser_m[ci]
        Aa, Bb, Cc, Dd = obs.planes_cam[pj]
        A[k] = [Aa * x, Aa * y, Aa, Bb * x, Bb * y, Bb, Cc * x, Cc * y, Cc]
        b[k] = -Dd
    return A, b


def _X_to_Rt(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r1 = np.array([X[0], X[3], X[6]])
    r2 = np.array([X[1], X[4], X[7]])
    t = np.array([X[2], X[5], X[8]])
    R = np.column_stack([r1, r2, np.cross(r1, r2)])
    return R, t


def solve_paper(observations: Sequence[LrfObservation]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Paper eq. 11: stack 6 rows per observation, solve ``A X = b`` by linear
    least squares, complete ``R`` with ``r3 = r1 x r2``.

    Returns ``(R_raw, t, info)``. ``R_raw`` is the paper's matrix, in general
    *not* orthonormal (the paper does not orthonormalise); ``info`` holds
    ``R_so3`` (nearest rotation, Frobenius, via SVD), ``T`` (4x4 with
    ``R_so3``), ``X``, ``rank``, ``singular_values``, ``condition``,
    ``orthonormality_error`` (||R_raw^T R_raw - I||_F) and the eq. 12 error
    ``point_to_line_m`` (of the raw solution)."""
    obs = list(observations)
    if len(obs) < 2:
        raise ValueError(f"paper solver needs >= 2 observations (12 equations for 9 unknowns), got {len(obs)}")
    rows = [paper_rows(o) for o in obs]
    A = np.concatenate([r[0] for r in rows])
    b = np.concatenate([r[1] for r in rows])
    X, _res, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    R, t = _X_to_Rt(X)
    R_so3 = project_to_so3(R)
    info = {
        "X": X, "rank": int(rank), "singular_values": sv,
        "condition": float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
        "R_so3": R_so3, "T": make_T(R_so3, t),
        "orthonormality_error": float(np.linalg.norm(R.T @ R - np.eye(3))),
        "point_to_line_m": point_to_line_error_m(R, t, obs),
        "point_to_line_so3_m": point_to_line_error_m(R_so3, t, obs),
    }
    return R, t, info


def corner_line_distances_m(R: np.ndarray, t: np.ndarray, obs: LrfObservation) -> np.ndarray:
    """(3,) true 3D distances of F, G, H (mapped by ``R, t``) to AB, AC, AD."""
    out = np.empty(3)
    for i, (pt, u) in enumerate(obs.lines_cam()):
        x, y = obs.corners_laser_m[i]
        p = R @ np.array([x, y, 0.0]) + t
        q = p - pt
        out[i] = np.linalg.norm(q - (q @ u) * u)
    return out


def point_to_line_error_m(R: np.ndarray, t: np.ndarray, observations: Iterable[LrfObservation]) -> float:
    """Paper eq. 12: mean distance (m) of the projected laser corners F, G, H
    to the camera lines AB, AC, AD over all observations.

    Eq. 12 as printed divides ``|A x + B y + C z + D|`` by ``sqrt(A^2+B^2+C^2)``,
    which is a point-to-*plane* distance although the text calls it the
    point-to-line distance. We implement the true 3D point-to-line distance
    ``|(p - a) - ((p - a).u) u|`` with each line from the two planes that
    define it (AB = planes 1&2, AC = 2&3, AD = 3&1)."""
    d = [corner_line_distances_m(R, t, o) for o in observations]
    return float(np.mean(np.concatenate(d))) if d else float("nan")


@dataclasses.dataclass
class AdaptiveResult:
    R: np.ndarray            # raw paper rotation (see solve_paper)
    t: np.ndarray
    observations_used: int
    converged: bool
    errors_m: list           # eq. 12 error of the current solution on each new observation
    info: dict


def paper_adaptive(observations_stream: Iterable[LrfObservation], threshold_m: float,
                   max_observations: int | None = None) -> AdaptiveResult:
    """Paper Algorithm 1.

    Observations are taken one at a time. The first two are stacked and
    solved (eq. 11). From the third on, the eq. 12 error of the *current*
    solution on the *new* observation is computed (line 18); when it is below
    ``threshold_m`` the current solution is returned, otherwise the new
    observation is added and X re-solved (lines 25-27). If the stream ends
    first, the last solution is returned with ``converged = False``."""
    used: list[LrfObservation] = []
    errors: list[float] = []
    R = t = None
    info: dict = {}
    for o in observations_stream:
        if max_observations is not None and len(used) >= max_observations:
            break
        if len(used) >= 2 and R is not None:
            err = float(np.mean(corner_line_distances_m(R, t, o)))
            errors.append(err)
            if err < threshold_m:
                return AdaptiveResult(R, t, len(used), True, errors, info)
        used.append(o)
        if len(used) >= 2:
            R, t, info = solve_paper(used)
    if R is None:
        raise ValueError("paper_adaptive: fewer than 2 observations in the stream")
    return AdaptiveResult(R, t, len(used), False, errors, info)


# ----------------------------------------------------------------------------
# Correspondence check (which laser triangle segment is ABC)
# ----------------------------------------------------------------------------
def resolve_assignment(observations: Sequence[LrfObservation], ratio: float = 0.5
                       ) -> tuple[list[LrfObservation], list[bool]]:
    """Check the laser-segment / camera-triangle pairing and fix it.

    Features pair triangles by left/right order (laser angle grows to the
    left, image x to the right), which fails if one sensor is mounted
    upside down or a detection is mirrored. 1) Solve the paper system with
    all observations as given and with all swapped; keep the lower eq. 12
    error. 2) For each observation, compare its eq. 12 error under the
    current solution with and without the swap; swap it when that is
    ``ratio`` times better, and re-solve. Needs >= 2 observations (with one
    observation it returns the input unchanged). Returns the (possibly
    swapped) observations and one flag per observation (True = swapped)."""
    obs = list(observations)
    flags = [False] * len(obs)
    if len(obs) < 2:
        return obs, flags

    def err_of(ol: list[LrfObservation]) -> tuple[float, np.ndarray, np.ndarray]:
        try:
            R, t, info = solve_paper(ol)
        except (np.linalg.LinAlgError, ValueError, FitError):
            return float("inf"), np.eye(3), np.zeros(3)
        return point_to_line_error_m(info["R_so3"], t, ol), info["R_so3"], t

    e0, R0, t0 = err_of(obs)
    sw = [o.swapped() for o in obs]
    e1, R1, t1 = err_of(sw)
    if e1 < e0:
        obs, flags, R, t = sw, [True] * len(obs), R1, t1
    else:
        R, t = R0, t0
    if len(obs) >= 3:
        changed = False
        for i, o in enumerate(obs):
            a = float(np.mean(corner_line_distances_m(R, t, o)))
            b = float(np.mean(corner_line_distances_m(R, t, o.swapped())))
            if b < ratio * a:
                obs[i] = o.swapped()
                flags[i] = not flags[i]
                changed = True
        if changed:
            _, R, t = err_of(obs)
    return obs, flags


def reject_outlier_observations(observations: Sequence[LrfObservation], min_m: float = 0.03,
                                factor: float = 5.0, options: OursOptions | None = None,
                                chi2_max: float = 22.5) -> tuple[list[LrfObservation], list[int], list[float]]:
    """Drop observations that disagree with the others (a mis-detected board).

    Fit ours (robust loss) on all; each observation's whitened residuals give
    its chi^2 (6 residuals: two per face). The worst is dropped when its chi^2
    exceeds ``max(chi2_max, factor * median chi^2)`` (22.5 = chi^2_6 at 99.9 %;
    the median guards against noise that is larger everywhere) *or* its worst
    corner lies farther than ``max(min_m, factor * median)`` from its camera
    line; then the rest is refitted. At most a third, and only from 3
    observations on (with two nothing tells which one is wrong). Returns
    (kept, dropped indices, chi^2 of every input observation)."""
    obs = list(observations)
    idx = list(range(len(obs)))
    dropped: list[int] = []
    chi_all = [float("nan")] * len(obs)
    opt = options or OursOptions()
    while len(idx) >= 3 and len(dropped) < len(obs) // 3:
        sub = [obs[i] for i in idx]
        sol = solve_ours(sub, options=opt)
        R, t = sol.T[:3, :3], sol.T[:3, 3]
        chi = np.array(observation_chi2(sub, R, t, opt))
        worst = np.array([float(np.max(corner_line_distances_m(R, t, o))) for o in sub])
        for i, c in zip(idx, chi):
            chi_all[i] = float(c)
        k = int(np.argmax(chi))
        bad_chi = chi[k] > max(chi2_max, factor * float(np.median(chi)))
        kw = int(np.argmax(worst))
        bad_corner = worst[kw] > max(min_m, factor * float(np.median(worst)))
        if not (bad_chi or bad_corner):
            break
        dropped.append(idx.pop(k if bad_chi else kw))
    return [obs[i] for i in idx], dropped, chi_all


def observation_chi2(observations: Sequence[LrfObservation], R: np.ndarray, t: np.ndarray,
                     options: OursOptions | None = None) -> list[float]:
    """Sum of squared whitened residuals of each observation at (R, t)."""
    opt = options or OursOptions()
    prob = _Problem(observations, opt)
    prob.update_weights(R, t)
    r = prob.residuals(np.zeros(6), R, t)
    out = [0.0] * len(prob.obs)
    if prob.has_points:
        rr = r[: 2 * len(prob.faces)].reshape(-1, 2)
        for (k, _f), v in zip(prob.faces, rr):
            out[k] += float(v @ v)
    return out


def covariance_left(cov_right: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Covariance of the perturbation ``(exp(dtheta) R, t + dt)`` (rotation in
    the camera frame) from that of ``(R exp(w), t + v)`` (laser frame):
    ``dtheta = R w``."""
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = np.eye(3)
    return J @ cov_right @ J.T


def pose_error_vector(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Error (6,) in the left convention of :func:`covariance_left`: rotation
    vector of ``R_true R_est^T`` and ``t_true - t_est``."""
    dR = T_true[:3, :3] @ T_est[:3, :3].T
    return np.concatenate([so3_log(dR), T_true[:3, 3] - T_est[:3, 3]])


def mahalanobis2(T_est: np.ndarray, cov_left: np.ndarray, T_true: np.ndarray) -> float:
    """Squared Mahalanobis distance of the 6-dof error against a covariance."""
    e = pose_error_vector(T_est, T_true)
    try:
        return float(e @ np.linalg.solve(cov_left, e))
    except np.linalg.LinAlgError:
        return float("inf")


def information_at(observations: Sequence[LrfObservation], T: np.ndarray,
                   options: OursOptions | None = None) -> np.ndarray:
    """``J^T J`` (6x6, right perturbation) of our whitened residuals at ``T``:
    with the true noise in the observations this is the Fisher information,
    its inverse the Cramer-Rao bound of the pose given these features."""
    opt = options or OursOptions()
    R, t = np.asarray(T)[:3, :3], np.asarray(T)[:3, 3]
    prob = _Problem(observations, opt)
    prob.update_weights(R, t)
    fun = lambda x: prob.residuals(x, R, t)
    J = _num_jac(fun, np.zeros(6))
    return J.T @ J


# ----------------------------------------------------------------------------
# Ours: SE(3) refinement with point-on-plane + corner-on-line residuals
# ----------------------------------------------------------------------------
@dataclasses.dataclass
class OursSolution:
    """``T`` = T_camera_laser (4x4). ``covariance`` 6x6, rotation first:
    rotation vector ``w`` of the perturbation ``R = R_hat exp(w)`` (axes of the
    laser frame, rad) and translation ``t = t_hat + v`` (camera frame, m)."""
    T: np.ndarray
    covariance: np.ndarray
    metrics: dict
    observability: dict

    def sigma_deg_mm(self) -> tuple[float, float]:
        d = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return float(np.degrees(d[:3].max())), float(d[3:].max() * 1000.0)


@dataclasses.dataclass
class OursOptions:
    laser_sigma_m: float | None = None   # None: each observation's laser_sigma_m
    laser_sigma_floor_m: float = 0.001   # added in quadrature to every laser point
    plane_sigma_floor_m: float = 0.0005  # floor on a camera plane's offset sigma
    default_plane_sigma_m: float = 0.002 # plane offset sigma when no PlaneStats given
    corner_weight: float = 0.0           # > 0 adds corner-on-line residuals (same data: counted twice)
    loss: str = "soft_l1"
    f_scale: float = 3.0                 # robust-loss scale in sigmas
    scale_covariance: bool = True        # multiply by s^2 when the residuals fail the chi^2 test (see solve_ours)
    target_sigma_deg: float = 0.1
    target_sigma_mm: float = 2.0
    max_nfev: int = 50


class _Problem:
    """Each laser segment on a board face must lie in the camera's plane of
    that face: two whitened residuals per face and observation.

    The laser points of a segment are reduced to their weighted total-least-
    squares line (per-point sigma: range noise times |cos(beam, line normal)|,
    since the R2000's noise is along the beam). Two virtual points at
    ``s_mean -/+ a`` along the line, with ``a`` the weighted standard
    deviation of the points' along-line positions, have *independent* errors
    of variance ``2 / sum(w)`` across the line. Their signed distances to the
    camera plane are the residuals; the plane's own uncertainty at those two
    points (centroid and tilt terms of the plane fit, correlated between the
    two) is added to the 2x2 covariance used for whitening. Nothing is counted
    twice and no per-point weight depends on the unknown pose."""

    def __init__(self, obs: Sequence[LrfObservation], opt: OursOptions):
        self.opt = opt
        self.obs = list(obs)
        Q, N, LV, FACE = [], [], [], []
        for k, o in enumerate(self.obs):
            sig = opt.laser_sigma_m if opt.laser_sigma_m is not None else o.laser_sigma_m
            for f in range(3):
                if len(o.face_points_laser_m) != 3:
                    continue
                pts = np.asarray(o.face_points_laser_m[f], dtype=float)
                if pts.shape[0] < 3:
                    continue
                seg = _segment_line(pts, sig, opt.laser_sigma_floor_m)
                if seg is None:
                    continue
                q, nu, var = seg
                Q.append(q)
                N.append(o.planes_cam[f])
                LV.append((nu, var))
                FACE.append((k, f))
        self.has_points = bool(Q)
        self.q = np.array(Q)            # (S, 2, 2) virtual points, laser xy
        self.planes = np.array(N)       # (S, 4)
        self.lv = LV
        self.faces = FACE
        self.stats = [o.plane_stats if len(o.plane_stats) == 3 else None for o in self.obs]
        self.lines = [o.lines_cam() for o in self.obs]

    def update_weights(self, R: np.ndarray, t: np.ndarray) -> None:
        """Whitening matrices at the current estimate (the plane term depends
        on where the virtual points land on the plane)."""
        opt = self.opt
        self.W = []
        for s_, ((k, f), (nu, var)) in enumerate(zip(self.faces, self.lv)):
            n = self.planes[s_, :3]
            pc = np.column_stack([self.q[s_], np.zeros(2)]) @ R.T + t
            g = float(n @ (R[:, :2] @ nu))
            C = np.eye(2) * (g * g * var)
            st = self.stats[k]
            if st is None:
                C += np.full((2, 2), opt.default_plane_sigma_m ** 2)
            else:
                C += _plane_offset_cov(st[f], pc) + np.eye(2) * opt.plane_sigma_floor_m ** 2
            L = np.linalg.cholesky(C + np.eye(2) * 1e-12)
            self.W.append(np.linalg.inv(L))
        self.W = np.array(self.W) if self.W else np.zeros((0, 2, 2))
        # Corner terms (optional; they reuse the same laser lines and planes).
        self.corner_basis, self.corner_pt = [], []
        for k, o in enumerate(self.obs):
            for i, (pt, u) in enumerate(self.lines[k]):
                a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
                a /= np.linalg.norm(a)
                Bm = np.stack([a, np.cross(u, a)])
                C2 = np.asarray(o.corner_cov_laser[i]) if o.corner_cov_laser is not None \
                    else np.eye(2) * o.laser_sigma_m ** 2
                Cl = Bm @ (R[:, :2] @ C2 @ R[:, :2].T) @ Bm.T + np.eye(2) * (opt.plane_sigma_floor_m ** 2 + 1e-8)
                self.corner_basis.append(np.linalg.solve(np.linalg.cholesky(Cl), Bm))
                self.corner_pt.append(pt)

    def residuals(self, x: np.ndarray, R0: np.ndarray, t0: np.ndarray) -> np.ndarray:
        R = R0 @ so3_exp(x[:3])
        t = t0 + x[3:]
        out = []
        if self.has_points:
            pc = self.q @ R[:, :2].T + t                       # (S, 2, 3)
            r = np.einsum("sij,sj->si", pc, self.planes[:, :3]) + self.planes[:, 3:4]
            out.append(np.einsum("sij,sj->si", self.W, r).ravel())
        if self.opt.corner_weight > 0:
            cw = np.sqrt(self.opt.corner_weight)
            rc = []
            j = 0
            for o in self.obs:
                for i in range(3):
                    p = R[:, :2] @ o.corners_laser_m[i] + t
                    rc.append(cw * (self.corner_basis[j] @ (p - self.corner_pt[j])))
                    j += 1
            out.append(np.concatenate(rc))
        return np.concatenate(out) if out else np.zeros(0)

    def plane_rms(self, R: np.ndarray, t: np.ndarray) -> float:
        """RMS distance of all laser face points to their camera planes (m)."""
        r = []
        for (k, f) in self.faces:
            o = self.obs[k]
            pts = np.asarray(o.face_points_laser_m[f], dtype=float)
            pc = pts @ R[:, :2].T + t
            r.append(pc @ o.planes_cam[f, :3] + o.planes_cam[f, 3])
        r = np.concatenate(r) if r else np.zeros(0)
        return float(np.sqrt(np.mean(r * r))) if len(r) else float("nan")


def _segment_line(pts: np.ndarray, sigma_range_m: float, floor_m: float):
    """Weighted TLS line of a laser segment -> (two virtual points (2,2),
    unit normal (2,), variance of each virtual point across the line)."""
    c0 = pts.mean(axis=0)
    q = pts - c0
    ev, V = np.linalg.eigh(q.T @ q)
    u, nu = V[:, 1], V[:, 0]
    beam = pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-9)
    sp = np.sqrt((sigma_range_m * np.abs(beam @ nu)) ** 2 + floor_m ** 2)
    w = 1.0 / sp ** 2
    for _ in range(2):  # re-fit with the weights (normal barely moves)
        c = (w[:, None] * pts).sum(axis=0) / w.sum()
        q = pts - c
        ev, V = np.linalg.eigh((w[:, None] * q).T @ q)
        u, nu = V[:, 1], V[:, 0]
        sp = np.sqrt((sigma_range_m * np.abs(beam @ nu)) ** 2 + floor_m ** 2)
        w = 1.0 / sp ** 2
    s = q @ u
    W = float(w.sum())
    s_mean = float((w * s).sum() / W)
    a = float(np.sqrt((w * (s - s_mean) ** 2).sum() / W))
    if a < 1e-4:
        return None
    base = c + s_mean * u
    return np.stack([base - a * u, base + a * u]), nu, 2.0 / W


def _plane_offset_cov(st: PlaneStats, p: np.ndarray) -> np.ndarray:
    """Covariance (len(p) x len(p)) of the fitted plane's offset along its
    normal at points ``p``: centroid term plus the correlated tilt terms."""
    a = (np.atleast_2d(p) - st.centroid) @ st.axes.T
    return st.variance_factor * (1.0 / st.weight_sum + (a / st.spread) @ a.T)


def _num_jac(fun, x: np.ndarray, h_rot: float = 1e-6, h_t: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(6):
        h = h_rot if i < 3 else h_t
        e = np.zeros(6)
        e[i] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.column_stack(cols)


_AXES = ("x", "y", "z")
_ROT_NAMES = {"x": "roll, about the laser's x axis", "y": "pitch, about the laser's y axis",
              "z": "yaw, about the laser's z axis"}


def observability_report(JtJ: np.ndarray, R: np.ndarray, mean_range_m: float,
                         cov: np.ndarray, target_sigma_deg: float, target_sigma_mm: float) -> dict:
    """Eigen-analysis of the (whitened) normal matrix ``J^T J``.

    Rotation is scaled by ``mean_range_m`` so that a rotation and a
    translation moving board points by the same distance count the same.
    The weakest direction (smallest eigenvalue) is named in words with advice."""
    L = max(mean_range_m, 0.3)
    S = np.diag([1.0 / L] * 3 + [1.0] * 3)   # x_scaled = diag(L,..,1) x  ->  J_s = J S
    H = S @ JtJ @ S
    evals, evecs = np.linalg.eigh(H)
    evals = np.maximum(evals, 0.0)
    cond = float(evals[-1] / evals[0]) if evals[0] > 0 else float("inf")
    v = evecs[:, 0]
    rot_part = float(np.linalg.norm(v[:3]))
    trans_part = float(np.linalg.norm(v[3:]))
    if rot_part >= trans_part:
        ax = _AXES[int(np.argmax(np.abs(v[:3])))]
        name = f"rotation ({_ROT_NAMES[ax]})"
        advice = {"z": "turn the AGV 20-30 deg relative to the board between observations",
                  "x": "observe the board at different lateral offsets (left/right of centre) and distances",
                  "y": "observe the board at different distances (move closer/farther by 0.5 m or more)"}[ax]
    else:
        vt_cam = v[3:] / trans_part
        vt_laser = R.T @ vt_cam
        axc = _AXES[int(np.argmax(np.abs(vt_cam)))]
        axl = _AXES[int(np.argmax(np.abs(vt_laser)))]
        name = f"translation along camera {axc} (laser {axl})"
        advice = {"z": "change the height relation: tilt the board or observe it from different distances",
                  "x": "move the AGV closer/farther and turn it 20-30 deg relative to the board",
                  "y": "move the AGV sideways and turn it 20-30 deg relative to the board"}[axl]
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    sig_deg, sig_mm = float(np.degrees(sd[:3].max())), float(sd[3:].max() * 1000.0)
    weak = (not np.isfinite(cond)) or cond > 1e8 or sig_deg > 3 * target_sigma_deg or sig_mm > 3 * target_sigma_mm
    return {
        "verdict": "weak" if weak else "ok",
        "weakest_direction": name,
        "weakest_eigenvector": v.tolist(),
        "eigenvalues_scaled": evals.tolist(),
        "condition_number": cond,
        "advice": advice if weak else "",
        "sigma_rotation_deg": sig_deg,
        "sigma_translation_mm": sig_mm,
    }


def solve_ours(observations: Sequence[LrfObservation], T_init: np.ndarray | None = None,
               options: OursOptions | None = None) -> OursSolution:
    """Our solver: robust weighted SE(3) least squares.

    Residuals (all whitened to unit a-priori variance), see :class:`_Problem`:
    * every laser segment on a face (base, FG, GH) must lie in the camera's
      plane of that face (base, ABC, ACD): two residuals per face and
      observation, from the segment's weighted line, whitened with the laser
      line and plane-fit covariances together;
    * optionally (``corner_weight`` > 0, default off) corners F, G, H -> the
      camera lines AB, AC, AD; they reuse the same lines and planes.

    Start: ``T_init`` or the paper solution projected to SO(3). Solved with
    scipy ``least_squares`` (soft-L1 loss, rotation-vector perturbation on
    the right). Whitening is recomputed once at the first solution and the
    problem solved again. Covariance: ``(J^T J)^-1`` of the whitened residuals
    at the solution (a-priori noise model), multiplied by the posterior
    variance factor s^2 when the residuals are larger than the noise model
    allows (s^2 above the 99 % quantile of chi^2_dof / dof; within it, s^2 > 1
    is what chance gives and scaling would make the covariance pessimistic)."""
    opt = options or OursOptions()
    obs = list(observations)
    t_start = time.perf_counter()
    if len(obs) < 1:
        raise ValueError("solve_ours needs >= 1 observation")
    if T_init is None:
        if len(obs) < 2:
            raise ValueError("solve_ours without T_init needs >= 2 observations (paper initialisation)")
        R_raw, t0, info0 = solve_paper(obs)
        R0 = info0["R_so3"]
    else:
        R0 = np.asarray(T_init, dtype=float)[:3, :3]
        t0 = np.asarray(T_init, dtype=float)[:3, 3]
    prob = _Problem(obs, opt)
    R, t = R0.copy(), t0.copy()
    res = None
    for _ in range(2):
        prob.update_weights(R, t)
        fun = lambda x, R_=R, t_=t: prob.residuals(x, R_, t_)
        res = least_squares(fun, np.zeros(6), method="trf", loss=opt.loss, f_scale=opt.f_scale,
                            x_scale=np.array([0.01] * 3 + [0.01] * 3), max_nfev=opt.max_nfev)
        R = R @ so3_exp(res.x[:3])
        t = t + res.x[3:]
    prob.update_weights(R, t)
    fun = lambda x: prob.residuals(x, R, t)
    r = fun(np.zeros(6))
    J = _num_jac(fun, np.zeros(6))
    JtJ = J.T @ J
    dof = max(len(r) - 6, 1)
    s2 = float(r @ r / dof)
    try:
        cov = np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(JtJ)
    from scipy.stats import chi2 as _chi2
    if opt.scale_covariance and s2 > float(_chi2.ppf(0.99, dof)) / dof:
        cov = cov * s2
    T = make_T(R, t)
    mean_range = float(np.mean(np.linalg.norm(np.concatenate([o.corners_laser_m for o in obs]), axis=1)))
    obsv = observability_report(JtJ, R, mean_range, cov, opt.target_sigma_deg, opt.target_sigma_mm)
    plane_rms = prob.plane_rms(R, t) if prob.has_points else float("nan")
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    metrics = {
        "point_to_line_m": point_to_line_error_m(R, t, obs),
        "plane_rms_m": plane_rms,
        "variance_factor": s2,
        "residuals": len(r),
        "nfev": int(res.nfev) if res is not None else 0,
        "sigma_rotation_deg": float(np.degrees(sd[:3].max())),
        "sigma_translation_mm": float(sd[3:].max() * 1000.0),
        "condition_number": obsv["condition_number"],
        "runtime_s": time.perf_counter() - t_start,
    }
    return OursSolution(T, cov, metrics, obsv)


def rotation_error_of_raw(R_raw: np.ndarray, R_true: np.ndarray) -> float:
    """Rotation error (deg) of a possibly non-orthonormal paper matrix, measured
    on its nearest rotation (the angle of a non-rotation is undefined)."""
    Rn = project_to_so3(R_raw)
    return float(np.degrees(np.linalg.norm(so3_log(Rn.T @ R_true))))
