"""Camera models (ROS-free): pinhole with the distortion models ROS names.

``distortion_model`` follows sensor_msgs/CameraInfo: ``plumb_bob`` (k1 k2 p1
p2 k3), ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6), ``equidistant``
(fisheye k1 k2 k3 k4), or ``''``/``none`` for an ideal pinhole. Points are in
the optical frame (z forward, x right, y down), pixels are (u, v) with u to
the right and v down, (0, 0) the centre of the top-left pixel.
"""
from __future__ import annotations

import dataclasses

import numpy as np

SUPPORTED_MODELS = ("plumb_bob", "rational_polynomial", "equidistant", "none", "")


@dataclasses.dataclass
class CameraModel:
    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.D = np.asarray(self.D, dtype=float).ravel()
        self.width = int(self.width)
        self.height = int(self.height)
        if self.distortion_model not in SUPPORTED_MODELS:
            raise ValueError(
                f"unsupported distortion_model {self.distortion_model!r}; "
                f"supported: plumb_bob, rational_polynomial, equidistant, none")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0):
            raise ValueError("camera matrix K has no focal length (fx, fy must be > 0): "
                             "is the camera calibrated?")
        self._rays = None

    # -- constructors ---------------------------------------------------------
    @classmethod
    def from_K(cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
               D=None, distortion_model: str = "plumb_bob") -> "CameraModel":
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(width, height, K, np.zeros(5) if D is None else D, distortion_model)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def is_distorted(self) -> bool:
        return self.distortion_model not in ("", "none") and bool(np.any(self.D != 0))

    def _coeffs(self) -> np.ndarray:
        n = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}.get(self.distortion_model, 0)
        c = np.zeros(n)
        m = min(n, self.D.size)
        c[:m] = self.D[:m]
        return c

    # -- distortion on normalised coordinates ---------------------------------
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Map ideal normalised coordinates (N,2) to distorted normalised ones."""
        xn = np.asarray(xn, dtype=float)
        if not self.is_distorted:
            return xn.copy()
        x, y = xn[:, 0], xn[:, 1]
        c = self._coeffs()
        if self.distortion_model == "equidistant":
            r = np.hypot(x, y)
            th = np.arctan(r)
            th2 = th * th
            thd = th * (1 + c[0] * th2 + c[1] * th2**2 + c[2] * th2**3 + c[3] * th2**4)
            s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
            return np.stack([x * s, y * s], axis=1)
        r2 = x * x + y * y
        k1, k2, p1, p2, k3 = c[0], c[1], c[2], c[3], c[4]
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        if self.distortion_model == "rational_polynomial":
            k4, k5, k6 = c[5], c[6], c[7]
            radial = radial / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def undistort(self, xd: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Inverse of :meth:`distort` (N,2), by Newton's method.

        A fixed-point iteration converges too slowly where the distortion compresses strongly
        (a fisheye beyond ~50 deg off axis was left pixels off after 20 steps), so:
        ``equidistant`` solves theta_d = theta (1 + k1 theta^2 + ...) for theta per point (1-D
        Newton) and ``plumb_bob`` / ``rational_polynomial`` take 2-D Newton steps with the
        Jacobian of :meth:`distort`, until the residual is below 1e-12."""
        xd = np.asarray(xd, dtype=float)
        if not self.is_distorted:
            return xd.copy()
        if self.distortion_model == "equidistant":
            return self._undistort_equidistant(xd, iterations)
        x = xd.copy()
        h = 1e-7
        for _ in range(iterations):
            f0 = self.distort(x)
            err = f0 - xd
            if not np.any(np.abs(err) > 1e-12):
                break
            jx = (self.distort(x + [h, 0.0]) - f0) / h
            jy = (self.distort(x + [0.0, h]) - f0) / h
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            ok = np.abs(det) > 1e-12
            dets = np.where(ok, det, 1.0)
            dx = np.where(ok, (jy[:, 1] * err[:, 0] - jy[:, 0] * err[:, 1]) / dets, err[:, 0])
            dy = np.where(ok, (-jx[:, 1] * err[:, 0] + jx[:, 0] * err[:, 1]) / dets, err[:, 1])
            step = np.stack([dx, dy], axis=1)
            # backtracking: a step is taken only where it lowers the residual (beyond the radius
            # where the polynomial folds back there is no inverse; the point stays where it was)
            e0 = np.sum(err ** 2, axis=1)
            moved = np.zeros(len(x), bool)
            for _ in range(6):
                xn = x - step
                better = (np.sum((self.distort(xn) - xd) ** 2, axis=1) < e0) & ~moved
                x[better] = xn[better]
                moved |= better
                step *= 0.5
            if not moved.any():
                break
        return x

    def _undistort_equidistant(self, xd: np.ndarray, iterations: int) -> np.ndarray:
        k = self._coeffs()
        thd = np.hypot(xd[:, 0], xd[:, 1])
        th = np.minimum(thd, 1.5)
        for _ in range(iterations):
            t2 = th * th
            f = th * (1 + k[0] * t2 + k[1] * t2**2 + k[2] * t2**3 + k[3] * t2**4) - thd
            df = 1 + 3 * k[0] * t2 + 5 * k[1] * t2**2 + 7 * k[2] * t2**3 + 9 * k[3] * t2**4
            step = f / np.where(np.abs(df) > 1e-9, df, 1e-9)
            th = np.clip(th - step, 0.0, np.pi / 2 - 1e-6)
            if not np.any(np.abs(step) > 1e-13):
                break
        scale = np.where(thd > 1e-12, np.tan(th) / np.maximum(thd, 1e-12), 1.0)
        return xd * scale[:, None]

    # -- projection ------------------------------------------------------------
    def project(self, pts_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) optical-frame points to pixels. Returns (uv (N,2),
        valid (N,)) where valid means in front of the camera (z > 1 cm) and
        inside the image."""
        p = np.asarray(pts_cam, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        front = z > 1e-2
        zs = np.where(front, z, 1.0)
        xn = np.stack([p[:, 0] / zs, p[:, 1] / zs], axis=1)
        xd = self.distort(xn)
        uv = xd @ self.K[:2, :2].T + self.K[:2, 2]
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < self.width - 0.5) & \
                 (uv[:, 1] >= -0.5) & (uv[:, 1] < self.height - 0.5)
        return uv, front & inside & np.all(np.isfinite(uv), axis=1)

    def pixels_to_rays(self, uv: np.ndarray) -> np.ndarray:
        """(N,2) pixels -> (N,3) rays with z = 1 (undistorted)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        Kinv = np.linalg.inv(self.K)
        xd = uv @ Kinv[:2, :2].T + Kinv[:2, 2]
        xn = self.undistort(xd)
        return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)

    def pixel_rays(self) -> np.ndarray:
        """(H*W, 3) rays with z = 1 for every pixel, row-major (cached)."""
        if self._rays is None:
            v, u = np.mgrid[0:self.height, 0:self.width]
            uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
            self._rays = self.pixels_to_rays(uv)
        return self._rays

    def depth_to_points(self, depth_m: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Back-project a z-depth image (metres) to optical-frame points.

        Pixels with NaN, inf or non-positive depth are dropped. ``stride``
        keeps every stride-th row and column. Returns (points (M,3),
        pixel_index (M,)) with ``pixel_index = v * width + u``."""
        depth = np.asarray(depth_m)
        if depth.shape != (self.height, self.width):
            raise ValueError(f"depth image is {depth.shape[1] if depth.ndim > 1 else '?'}x{depth.shape[0]} "
                             f"but CameraInfo says {self.width}x{self.height}")
        rays = self.pixel_rays()
        if stride > 1:
            v, u = np.mgrid[0:self.height:stride, 0:self.width:stride]
            idx = (v * self.width + u).ravel()
        else:
            idx = np.arange(self.height * self.width)
        z = depth.ravel()[idx].astype(float)
        ok = np.isfinite(z) & (z > 0)
        idx = idx[ok]
        return rays[idx] * z[ok][:, None], idx

    def scaled(self, factor: float) -> "CameraModel":
        """The same camera at a different resolution (e.g. a depth stream at half size)."""
        K = self.K.copy()
        K[0, :] *= factor
        K[1, :] *= factor
        K[0, 2] = (self.K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * factor - 0.5
        return CameraModel(int(round(self.width * factor)), int(round(self.height * factor)),
                           K, self.D.copy(), self.distortion_model)
