"""Fusion of independent extrinsic estimates (core.fusion): the weighted mean, its covariance, the shared
floor that averaging never reduces, the Birge inflation and the outlier window."""
import numpy as np
import pytest

from lidar_cam_calib.core.fusion import fuse_estimates
from lidar_cam_calib.core.geometry import make_T, so3_exp, so3_log


def _perturb(T, d):
    return make_T(so3_exp(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])


def _err(T, T0):
    return np.concatenate([so3_log(T[:3, :3] @ T0[:3, :3].T), T[:3, 3] - T0[:3, 3]])


T0 = make_T(so3_exp(np.array([1.2, -0.4, 0.3])), np.array([0.3, -0.1, 1.2]))


def test_one_estimate_is_returned_unchanged():
    C = np.diag([1e-5] * 3 + [1e-4] * 3)
    f = fuse_estimates([T0], [C], shared=0.2 * C)
    assert np.allclose(f.T, T0) and np.allclose(f.cov, C)
    assert f.used == [0] and f.dropped == [] and f.birge == 1.0


def test_weighted_mean_and_covariance_follow_the_information():
    # two estimates, the second four times as precise: the mean sits 1/5 of the way from it to the first
    C1 = np.diag([4e-6] * 3 + [4e-4] * 3)
    C2 = C1 / 4
    d = np.array([2e-3, -1e-3, 1e-3, 0.02, 0.01, -0.03])
    f = fuse_estimates([_perturb(T0, d), T0], [C1, C2])
    assert np.allclose(_err(f.T, T0), d / 5, atol=1e-7)
    assert np.allclose(np.diag(f.cov), np.diag(C1) / 5 * max(1.0, f.chi2 / 6))


def test_many_consistent_estimates_are_honest_and_keep_the_shared_floor():
    rng = np.random.default_rng(3)
    own = np.diag([(0.2 * np.pi / 180) ** 2] * 3 + [0.03 ** 2] * 3)
    F = np.diag([(0.05 * np.pi / 180) ** 2] * 3 + [0.01 ** 2] * 3)
    m2 = []
    for _ in range(200):
        s = rng.multivariate_normal(np.zeros(6), F)   # shared by every window of the drive
        Ts = [_perturb(T0, s + rng.multivariate_normal(np.zeros(6), own)) for _ in range(8)]
        f = fuse_estimates(Ts, [own + F] * 8, shared=F)
        e = _err(f.T, T0)
        m2.append(e @ np.linalg.solve(f.cov, e))
        # never below the shared floor, far below one window
        assert np.all(np.diag(f.cov) >= np.diag(F)) and np.all(np.diag(f.cov) < np.diag(own + F) / 2.5)
    assert 4.5 < np.mean(m2) < 7.5   # chi-square with 6 dof: mean 6 (the Birge factor only widens)


def test_scatter_beyond_the_covariances_widens_the_fused_covariance():
    rng = np.random.default_rng(5)
    C = np.diag([1e-6] * 3 + [1e-4] * 3)
    Ts = [_perturb(T0, rng.multivariate_normal(np.zeros(6), 9 * C)) for _ in range(6)]  # 3x the claimed sigma
    f = fuse_estimates(Ts, [C] * 6)
    assert f.birge > 4 and np.allclose(f.cov, C / 6 * f.birge)


def test_a_window_far_from_the_others_is_left_out_and_reported():
    rng = np.random.default_rng(7)
    C = np.diag([(0.1 * np.pi / 180) ** 2] * 3 + [0.02 ** 2] * 3)
    Ts = [_perturb(T0, rng.multivariate_normal(np.zeros(6), C)) for _ in range(4)]
    Ts.insert(2, _perturb(T0, np.array([0, 0, 0, 0.25, 0, 0])))   # 25 cm off along x: 12 sigma
    f = fuse_estimates(Ts, [C] * 5)
    assert [i for i, _ in f.dropped] == [2] and f.dropped[0][1] > 100
    assert f.used == [0, 1, 3, 4]
    assert np.linalg.norm(f.T[:3, 3] - T0[:3, 3]) < 0.04
    # two windows that disagree: neither can be told to be the wrong one, both stay and the Birge ratio
    # widens the covariance to cover them
    f2 = fuse_estimates(Ts[1:3], [C] * 2)
    assert f2.dropped == [] and f2.birge > 10 and not f2.agree
    assert fuse_estimates(Ts[:2], [C] * 2).agree
    # three windows, the wrong one the most confident: the two that agree are kept (the scale the suspect is
    # judged by comes from the other windows' pairs, which it does not enter)
    f3 = fuse_estimates([Ts[0], Ts[1], Ts[2]], [C, C, C / 4])
    assert [i for i, _ in f3.dropped] == [2] and f3.used == [0, 1] and f3.agree


def test_bad_input_is_refused_with_a_message():
    with pytest.raises(ValueError, match="no estimate"):
        fuse_estimates([], [])
    C = np.eye(6) * 1e-4
    C[0, 0] = np.nan
    with pytest.raises(ValueError, match="not a finite 6x6"):
        fuse_estimates([T0], [C])
