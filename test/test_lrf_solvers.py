import numpy as np

from lidar_cam_calib.core.geometry import pose_errors
from lidar_cam_calib.bench.lrf import synthetic_observations
from lidar_cam_calib.lrf.solvers import (paper_adaptive, point_to_line_error_m, resolve_assignment,
                                         solve_ours, solve_paper)

NOISELESS = dict(laser_sigma_m=1e-7, depth_k=1e-10, depth_floor_m=1e-8)


def test_exact_recovery_without_noise():
    obs, T = synthetic_observations(3, 0, **NOISELESS)
    R, t, info = solve_paper(obs)
    assert info["orthonormality_error"] < 1e-4
    er, et = pose_errors(info["T"], T)
    assert er < 1e-3 and et < 0.01
    assert point_to_line_error_m(R, t, obs) < 1e-5
    sol = solve_ours(obs)
    er, et = pose_errors(sol.T, T)
    assert er < 1e-3 and et < 0.01


def test_noisy_ours_beats_paper_with_many_observations():
    errs = {"paper": [], "ours": []}
    for seed in range(3):
        obs, T = synthetic_observations(12, 10 + seed)
        _, _, info = solve_paper(obs)
        errs["paper"].append(pose_errors(info["T"], T))
        sol = solve_ours(obs)
        errs["ours"].append(pose_errors(sol.T, T))
        assert np.isfinite(sol.covariance).all() and sol.observability["verdict"] in ("ok", "weak")
    p, o = np.mean(errs["paper"], axis=0), np.mean(errs["ours"], axis=0)
    assert o[0] < 0.5 and o[1] < 10.0
    assert o[0] < p[0] and o[1] < p[1]


def test_assignment_swap_is_detected():
    obs, T = synthetic_observations(4, 3)
    bad = [o.swapped() for o in obs]
    fixed, flags = resolve_assignment(bad)
    assert all(flags)
    _, _, info = solve_paper(fixed)
    assert pose_errors(info["T"], T)[0] < 3.0


def test_paper_adaptive_stops():
    obs, T = synthetic_observations(8, 4)
    r = paper_adaptive(iter(obs), threshold_m=0.05)
    assert r.converged and 2 <= r.observations_used < 8
    r2 = paper_adaptive(iter(obs), threshold_m=1e-6)
    assert not r2.converged and r2.observations_used == 8
