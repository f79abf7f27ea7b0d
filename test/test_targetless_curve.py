"""The control-curve non-rigid refinement (paper 001, Section 3.3)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_cam_calib.core.errors import CalibError
from lidar_cam_calib.targetless.curve import curve_refine


def _street(rng, n_obj=9):
    """Object centroids along a gently curved street and points around them."""
    s = np.sort(rng.uniform(-30, 30, n_obj))
    side = 6.0 * np.sign(rng.standard_normal(n_obj))
    ctrl = np.column_stack([s, side + 0.002 * s ** 2, rng.uniform(0.5, 2.0, n_obj)])
    pts = np.concatenate([c + rng.normal(0, 0.3, (40, 3)) for c in ctrl])
    return ctrl, pts


def _stretch(p):
    """A smooth non-rigid distortion: stretch along the drive growing with distance, and a bend."""
    q = p.copy()
    q[:, 0] = p[:, 0] * 1.02
    q[:, 1] = p[:, 1] + 0.0004 * p[:, 0] ** 2
    return q


def test_curve_takes_a_stretched_cloud_back():
    rng = np.random.default_rng(3)
    ctrl, pts = _street(rng)
    lid_ctrl, lid_pts = _stretch(ctrl), _stretch(pts)   # LiDAR side distorted
    f = curve_refine(lid_ctrl, ctrl, bins_per_segment=12)
    # control points land exactly on their partners
    np.testing.assert_allclose(f(lid_ctrl), ctrl, atol=1e-9)
    before = np.linalg.norm(lid_pts - pts, axis=1)
    after = np.linalg.norm(f(lid_pts) - pts, axis=1)
    assert np.median(before) > 0.2
    assert np.median(after) < 0.25 * np.median(before), (np.median(before), np.median(after))


def test_curve_is_identity_when_aligned_and_refuses_bad_input():
    rng = np.random.default_rng(4)
    ctrl, pts = _street(rng, 5)
    f = curve_refine(ctrl, ctrl)
    np.testing.assert_allclose(f(pts), pts, atol=1e-12)
    assert f.max_shift_m == 0.0
    with pytest.raises(CalibError, match="at least 2"):
        curve_refine(ctrl[:1], ctrl[:1])
    with pytest.raises(CalibError, match="registration is wrong"):
        curve_refine(ctrl, ctrl + [3.0, 0, 0], max_shift_m=1.0)
    with pytest.raises(CalibError, match="control points"):
        curve_refine(ctrl, ctrl[:3])
    # two pairs: a straight segment still works (linear spline)
    g = curve_refine(ctrl[:2], ctrl[:2] + [0.1, 0, 0])
    np.testing.assert_allclose(g.displacement(ctrl[:2]), [[0.1, 0, 0]] * 2, atol=1e-9)
    # the fade leaves far points alone
    h = curve_refine(ctrl, ctrl + [0.2, 0, 0], reach_m=1.0)
    far = ctrl.mean(0) + [0, 0, 50.0]
    np.testing.assert_allclose(h(far[None]), far[None], atol=1e-12)
