"""Control-curve-based non-rigid refinement (paper 001, Section 3.3), ROS-free.

After the rigid registration, the matched object centroids are the control points: one
curve through the LiDAR centroids and one through their SfM partners, both ordered along
the drive. Each curve segment between neighbouring control points is cut into the same
number of equal bins, so that bin ``j`` of a LiDAR segment belongs to bin ``j`` of the SfM
segment; every LiDAR point goes to its nearest LiDAR bin and moves by that bin's
translation (SfM bin minus LiDAR bin). As the paper says, this is a local, piecewise
translation that bends the LiDAR cloud onto the camera's where the SfM scale drifts or the
moving car stretched the sweep.

Curve: an interpolating cubic B-spline (scipy ``make_interp_spline``; quadratic or linear
when there are fewer control points) in the chord-length parameter. The paper uses a NURBS;
with unit weights a NURBS is this B-spline, and there is nothing in the data to set other
weights from, so the rational part adds nothing. Interpolating (not smoothing) keeps each
segment between its two control points, which is what the bin correspondence needs.

:func:`curve_refine` returns the moved points and the displacement field as a callable, so
the final PnP can push LiDAR centroids through the same deformation.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..core.errors import CalibError


@dataclasses.dataclass
class CurveField:
    """The fitted deformation: ``lidar_bins`` (B,3) on the LiDAR curve and their
    ``shift`` (B,3) to the SfM curve. ``__call__(points)`` moves points by the shift of
    their nearest bin (points farther than ``reach_m`` from the curve are moved by the
    shift faded linearly to zero at ``2 * reach_m``; 0 = no fade)."""
    lidar_bins: np.ndarray
    shift: np.ndarray
    order: np.ndarray          # control pair indices in curve order
    reach_m: float = 0.0

    def __post_init__(self) -> None:
        self._tree = cKDTree(self.lidar_bins)

    def displacement(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 3)
        d, j = self._tree.query(p)
        s = self.shift[j]
        if self.reach_m > 0:
            fade = np.clip(2.0 - d / self.reach_m, 0.0, 1.0)
            s = s * fade[:, None]
        return s

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float).reshape(-1, 3)
        return p + self.displacement(p)

    @property
    def max_shift_m(self) -> float:
        return float(np.linalg.norm(self.shift, axis=1).max()) if len(self.shift) else 0.0


def _drive_order(ctrl: np.ndarray) -> np.ndarray:
    """Order control points along their main horizontal direction (the street)."""
    c = ctrl - ctrl.mean(0)
    xy = c[:, :2]
    if len(ctrl) < 2:
        return np.arange(len(ctrl))
    _, _, Vt = np.linalg.svd(xy, full_matrices=False)
    return np.argsort(xy @ Vt[0])


def _spline(ctrl: np.ndarray):
    from scipy.interpolate import make_interp_spline
    seg = np.linalg.norm(np.diff(ctrl, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(np.maximum(seg, 1e-6))])
    k = min(3, len(ctrl) - 1)
    return make_interp_spline(u, ctrl, k=k), u


def curve_refine(lidar_ctrl: np.ndarray, sfm_ctrl: np.ndarray, bins_per_segment: int = 10,
                 reach_m: float = 0.0, max_shift_m: float | None = None) -> CurveField:
    """The deformation that takes the LiDAR control points (already rigidly registered, in
    the SfM frame) onto their SfM partners. ``lidar_ctrl[i]`` matches ``sfm_ctrl[i]``.

    Raises :class:`CalibError` with fewer than 2 pairs, or when a control shift is larger
    than ``max_shift_m`` (the rigid registration is then wrong, not locally distorted)."""
    a = np.asarray(lidar_ctrl, float).reshape(-1, 3)
    b = np.asarray(sfm_ctrl, float).reshape(-1, 3)
    if len(a) != len(b):
        raise CalibError(f"curve refinement: {len(a)} LiDAR and {len(b)} SfM control points")
    if len(a) < 2:
        raise CalibError(f"curve refinement needs at least 2 matched objects, got {len(a)}")
    d = np.linalg.norm(b - a, axis=1)
    if max_shift_m is not None and d.max() > max_shift_m:
        raise CalibError(f"curve refinement: a matched object is {d.max():.2f} m from its partner after the "
                         f"rigid registration (max {max_shift_m} m): the registration is wrong")
    order = _drive_order(0.5 * (a + b))
    a, b = a[order], b[order]
    # drop repeated control points (two objects at one place would make the parameter degenerate)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(a, axis=0), axis=1) > 1e-3])
    a, b, order = a[keep], b[keep], order[keep]
    if len(a) < 2:
        raise CalibError("curve refinement: the matched objects are all at one place")
    sa, ua = _spline(a)
    sb, ub = _spline(b)
    n = max(1, int(bins_per_segment))
    la, lb = [], []
    for i in range(len(a) - 1):
        # bin centres of segment i, the same fractions of the segment on both curves
        f = (np.arange(n) + 0.5) / n
        la.append(sa(ua[i] + f * (ua[i + 1] - ua[i])))
        lb.append(sb(ub[i] + f * (ub[i + 1] - ub[i])))
    # the control points themselves are bins too (their shift is exactly the pair's difference)
    la.append(a)
    lb.append(b)
    la, lb = np.concatenate(la), np.concatenate(lb)
    return CurveField(la, lb - la, order, float(reach_m))


__all__ = ["CurveField", "curve_refine"]
