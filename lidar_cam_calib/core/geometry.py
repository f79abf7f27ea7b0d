"""SO(3)/SE(3) utilities (ROS-free).

Conventions
-----------
* ``T_a_b`` is a 4x4 homogeneous matrix that maps a point expressed in frame
  ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``.
* Rotation vectors are axis * angle in radians.
* Quaternions are ``(x, y, z, w)`` as in geometry_msgs, normalised, ``w >= 0``.
* Tangent-space ordering is *rotation first*: ``xi = (wx, wy, wz, tx, ty, tz)``;
  covariances follow the same order (radians, metres).
"""
from __future__ import annotations

import numpy as np

_EPS = 1e-12


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 skew-symmetric matrix with ``skew(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    w = np.asarray(w, dtype=float).reshape(3)
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-9:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix; robust near 0 and pi."""
    R = np.asarray(R, dtype=float)
    c = np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0)
    th = float(np.arccos(c))
    if th < 1e-7:
        return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.pi - th < 1e-4:
        # Near pi: axis from the symmetric part.
        B = 0.5 * (R + np.eye(3))
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], _EPS))
        # Fix sign with the antisymmetric part when it is informative.
        s = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        if np.dot(s, axis) < 0:
            axis = -axis
        return axis / np.linalg.norm(axis) * th
    return th / (2.0 * np.sin(th)) * np.array(
        [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]
    )


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Closest rotation matrix (Frobenius) to a 3x3 matrix, det = +1."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to an (N, 3) array of points."""
    pts = np.asarray(pts, dtype=float)
    return pts @ T[:3, :3].T + T[:3, 3]


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Transform of a tangent vector ``(w, v)``; here simply ``(exp(w), v)``.

    We use the decoupled parametrisation (rotation vector, translation) rather
    than the true SE(3) exponential: it is what the solvers perturb and what
    the covariance is expressed in (rotation first).
    """
    xi = np.asarray(xi, dtype=float).reshape(6)
    return make_T(so3_exp(xi[:3]), xi[3:])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`se3_exp` (rotation vector, translation)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([so3_log(T[:3, :3]), T[:3, 3]])


def quat_from_R(R: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) with w >= 0 from a rotation matrix."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s,
                      (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s,
                      (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s,
                      (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s,
                      0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q = q / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return q


def R_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix from a quaternion (x, y, z, w); normalises first."""
    x, y, z, w = np.asarray(q, dtype=float).reshape(4) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def R_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (ROS fixed-axis convention), radians."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def rpy_from_R(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in radians, inverse of :func:`R_from_rpy`."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([roll, pitch, yaw])


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle of ``R_est^T R_true`` in degrees."""
    return float(np.degrees(np.linalg.norm(so3_log(np.asarray(R_est).T @ np.asarray(R_true)))))


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in millimetres)."""
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    return (rotation_error_deg(T_est[:3, :3], T_true[:3, :3]),
            float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1000.0))


def spin_time_s(x: np.ndarray, y: np.ndarray, period_s: float, spin: int = -1, start_azimuth_deg: float = 180.0,
                stamp_fraction: float = 0.0) -> np.ndarray:
    """When a spinning LiDAR measured each point, from its azimuth ``atan2(y, x)`` alone (s after the
    sweep's stamp): the head turns once per ``period_s`` in the direction ``spin`` (-1 clockwise seen from
    above: Velodyne, Ouster) from ``start_azimuth_deg``, and ``stamp_fraction`` of the turn lies before the
    stamp (0: stamped at the start; KITTI: 0.5, stamped facing forward)."""
    az = np.degrees(np.arctan2(y, x))
    return (np.mod(spin * (az - start_azimuth_deg), 360.0) / 360.0 - stamp_fraction) * period_s


# Optical frame (z forward, x right, y down) expressed in a body frame
# (x forward, y left, z up): p_body = R_BODY_OPTICAL @ p_optical.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
