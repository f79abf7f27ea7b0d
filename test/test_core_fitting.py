import numpy as np
import pytest

from lidar_cam_calib.core.fitting import (FitError, fit_line_2d_lsq, fit_plane_lsq, intersect_lines_2d,
                                          intersect_planes, ransac_line_2d, ransac_plane)


def test_ransac_plane_recovers_plane_with_outliers():
    rng = np.random.default_rng(0)
    n_true = np.array([0.2, -0.3, 0.93])
    n_true /= np.linalg.norm(n_true)
    uv = rng.uniform(-1, 1, (500, 2))
    a = np.cross(n_true, [1, 0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n_true, a)
    pts = uv[:, :1] * a + uv[:, 1:] * b - 2.0 * n_true + rng.normal(0, 0.002, (500, 1)) * n_true
    pts = np.vstack([pts, rng.uniform(-2, 2, (200, 3))])
    n, d, mask = ransac_plane(pts, 0.01, 200, np.random.default_rng(1), min_inliers=100)
    assert abs(abs(n @ n_true) - 1) < 1e-4 and abs(d - 2.0) < 2e-3 and d >= 0
    assert mask[:500].mean() > 0.97 and mask[500:].mean() < 0.1
    n2, d2, m2 = ransac_plane(pts, 0.01, 200, np.random.default_rng(1), min_inliers=100)
    assert np.array_equal(m2, mask)  # deterministic given rng


def test_line_fit_and_intersections():
    rng = np.random.default_rng(2)
    s = np.linspace(0, 1, 200)
    xy = np.column_stack([1 + s, 2 + 0.5 * s]) + rng.normal(0, 1e-3, (200, 2))
    xy = np.vstack([xy, rng.uniform(0, 3, (50, 2))])
    p, u, m = ransac_line_2d(xy, 0.005, 100, rng)
    assert abs(abs(u @ np.array([2, 1]) / np.sqrt(5)) - 1) < 1e-4
    c, u2 = fit_line_2d_lsq(xy[:200])
    X = intersect_lines_2d(c, u2, np.array([1.0, 0.0]), np.array([0.0, 1.0]))
    assert abs(X[0] - 1.0) < 1e-9 and abs(X[1] - 2.0) < 3e-3
    with pytest.raises(FitError):
        intersect_lines_2d(c, u2, c + 1, u2)


def test_intersect_planes_and_degenerate():
    p, u = intersect_planes((np.array([1.0, 0, 0]), -1.0), (np.array([0, 1.0, 0]), -2.0))
    assert np.allclose(p, [1, 2, 0]) and np.allclose(abs(u), [0, 0, 1])
    with pytest.raises(FitError):
        intersect_planes((np.array([1.0, 0, 0]), 0.0), (np.array([1.0, 0, 0]), 1.0))
    with pytest.raises(FitError):
        fit_plane_lsq(np.zeros((2, 3)))
