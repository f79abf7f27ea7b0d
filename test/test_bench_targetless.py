"""The targetless bench's clock prior and its per-window records (no simulation: these are the pieces that
decide what the calibrator is told and what the JSON keeps)."""
from __future__ import annotations

import math
import types

import numpy as np

from lidar_cam_calib.bench.targetless import FAMILY_OFFSET_SIGMA_S, _numeric, _offset_prior


def test_offset_prior_unknown_is_zero_with_the_family_spread():
    run = types.SimpleNamespace(time_offset_s=0.07)
    assert _offset_prior(run, 5, False, 0.0005) == (0.0, float(FAMILY_OFFSET_SIGMA_S))


def test_offset_prior_known_carries_a_drawn_error_of_the_told_sigma():
    run = types.SimpleNamespace(time_offset_s=0.07)
    told, sigma = _offset_prior(run, 5, True, 0.0005)
    assert sigma == 0.0005 and told != 0.07
    assert _offset_prior(run, 5, True, 0.0005) == (told, sigma)      # the same seed, the same draw
    errs = np.array([_offset_prior(run, s, True, 0.0005)[0] - 0.07 for s in range(400)])
    # the drawn errors have the sigma the calibrator is told (the covariance check relies on it)
    assert abs(errs.mean()) < 4 * 0.0005 / math.sqrt(400)
    assert 0.85 * 0.0005 < errs.std() < 1.15 * 0.0005
    assert _offset_prior(run, 5, True, 0.0) == (0.07, 0.0)             # an exact clock when asked


def test_numeric_keeps_numbers_only():
    m = {"edge_inliers": np.float64(0.61), "edge_views": np.int64(8), "hausdorff_m": 0.02, "flag": True,
         "why": "text", "arr": [1, 2]}
    out = _numeric(m)
    assert out == {"edge_inliers": 0.61, "edge_views": 8.0, "hausdorff_m": 0.02}
    assert all(type(v) is float for v in out.values()) and _numeric(None) == {}


def test_perturbed_edge_starts_report_the_edge_stage_basin():
    """The learned methods' protocol applied to the edge refinement alone, on the synthetic board scene:
    from the truth and from small perturbations it stays or comes back; the record says how far each
    start was and where it ended."""
    from test_targetless_edges import _views

    from lidar_cam_calib.bench.targetless import perturbed_edge_starts
    cam, X, views = _views()
    axes = (X[:3, :3] @ np.array([1.0, 0.0, 0.0]), X[:3, :3] @ np.array([0.0, 0.0, 1.0]))
    pts = np.concatenate([v.pts for v in views])
    out = perturbed_edge_starts(views, cam, X, axes, 3, pts, levels=((0.3, 0.03), (20.0, 1.0)))
    f0 = out["from_official"]
    assert f0["fit"] and f0["rotation_error_deg"] < 0.1 and f0["x_error_px"] < 0.5
    near, far = out["levels"]
    assert near["starts"] == 3 and len(near["runs"]) == 3
    assert all(0.0 < r["start_rotation_deg"] <= 0.3 * math.sqrt(3) + 1e-9 for r in near["runs"])
    assert near["converged"] == 3 and near["median_rotation_error_deg"] < 0.2
    # 20 deg and 1 m away the local fit does not come back (the coarse search is what reaches that far)
    assert far["converged"] < 3
