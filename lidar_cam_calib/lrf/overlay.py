"""Overlay images for the lrf method (cv2 drawing only, no matplotlib).

``render_overlay``: the depth image colourised (turbo; grey where invalid)
with the laser points projected by ``T_camera_laser`` (coloured by range)
and, if given, the detected board planes' inlier pixels tinted and the laser
corners F, G, H drawn as circles.
"""
from __future__ import annotations

import numpy as np

from ..core.geometry import transform_points
from .features import scan_points

_FACE_BGR = ((255, 255, 0), (0, 255, 0), (255, 0, 255))  # base, ABC, ACD


def colourise_depth(depth_m: np.ndarray, max_m: float | None = None) -> np.ndarray:
    import cv2
    d = np.asarray(depth_m, dtype=np.float32)
    ok = np.isfinite(d) & (d > 0)
    if not np.any(ok):
        return np.full(d.shape + (3,), 40, np.uint8)
    hi = max_m or float(np.percentile(d[ok], 98))
    lo = float(np.percentile(d[ok], 2))
    v = np.zeros(d.shape, np.uint8)
    v[ok] = np.clip(255 * (d[ok] - lo) / max(hi - lo, 1e-6), 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(v, cv2.COLORMAP_TURBO)
    img = (img * 0.6).astype(np.uint8)
    img[~ok] = (40, 40, 40)
    return img


def render_overlay(frame, T_camera_laser: np.ndarray, features=None) -> np.ndarray:
    """BGR uint8 image (camera resolution). ``features``: optional
    ``(ScanFeatures, DepthFeatures)`` (either may be None)."""
    import cv2
    img = colourise_depth(frame.depth_m)
    cam = frame.camera
    sf, df = features if features is not None else (None, None)
    if df is not None:
        for f, pix in enumerate(df.pixel_index):
            u, v = pix % cam.width, pix // cam.width
            img[v, u] = (0.5 * img[v, u] + 0.5 * np.array(_FACE_BGR[f])).astype(np.uint8)
    xy, _ = scan_points(frame.scan_ranges_m, frame.scan_angle_min_rad, frame.scan_angle_increment_rad,
                        frame.scan_range_min_m, frame.scan_range_max_m)
    if len(xy):
        p = transform_points(T_camera_laser, np.column_stack([xy, np.zeros(len(xy))]))
        uv, ok = cam.project(p)
        rng = np.linalg.norm(xy, axis=1)
        if np.any(ok):
            c = np.clip(255 * (rng[ok] - rng[ok].min()) / max(np.ptp(rng[ok]), 1e-6), 0, 255).astype(np.uint8)
            col = cv2.applyColorMap(c.reshape(-1, 1), cv2.COLORMAP_JET).reshape(-1, 3)
            uvi = np.round(uv[ok]).astype(int)
            for (u, v), cc in zip(uvi, col):
                cv2.circle(img, (int(u), int(v)), 1, tuple(int(x) for x in cc), -1)
    if sf is not None:
        p = transform_points(T_camera_laser, np.column_stack([sf.corners_m, np.zeros(3)]))
        uv, ok = cam.project(p)
        for (u, v), good, name in zip(uv, ok, "FGH"):
            if good:
                cv2.circle(img, (int(round(u)), int(round(v))), 6, (255, 255, 255), 2)
                cv2.putText(img, name, (int(u) + 7, int(v) - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                            (255, 255, 255), 1, cv2.LINE_AA)
    return img


def render_residuals(per_observation_mm, width: int = 480, height: int = 240,
                     title: str = "point-to-line error per observation (mm)") -> np.ndarray:
    """Bar chart (BGR uint8) of per-observation residuals, e.g. eq. 12 per observation."""
    import cv2
    vals = np.asarray(per_observation_mm, dtype=float).ravel()
    img = np.full((height, width, 3), 255, np.uint8)
    cv2.putText(img, title, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if vals.size == 0:
        return img
    top = max(float(np.nanmax(vals)), 1e-6)
    x0, y0, y1 = 30, 30, height - 20
    bw = max(2, (width - x0 - 10) // vals.size)
    for i, v in enumerate(vals):
        h = int((y1 - y0) * (v / top)) if np.isfinite(v) else 0
        cv2.rectangle(img, (x0 + i * bw + 1, y1 - h), (x0 + (i + 1) * bw - 2, y1), (200, 120, 40), -1)
    cv2.line(img, (x0, y1), (width - 5, y1), (0, 0, 0), 1)
    cv2.putText(img, f"max {top:.1f}", (x0, y0 - 2), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    return img


def save_png(path: str, img: np.ndarray) -> None:
    import cv2
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
