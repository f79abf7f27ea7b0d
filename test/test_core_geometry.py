import numpy as np
import pytest

from lidar_cam_calib.core import geometry as g


def rand_R(rng):
    return g.so3_exp(rng.normal(size=3))


def test_exp_log_roundtrip_including_near_pi():
    rng = np.random.default_rng(1)
    for _ in range(200):
        w = rng.normal(size=3)
        w *= rng.uniform(0, np.pi - 1e-6) / np.linalg.norm(w)
        np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-7)
    w = np.array([0.0, 0.0, np.pi - 1e-6])
    np.testing.assert_allclose(np.abs(g.so3_log(g.so3_exp(w))), np.abs(w), atol=1e-5)
    np.testing.assert_allclose(g.so3_log(np.eye(3)), 0.0, atol=1e-15)


def test_quaternion_roundtrip_and_sign():
    rng = np.random.default_rng(2)
    for _ in range(100):
        R = rand_R(rng)
        q = g.quat_from_R(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(g.R_from_quat(q), R, atol=1e-12)
    # 90 deg about z: q = (0, 0, sin45, cos45)
    np.testing.assert_allclose(g.quat_from_R(g.R_from_rpy(0, 0, np.pi / 2)),
                               [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_rpy_roundtrip_and_convention():
    r, p, y = 0.1, -0.2, 0.3
    R = g.R_from_rpy(r, p, y)
    np.testing.assert_allclose(g.rpy_from_R(R), [r, p, y], atol=1e-12)
    # yaw 90 deg maps x to y
    np.testing.assert_allclose(g.R_from_rpy(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_inverse_and_transform_points():
    rng = np.random.default_rng(3)
    T = g.make_T(rand_R(rng), rng.normal(size=3))
    np.testing.assert_allclose(T @ g.inv_T(T), np.eye(4), atol=1e-12)
    p = rng.normal(size=(10, 3))
    np.testing.assert_allclose(g.transform_points(g.inv_T(T), g.transform_points(T, p)), p, atol=1e-12)


def test_project_to_so3_and_errors():
    rng = np.random.default_rng(4)
    R = rand_R(rng)
    M = R + 1e-3 * rng.normal(size=(3, 3))
    Rp = g.project_to_so3(M)
    np.testing.assert_allclose(Rp.T @ Rp, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rp) == pytest.approx(1.0)
    assert g.rotation_error_deg(Rp, R) < 0.2
    T1 = g.make_T(np.eye(3), [0, 0, 0])
    T2 = g.make_T(g.so3_exp([0, 0, np.radians(2.0)]), [0.003, 0.004, 0])
    er, et = g.pose_errors(T1, T2)
    assert er == pytest.approx(2.0) and et == pytest.approx(5.0)


def test_body_optical_rotation():
    # optical z (forward) is body x; optical x (right) is body -y; optical y (down) is body -z
    np.testing.assert_allclose(g.R_BODY_OPTICAL @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(g.R_BODY_OPTICAL @ [1, 0, 0], [0, -1, 0])
    np.testing.assert_allclose(g.R_BODY_OPTICAL @ [0, 1, 0], [0, 0, -1])
    assert np.linalg.det(g.R_BODY_OPTICAL) == pytest.approx(1.0)
