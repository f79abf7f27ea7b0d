"""The final 3D-2D step of paper 001 (Section 3.4) and the result covariance (ROS-free).

:func:`final_pnp`: LiDAR points (object centroids in the paper) pushed through
the registration chain give pixels in the reference image; OpenCV
``solvePnP`` (iterative, Levenberg-Marquardt) from the chain's own estimate
gives the single rigid ``T_camera_lidar``. Its Gauss-Newton information
``J^T J / sigma^2`` is returned with it.

:func:`pnp_covariance`: 6x6, rotation first, of the perturbation
``T = (exp(dtheta) R, t + dt)``, from that information.
"""
from __future__ import annotations

import numpy as np

from ..core.camera import CameraModel
from ..core.errors import CalibError
from ..core.geometry import make_T, skew, so3_exp


def _ideal_project(K: np.ndarray, T: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = p @ T[:3, :3].T + T[:3, 3]
    z = q[:, 2]
    uv = q[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None] @ K[:2, :2].T + K[:2, 2]
    return uv, z


def final_pnp(pts_lidar: np.ndarray, uv_ideal: np.ndarray, camera: CameraModel, T0: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """(T_camera_lidar, residuals px (M,)) by LM from ``T0``; pixels are in the
    ideal (undistorted, same K) image."""
    import cv2
    p = np.asarray(pts_lidar, float).reshape(-1, 3)
    uv = np.asarray(uv_ideal, float).reshape(-1, 2)
    if p.shape[0] < 6:
        raise CalibError(f"final PnP needs at least 6 LiDAR points in view, got {p.shape[0]}")
    rv0, _ = cv2.Rodrigues(T0[:3, :3])
    ok, rv, tv = cv2.solvePnP(p, uv, camera.K, None, rv0.copy(), T0[:3, 3].reshape(3, 1).copy(),
                              useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibError("final PnP (Levenberg-Marquardt) did not converge")
    T = make_T(cv2.Rodrigues(rv)[0], tv.ravel())
    pr, _ = _ideal_project(camera.K, T, p)
    return T, np.linalg.norm(pr - uv, axis=1)


def pnp_information(pts_lidar: np.ndarray, camera: CameraModel, T: np.ndarray, sigma_px: float) -> np.ndarray:
    """6x6 information (rotation first) of the pixel residuals w.r.t. the
    perturbation ``(exp(dtheta) R, t + dt)``."""
    K = camera.K
    p = np.asarray(pts_lidar, float).reshape(-1, 3)
    Rp = p @ T[:3, :3].T
    q = Rp + T[:3, 3]
    H = np.zeros((6, 6))
    for rp, qq in zip(Rp, q):
        x, y, z = qq
        Jp = np.array([[K[0, 0] / z, 0, -K[0, 0] * x / z**2], [0, K[1, 1] / z, -K[1, 1] * y / z**2]])
        J = np.concatenate([Jp @ -skew(rp), Jp], axis=1)
        H += J.T @ J
    return H / max(sigma_px, 1e-6) ** 2


def perturb(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(exp(d[:3]) R, t + d[3:])."""
    return make_T(so3_exp(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])


__all__ = ["final_pnp", "perturb", "pnp_information"]
