"""Overlay for the targetless method: LiDAR points coloured by depth on the camera image (cv2 only)."""
from __future__ import annotations

import numpy as np

from ..core.camera import CameraModel
from ..core.geometry import transform_points


def render_overlay(image: np.ndarray, camera: CameraModel, points_lidar: np.ndarray, T_camera_lidar: np.ndarray,
                   max_depth_m: float = 40.0, radius_px: int = 1) -> np.ndarray:
    """BGR image with every LiDAR point in view drawn through ``T_camera_lidar``,
    coloured by depth (turbo colour map, near = red)."""
    import cv2
    img = np.asarray(image)
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    out = (out * 0.7).astype(np.uint8)
    pc = transform_points(T_camera_lidar, np.asarray(points_lidar, float).reshape(-1, 3))
    uv, ok = camera.project(pc)
    if not np.any(ok):
        return out
    z = pc[ok, 2]
    order = np.argsort(-z)  # far first, near drawn on top
    v = np.clip(255 * (1.0 - np.minimum(z[order], max_depth_m) / max_depth_m), 0, 255).astype(np.uint8)
    col = cv2.applyColorMap(v.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
    pix = np.round(uv[ok][order]).astype(int)
    if radius_px <= 0:
        out[pix[:, 1].clip(0, out.shape[0] - 1), pix[:, 0].clip(0, out.shape[1] - 1)] = col
    else:
        for (u, w), c in zip(pix, col):
            cv2.circle(out, (int(u), int(w)), radius_px, tuple(int(x) for x in c), -1)
    return out


__all__ = ["render_overlay"]
