"""The checkerboard in one image (ROS-free): paper 000, section 2.1.2 (2).

Sub-pixel inner corners by OpenCV's ``findChessboardCornersSB`` (sector
based, sub-pixel accurate), with the classic detector plus ``cornerSubPix``
as a fall-back. Large images are searched at a reduced scale first and the
corners refined at full resolution.

Corner order: OpenCV returns the grid row by row with ``pattern_size[0]``
corners per row, but which end comes first is arbitrary (four orders, all of
which are rigid motions of a planar board). :func:`canonical_order` turns
the grid so that the board's z axis points towards the camera (the camera
sees the printed side); the 180 deg turn about the board normal that is left
is resolved against the LiDAR in :mod:`lidar_cam_calib.board.solvers`.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.camera import CameraModel
from ..core.errors import CalibError, InputError
from .frame import BoardGeometry


class CornersNotFound(CalibError):
    """The checkerboard was not found in the image."""


@dataclasses.dataclass
class ImageCorners:
    """``uv``: (n,2) distorted pixels in board order (x fastest);
    ``xn``: (n,2) undistorted normalised coordinates; ``T_camera_board``:
    board pose from PnP (z towards the camera); ``rms_px``: PnP reprojection."""
    uv: np.ndarray
    xn: np.ndarray
    T_camera_board: np.ndarray
    rms_px: float


def to_gray(image: np.ndarray) -> np.ndarray:
    import cv2
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    elif img.ndim != 2:
        raise InputError(f"image of shape {img.shape} is neither mono nor colour")
    if img.dtype == np.uint16:
        img = (img / 256).astype(np.uint8)
    elif img.dtype != np.uint8:
        f = img.astype(np.float32)
        lo, hi = np.nanpercentile(f, 1), np.nanpercentile(f, 99)
        img = np.clip(255 * (f - lo) / max(hi - lo, 1e-6), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def find_corners(image: np.ndarray, pattern_size: tuple, max_search_px: int = 1000) -> np.ndarray:
    """(n,2) sub-pixel corners in OpenCV order, or :class:`CornersNotFound`."""
    import cv2
    gray = to_gray(image)
    h, w = gray.shape
    c = None
    # 1) classic detector (fast), 2) sector-based detector on a reduced image
    for sc in (min(1.0, max_search_px / max(h, w)),):
        small = gray if sc >= 1.0 else cv2.resize(gray, (int(round(w * sc)), int(round(h * sc))),
                                                  interpolation=cv2.INTER_AREA)
        ok, c = cv2.findChessboardCorners(small, pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH |
                                          cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
        if not ok:
            ok, c = cv2.findChessboardCornersSB(small, pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok and c is not None:
            scale = sc
            break
    else:
        raise CornersNotFound(f"no {pattern_size[0]}x{pattern_size[1]} checkerboard corners in the "
                              f"{w}x{h} image (board out of view, blurred, or too small)")
    c = c.reshape(-1, 2).astype(np.float32)
    if scale < 1.0:
        c = (c + 0.5) / scale - 0.5
    # refine at full resolution; window from the corner spacing
    nx = pattern_size[0]
    grid = c.reshape(-1, nx, 2)
    sp = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    win = int(np.clip(sp * 0.35, 2, 12))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.005)
    c = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (win, win), (-1, -1), crit).reshape(-1, 2)
    return c.astype(float)


def _pnp(obj: np.ndarray, xn: np.ndarray) -> np.ndarray:
    import cv2
    ok, rv, tv = cv2.solvePnP(obj.astype(np.float64), xn.reshape(-1, 1, 2).astype(np.float64), np.eye(3), None,
                              flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rv, tv = cv2.solvePnP(obj, xn.reshape(-1, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CornersNotFound("PnP failed on the detected corners")
    R = cv2.Rodrigues(rv)[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, tv.ravel()
    return T


def canonical_order(uv: np.ndarray, xn: np.ndarray, board: BoardGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reorder the corner grid so the board z axis faces the camera; returns
    (uv, xn, T_camera_board)."""
    nx, ny = board.pattern_size
    obj = board.inner_corners_board()
    g_uv, g_xn = uv.reshape(ny, nx, 2), xn.reshape(ny, nx, 2)
    for flip_x in (False, True):
        u2 = g_uv[:, ::-1] if flip_x else g_uv
        x2 = g_xn[:, ::-1] if flip_x else g_xn
        T = _pnp(obj, x2.reshape(-1, 2))
        n, t = T[:3, 2], T[:3, 3]
        if n @ t < 0:  # normal towards the camera
            return u2.reshape(-1, 2).copy(), x2.reshape(-1, 2).copy(), T
    return u2.reshape(-1, 2).copy(), x2.reshape(-1, 2).copy(), T


def rotate_180(ic: ImageCorners, board: BoardGeometry) -> ImageCorners:
    """The same corners with the board turned 180 deg about its normal."""
    Rz = np.diag([-1.0, -1.0, 1.0, 1.0])
    return ImageCorners(ic.uv[::-1].copy(), ic.xn[::-1].copy(), ic.T_camera_board @ Rz, ic.rms_px)


def detect_image_corners(image: np.ndarray, camera: CameraModel, board: BoardGeometry) -> ImageCorners:
    """Corners, their undistorted normalised coordinates and the board pose."""
    if camera is None:
        raise InputError("no CameraInfo for this camera yet: its intrinsics are needed")
    img = np.asarray(image)
    if img.shape[0] != camera.height or img.shape[1] != camera.width:
        raise InputError(f"image is {img.shape[1]}x{img.shape[0]} but CameraInfo says "
                         f"{camera.width}x{camera.height}")
    uv = find_corners(img, board.pattern_size)
    xn = camera.pixels_to_rays(uv)[:, :2]
    uv, xn, T = canonical_order(uv, xn, board)
    P = board.inner_corners_board() @ T[:3, :3].T + T[:3, 3]
    uvp, _ = camera.project(P)
    rms = float(np.sqrt(np.mean(np.sum((uvp - uv) ** 2, axis=1))))
    return ImageCorners(uv, xn, T, rms)


__all__ = ["CornersNotFound", "ImageCorners", "canonical_order", "detect_image_corners", "find_corners",
           "rotate_180", "to_gray"]
