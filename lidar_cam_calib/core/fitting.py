"""Robust geometric fitting (ROS-free): planes in 3D, lines in 2D, intersections.

Conventions
-----------
* A plane is ``(n, d)`` with unit normal ``n`` and ``n . p + d = 0`` for points
  ``p`` on it (metres). Fitted planes are oriented so that ``d >= 0``: the
  normal points towards the origin of the frame the points are expressed in
  (i.e. towards the sensor that measured them).
* A 2D or 3D line is ``(point, unit_dir)``; fitted lines put ``point`` at the
  centroid of the inliers.
* RANSAC is deterministic given the ``numpy.random.Generator`` passed in; all
  hypotheses are drawn at once and scored in one vectorised pass (chunked to
  bound memory).

Errors raise :class:`FitError` (a ``ValueError``) with a human-readable reason.
"""
from __future__ import annotations

import numpy as np

from .errors import CalibError


class FitError(CalibError, ValueError):
    """A fit could not be made; ``str(err)`` says why."""


_CHUNK_ELEMS = 4_000_000  # hypotheses x points evaluated per chunk


# ----------------------------------------------------------------------------
# Planes
# ----------------------------------------------------------------------------
def _scatter(p: np.ndarray, weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(Weighted) centroid and scatter matrix of (N, k) points."""
    if weights is None:
        c = p.mean(axis=0)
        q = p - c
        return c, q.T @ q
    w = np.asarray(weights, dtype=float).ravel()
    c = (w[:, None] * p).sum(axis=0) / w.sum()
    q = p - c
    return c, (w[:, None] * q).T @ q


def fit_plane_lsq(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Total-least-squares plane through (N,3) points (N >= 3).

    Returns ``(n, d)``, ``n`` unit, oriented with ``d >= 0``."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if p.shape[0] < 3:
        raise FitError(f"plane fit needs >= 3 points, got {p.shape[0]}")
    c, S = _scatter(p, weights)
    evals, evecs = np.linalg.eigh(S)
    if evals[1] <= 1e-12 * max(evals[2], 1e-300):
        raise FitError("plane fit: points are collinear")
    n = evecs[:, 0]
    d = -float(n @ c)
    if d < 0:
        n, d = -n, -d
    return n / np.linalg.norm(n), d


def plane_distances(points: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """Signed distances (N,) of points to the plane ``(n, d)`` in metres."""
    return np.asarray(points, dtype=float) @ np.asarray(n, dtype=float) + float(d)


def ransac_plane(points: np.ndarray, threshold_m: float, iterations: int,
                 rng: np.random.Generator, min_inliers: int = 3,
                 refit_iterations: int = 2) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane with least-squares refit on the inliers.

    ``iterations`` random 3-point hypotheses are scored together; the one with
    most points within ``threshold_m`` (scalar, or (N,) per-point thresholds
    for heteroscedastic noise such as stereo depth) wins, then the plane is refitted by
    total least squares on its inliers (``refit_iterations`` times, recomputing
    the inlier set each time). Returns ``(n, d, inlier_mask)``.
    Raises :class:`FitError` when fewer than ``min_inliers`` points agree."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    N = p.shape[0]
    if N < max(3, min_inliers):
        raise FitError(f"plane RANSAC needs >= {max(3, min_inliers)} points, got {N}")
    idx = rng.integers(0, N, size=(int(iterations), 3))
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    ln = np.linalg.norm(nrm, axis=1)
    good = ln > 1e-9
    if not np.any(good):
        raise FitError("plane RANSAC: all samples degenerate (collinear points)")
    nrm = nrm[good] / ln[good, None]
    dd = -np.einsum("ij,ij->i", nrm, a[good])
    pf = p.astype(np.float32)
    thr = np.asarray(threshold_m, dtype=np.float32)
    thr_col = thr.reshape(-1, 1) if thr.ndim else thr
    counts = np.empty(nrm.shape[0], dtype=np.int64)
    step = max(1, _CHUNK_ELEMS // max(N, 1))
    for s in range(0, nrm.shape[0], step):
        dist = np.abs(pf @ nrm[s:s + step].T.astype(np.float32) + dd[s:s + step].astype(np.float32))
        counts[s:s + step] = (dist < thr_col).sum(axis=0)
    best = int(np.argmax(counts))
    if counts[best] < min_inliers:
        raise FitError(f"plane RANSAC: best plane has {int(counts[best])} inliers < {min_inliers}")
    n, d = nrm[best], float(dd[best])
    mask = np.abs(p @ n + d) < threshold_m
    for _ in range(max(0, refit_iterations)):
        if mask.sum() < 3:
            break
        n_new, d_new = fit_plane_lsq(p[mask])
        mask_new = np.abs(p @ n_new + d_new) < threshold_m
        if mask_new.sum() < 3:
            break
        n, d, mask = n_new, d_new, mask_new
    if d < 0:
        n, d = -n, -d
    if mask.sum() < min_inliers:
        raise FitError(f"plane RANSAC: refitted plane has {int(mask.sum())} inliers < {min_inliers}")
    return n, d, mask


def intersect_planes(plane1: tuple[np.ndarray, float], plane2: tuple[np.ndarray, float]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Line where two planes ``(n, d)`` meet: ``(point, unit_dir)``.

    ``point`` is the point of the line closest to the origin; ``unit_dir`` is
    ``n1 x n2`` normalised. Raises :class:`FitError` for (near-)parallel planes."""
    n1, d1 = np.asarray(plane1[0], dtype=float), float(plane1[1])
    n2, d2 = np.asarray(plane2[0], dtype=float), float(plane2[1])
    u = np.cross(n1, n2)
    s = float(np.linalg.norm(u))
    if s < 1e-6:
        raise FitError("planes are parallel: no intersection line")
    u = u / s
    # Solve n1.p = -d1, n2.p = -d2, u.p = 0.
    A = np.stack([n1, n2, u])
    point = np.linalg.solve(A, np.array([-d1, -d2, 0.0]))
    return point, u


def intersect_three_planes(planes: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """The single point common to three planes (raises FitError if degenerate)."""
    A = np.stack([np.asarray(p[0], dtype=float) for p in planes])
    b = -np.array([float(p[1]) for p in planes])
    if abs(np.linalg.det(A)) < 1e-9:
        raise FitError("three planes do not meet in a single point")
    return np.linalg.solve(A, b)


def point_line_distance(points: np.ndarray, line_point: np.ndarray, line_dir: np.ndarray) -> np.ndarray:
    """Euclidean distance (N,) of (N,D) points to a line ``(point, dir)`` (D = 2 or 3)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))
    u = np.asarray(line_dir, dtype=float)
    u = u / np.linalg.norm(u)
    q = p - np.asarray(line_point, dtype=float)
    perp = q - np.outer(q @ u, u)
    return np.linalg.norm(perp, axis=1)


# ----------------------------------------------------------------------------
# 2D lines
# ----------------------------------------------------------------------------
def fit_line_2d_lsq(xy: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares 2D line through (N,2) points (N >= 2): ``(centroid, unit_dir)``."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    if p.shape[0] < 2:
        raise FitError(f"line fit needs >= 2 points, got {p.shape[0]}")
    c, S = _scatter(p, weights)
    evals, evecs = np.linalg.eigh(S)
    if evals[1] <= 1e-18:
        raise FitError("line fit: all points coincide")
    u = evecs[:, 1]
    return c, u / np.linalg.norm(u)


def line_2d_distances(xy: np.ndarray, point: np.ndarray, unit_dir: np.ndarray) -> np.ndarray:
    """Signed perpendicular distances (N,) of 2D points to a line (left of dir is +)."""
    q = np.asarray(xy, dtype=float) - np.asarray(point, dtype=float)
    u = np.asarray(unit_dir, dtype=float)
    return q[:, 1] * u[0] - q[:, 0] * u[1]


def ransac_line_2d(xy: np.ndarray, threshold_m: float, iterations: int,
                   rng: np.random.Generator, min_inliers: int = 2,
                   refit_iterations: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RANSAC 2D line + total-least-squares refit: ``(point, unit_dir, inlier_mask)``."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    N = p.shape[0]
    if N < max(2, min_inliers):
        raise FitError(f"line RANSAC needs >= {max(2, min_inliers)} points, got {N}")
    idx = rng.integers(0, N, size=(int(iterations), 2))
    a, b = p[idx[:, 0]], p[idx[:, 1]]
    u = b - a
    ln = np.linalg.norm(u, axis=1)
    good = ln > 1e-9
    if not np.any(good):
        raise FitError("line RANSAC: all samples degenerate")
    u = u[good] / ln[good, None]
    a = a[good]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    off = -np.einsum("ij,ij->i", nrm, a)
    counts = np.empty(nrm.shape[0], dtype=np.int64)
    step = max(1, _CHUNK_ELEMS // max(N, 1))
    for s in range(0, nrm.shape[0], step):
        dist = np.abs(p @ nrm[s:s + step].T + off[s:s + step])
        counts[s:s + step] = (dist < threshold_m).sum(axis=0)
    best = int(np.argmax(counts))
    if counts[best] < min_inliers:
        raise FitError(f"line RANSAC: best line has {int(counts[best])} inliers < {min_inliers}")
    point, direction = a[best], u[best]
    mask = np.abs(line_2d_distances(p, point, direction)) < threshold_m
    for _ in range(max(0, refit_iterations)):
        if mask.sum() < 2:
            break
        pt, dr = fit_line_2d_lsq(p[mask])
        m2 = np.abs(line_2d_distances(p, pt, dr)) < threshold_m
        if m2.sum() < 2:
            break
        point, direction, mask = pt, dr, m2
    if mask.sum() < min_inliers:
        raise FitError(f"line RANSAC: refitted line has {int(mask.sum())} inliers < {min_inliers}")
    return point, direction, mask


def intersect_lines_2d(p1: np.ndarray, d1: np.ndarray, p2: np.ndarray, d2: np.ndarray,
                       min_angle_rad: float = 1e-3) -> np.ndarray:
    """Intersection point of two 2D lines ``p1 + s d1`` and ``p2 + t d2``.

    Raises :class:`FitError` when the lines are closer to parallel than
    ``min_angle_rad``."""
    p1, d1, p2, d2 = (np.asarray(v, dtype=float) for v in (p1, d1, p2, d2))
    cr = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(cr) < np.sin(min_angle_rad) * np.linalg.norm(d1) * np.linalg.norm(d2):
        raise FitError("2D lines are (nearly) parallel: no intersection")
    q = p2 - p1
    s = (q[0] * d2[1] - q[1] * d2[0]) / cr
    return p1 + s * d1
