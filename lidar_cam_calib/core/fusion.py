"""Fusion of independent extrinsic estimates of one sensor pair (ROS-free).

A method that calibrates on windows of data (``targetless``: one window of
frames from a moving car) gets one estimate ``(T_i, C_i)`` per accepted
window. Each estimate's error is modelled as ``u_i + s``: ``u_i`` is the
window's own error (covariance ``C_i - F``) and ``s`` an error every window
shares (covariance ``F``: the sensor's edge placement, the camera model, the
clock), which averaging over windows does not reduce.

The fused estimate is the information-weighted mean of the ``T_i`` in the
package's perturbation convention (``T = exp(dθ)·R, t + dt``, rotation
first), iterated about the running mean. Its covariance is
``(Σ (C_i - F)^-1)^-1``, multiplied by the Birge ratio ``χ²/dof`` when the
windows scatter more than their covariances say (never less than 1), plus
``F``. With three or more windows, a window that disagrees with the fusion of
the others beyond the ``1 - outlier_p`` quantile of χ² with 6 degrees of
freedom is left out (the worst first, one at a time) and reported; the
threshold is scaled by the common scatter of the other windows (the median
χ² of their pairwise differences over its expected value, at least 1), so
covariances that are all too small widen the result instead of dropping
windows. ``agree`` is False when exactly two windows remain and their
difference is beyond that quantile: neither can be told to be the wrong one
(a caller may wait for a third).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import chi2 as _chi2

from .geometry import so3_exp, so3_log


@dataclasses.dataclass
class FusedEstimate:
    T: np.ndarray            # 4x4 fused extrinsic
    cov: np.ndarray          # 6x6 in the package convention
    used: list               # indices of the estimates fused
    dropped: list            # [(index, chi2 against the others' fusion)]
    chi2: float              # scatter of the used estimates about the fused one
    dof: int                 # 6 * (len(used) - 1)
    birge: float             # max(1, chi2 / dof); 1 for one estimate
    agree: bool = True       # False: two estimates left that differ beyond the outlier quantile


def _delta(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """``T`` about ``T_ref`` in the package convention: (rotation vector of R R_ref^T, t - t_ref)."""
    return np.concatenate([so3_log(T[:3, :3] @ T_ref[:3, :3].T), T[:3, 3] - T_ref[:3, 3]])


def _apply(T_ref: np.ndarray, d: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(d[:3]) @ T_ref[:3, :3]
    T[:3, 3] = T_ref[:3, 3] + d[3:]
    return T


def _own(C: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``C - F`` kept positive definite (a window can never be known better than ``C`` says)."""
    D = C - F
    w, V = np.linalg.eigh(0.5 * (D + D.T))
    floor = 1e-6 * max(float(np.max(np.diag(C))), 1e-18)
    return (V * np.maximum(w, floor)) @ V.T


def _mean(Ts: list, Ws: list, iterations: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Information-weighted mean of ``Ts`` (weights ``Ws``) and the summed information."""
    H = sum(Ws)
    T = Ts[int(np.argmax([np.trace(W) for W in Ws]))].copy()
    for _ in range(iterations):
        g = sum(W @ _delta(Ti, T) for Ti, W in zip(Ts, Ws))
        d = np.linalg.solve(H, g)
        T = _apply(T, d)
        if np.linalg.norm(d) < 1e-12:
            break
    return T, H


def fuse_estimates(Ts: list, covs: list, shared: np.ndarray | None = None, outlier_p: float = 0.001
                   ) -> FusedEstimate:
    """Fuse independent estimates ``Ts`` (4x4) with covariances ``covs`` (6x6); ``shared``: the part of
    every covariance that all estimates have in common (see the module text). Raises ``ValueError`` on no
    estimate or a covariance that is not finite."""
    if not Ts:
        raise ValueError("no estimate to fuse")
    if len(Ts) != len(covs):
        raise ValueError(f"{len(Ts)} estimates but {len(covs)} covariances")
    F = np.zeros((6, 6)) if shared is None else np.asarray(shared, float)
    Cs = [np.asarray(C, float) for C in covs]
    for i, C in enumerate(Cs):
        if C.shape != (6, 6) or not np.all(np.isfinite(C)):
            raise ValueError(f"estimate {i}: covariance is not a finite 6x6 matrix")
    Cs_own = [_own(C, F) for C in Cs]
    Ws = [np.linalg.inv(C) for C in Cs_own]
    Ts = [np.asarray(T, float) for T in Ts]
    used = list(range(len(Ts)))
    dropped = []
    limit = float(_chi2.ppf(1.0 - outlier_p, 6))
    med6 = float(_chi2.ppf(0.5, 6))

    def pair(i, j):  # chi2 of two windows' difference (the shared error cancels)
        d = _delta(Ts[i], Ts[j])
        return float(d @ np.linalg.solve(Cs_own[i] + Cs_own[j], d))

    while len(used) >= 3:
        c2s = []
        for i in used:
            rest = [j for j in used if j != i]
            T_r, H_r = _mean([Ts[j] for j in rest], [Ws[j] for j in rest])
            d = _delta(Ts[i], T_r)
            c2s.append(float(d @ np.linalg.solve(Cs_own[i] + np.linalg.inv(H_r), d)))
        # judged against the common scatter of the other windows, pair by pair (covariances that are all
        # too small make every window look far from the others: that is for the Birge ratio, not for
        # leaving windows out; pairs keep the suspect window out of the scale it is judged by)
        k = int(np.argmax(c2s))
        others = [j for j in used if j != used[k]]
        common = max(1.0, float(np.median([pair(i, j) for a, i in enumerate(others) for j in others[a + 1:]]))
                     / med6)
        if c2s[k] / common <= limit:
            break
        dropped.append((used[k], c2s[k]))
        used.remove(used[k])
    T, H = _mean([Ts[i] for i in used], [Ws[i] for i in used])
    c2 = float(sum(_delta(Ts[i], T) @ Ws[i] @ _delta(Ts[i], T) for i in used))
    dof = 6 * (len(used) - 1)
    birge = max(1.0, c2 / dof) if dof > 0 else 1.0
    cov = np.linalg.inv(H) * birge + F
    return FusedEstimate(T=T, cov=0.5 * (cov + cov.T), used=used, dropped=dropped, chi2=c2, dof=dof, birge=birge,
                         agree=not (len(used) == 2 and c2 > limit))


__all__ = ["FusedEstimate", "fuse_estimates"]
