"""Overlay for the board method (cv2 drawing only): LiDAR points coloured by depth on a camera image.

``render_overlay(image, camera, points, T_camera_lidar)`` returns a BGR uint8 image of the
camera's resolution: the image (grey if mono) with every LiDAR point in front of the camera drawn
through the estimate, coloured by its depth (near red, far blue); optionally the detected image
corners (green) and the board's corners projected through the estimate (red crosses), the check
every user does first.
"""
from __future__ import annotations

import numpy as np

from ..core.camera import CameraModel
from ..core.geometry import transform_points


def render_overlay(image: np.ndarray, camera: CameraModel, points: np.ndarray, T_camera_lidar: np.ndarray,
                   corners_uv: np.ndarray | None = None, corners_lidar: np.ndarray | None = None,
                   max_points: int = 60000, radius: int = 2) -> np.ndarray:
    import cv2
    img = np.asarray(image)
    if img.ndim == 2:
        out = cv2.cvtColor(img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8),
                           cv2.COLOR_GRAY2BGR)
    else:
        out = img[:, :, :3].copy() if img.dtype == np.uint8 else np.clip(img[:, :, :3], 0, 255).astype(np.uint8)
    out = (out * 0.75).astype(np.uint8)
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) > max_points:
        P = P[np.linspace(0, len(P) - 1, max_points).astype(int)]
    if len(P):
        pc = transform_points(T_camera_lidar, P)
        uv, ok = camera.project(pc)
        if np.any(ok):
            z = pc[ok, 2]
            lo, hi = np.percentile(z, 2), np.percentile(z, 98)
            v = np.clip(255 * (z - lo) / max(hi - lo, 1e-6), 0, 255).astype(np.uint8)
            col = cv2.applyColorMap(255 - v.reshape(-1, 1), cv2.COLORMAP_JET).reshape(-1, 3)
            order = np.argsort(-z)  # far first, near drawn on top
            uvi = np.round(uv[ok][order]).astype(int)
            for (u, vv), c in zip(uvi, col[order]):
                cv2.circle(out, (int(u), int(vv)), radius, (int(c[0]), int(c[1]), int(c[2])), -1)
    if corners_uv is not None:
        for u, v in np.asarray(corners_uv).reshape(-1, 2):
            cv2.circle(out, (int(round(u)), int(round(v))), 4, (0, 255, 0), 1, cv2.LINE_AA)
    if corners_lidar is not None:
        uv, ok = camera.project(transform_points(T_camera_lidar, np.asarray(corners_lidar).reshape(-1, 3)))
        for (u, v), good in zip(uv, ok):
            if good:
                q = (int(round(u)), int(round(v)))
                cv2.drawMarker(out, q, (0, 0, 255), cv2.MARKER_CROSS, 8, 1, cv2.LINE_AA)
    return out


def render_frame_overlay(frame, name: str, T_camera_lidar: np.ndarray, observation=None, board=None) -> np.ndarray:
    """Overlay of one :class:`~lidar_cam_calib.board.frame.BoardFrame` for camera ``name``
    (``observation``: an accepted :class:`~lidar_cam_calib.board.solvers.Observation` to draw its corners)."""
    ci = frame.images[name]
    uv = corners = None
    if observation is not None and name in observation.images:
        uv = observation.images[name].uv
        if board is not None:
            corners = observation.lidar.virtual_corners(board)
    return render_overlay(ci.image, ci.camera, frame.points, T_camera_lidar, uv, corners)


__all__ = ["render_frame_overlay", "render_overlay"]
