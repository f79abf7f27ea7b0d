"""LrfCalibrator: collects board observations and solves T_camera_laser (ROS-free).

Shape shared by all methods: ``add(frame) -> Verdict``, ``ready()``,
``fit() -> CalibrationResult``, plus ``status()`` and ``reset()``.
"""
from __future__ import annotations

import dataclasses
import math
import numpy as np

from ..core.result import CalibrationResult
from .features import (FeatureConfig, FeatureError, extract_depth_features, extract_scan_features,
                       make_observation)
from .frame import LrfFrame
from .solvers import OursOptions, reject_outlier_observations, resolve_assignment, solve_ours, solve_paper


@dataclasses.dataclass
class LrfConfig(FeatureConfig):
    """Calibration parameters (inherits the feature-extraction ones).

    ``error_threshold_m``: paper Algorithm 1 stop threshold on the eq. 12 error.
    ``target_sigma_deg`` / ``target_sigma_mm``: 'done' when the 1-sigma
    uncertainty of our solution is below both. Duplicate pose: an observation
    whose laser corners F, G, H are all within ``duplicate_distance_m`` and whose
    FH direction is within ``duplicate_angle_deg`` of an accepted one."""
    error_threshold_m: float = 0.01
    target_sigma_deg: float = 0.3
    target_sigma_mm: float = 5.0
    min_observations: int = 2
    max_observations: int = 40
    duplicate_distance_m: float = 0.03
    duplicate_angle_deg: float = 2.0
    corner_weight: float = 0.0
    solver: str = "ours"


@dataclasses.dataclass
class Verdict:
    accepted: bool
    reason: str


def _direction_deg(corners: np.ndarray) -> float:
    d = corners[2] - corners[0]
    return math.degrees(math.atan2(d[1], d[0]))


class LrfCalibrator:
    """Collects observations (``add``) and solves (``fit``)."""

    def __init__(self, cfg: LrfConfig | None = None):
        self.cfg = cfg or LrfConfig()
        self.reset()

    def reset(self) -> None:
        self.observations = []
        self.features = []
        self.stamps = []
        self.frames_meta = None
        self.last_reason = "waiting for the first observation"
        self._last_fit = None

    # ------------------------------------------------------------------
    def add(self, frame: LrfFrame) -> Verdict:
        cfg = self.cfg
        if self.stamps and frame.stamp_s <= self.stamps[-1]:
            return self._reject(f"stamp {frame.stamp_s:.3f} s is not after the last accepted "
                                f"{self.stamps[-1]:.3f} s (out of order)")
        if len(self.observations) >= cfg.max_observations:
            return self._reject(f"already {cfg.max_observations} observations (max_observations)")
        try:
            sf = extract_scan_features(frame, cfg)
        except FeatureError as e:
            return self._reject(str(e))
        try:
            df = extract_depth_features(frame, cfg)
        except FeatureError as e:
            return self._reject(str(e))
        C = sf.corners_m
        for k, o in enumerate(self.observations):
            dist = np.linalg.norm(o.corners_laser_m - C, axis=1).max()
            dang = abs((_direction_deg(o.corners_laser_m) - _direction_deg(C) + 180) % 360 - 180)
            if dist < cfg.duplicate_distance_m and dang < cfg.duplicate_angle_deg:
                return self._reject(f"pose too similar to observation {k + 1} "
                                    f"(corners within {dist * 100:.1f} cm, {dang:.1f} deg): move the AGV")
        obs = make_observation(sf, df, frame.stamp_s, cfg.laser_sigma_m)
        self.observations.append(obs)
        self.features.append((sf, df))
        self.stamps.append(frame.stamp_s)
        self.frames_meta = (frame.laser_frame, frame.camera_frame)
        self._last_fit = None
        self.last_reason = f"observation {len(self.observations)} accepted"
        return Verdict(True, self.last_reason)

    def _reject(self, reason: str) -> Verdict:
        self.last_reason = reason
        return Verdict(False, reason)

    def ready(self) -> bool:
        return len(self.observations) >= max(2, self.cfg.min_observations)

    # ------------------------------------------------------------------
    def fit(self, solver: str | None = None) -> CalibrationResult:
        """Solve with ``'ours'`` (default) or ``'paper'``. Raises RuntimeError
        when fewer than 2 observations."""
        solver = solver or self.cfg.solver
        if not self.ready():
            raise RuntimeError(f"need >= {max(2, self.cfg.min_observations)} observations, "
                               f"have {len(self.observations)}")
        obs, flags = resolve_assignment(self.observations)
        obs, dropped, _ = reject_outlier_observations(obs)
        R_raw, t_p, info = solve_paper(obs)
        paper = {"point_to_line_mm": 1000 * info["point_to_line_m"],
                 "point_to_line_so3_mm": 1000 * info["point_to_line_so3_m"],
                 "orthonormality_error": info["orthonormality_error"],
                 "condition_number": info["condition"]}
        laser_frame, camera_frame = self.frames_meta
        notes = []
        if dropped:
            notes.append(f"observations {[i + 1 for i in dropped]} disagree with the others (a corner lies "
                         "far from its camera line: board mis-detected?) and were left out of the fit")
        if any(flags):
            notes.append(f"triangle correspondence swapped for observations "
                         f"{[i + 1 for i, f in enumerate(flags) if f]} (left/right check)")
        opt = OursOptions(laser_sigma_m=self.cfg.laser_sigma_m, corner_weight=self.cfg.corner_weight,
                          target_sigma_deg=self.cfg.target_sigma_deg, target_sigma_mm=self.cfg.target_sigma_mm)
        sol = solve_ours(obs, options=opt)
        metrics = {
            "point_to_line_mm": 1000 * sol.metrics["point_to_line_m"],
            "plane_rms_mm": 1000 * sol.metrics["plane_rms_m"],
            "variance_factor": sol.metrics["variance_factor"],
            "condition_number": sol.metrics["condition_number"],
            "observability": sol.observability["verdict"],
            "weakest_direction": sol.observability["weakest_direction"],
            "advice": sol.observability["advice"],
            "paper": paper,
            "rejected_observations": [i + 1 for i in dropped],
        }
        if solver == "paper":
            T = info["T"]
            cov = sol.covariance  # the paper gives none; ours at the same data as a guide
            notes.append("paper solver: R projected to SO(3) (raw R orthonormality error "
                         f"{info['orthonormality_error']:.2e}); covariance from our solver")
            metrics["point_to_line_mm"] = paper["point_to_line_so3_mm"]
        elif solver == "ours":
            T = sol.T
            cov = sol.covariance
        else:
            raise ValueError(f"unknown solver {solver!r} (use 'ours' or 'paper')")
        res = CalibrationResult(method="lrf", parent_frame=laser_frame, child_frame=camera_frame,
                                T_child_parent=T, covariance=cov, metrics=metrics,
                                observations_used=len(obs), stamps=list(self.stamps), solver=solver,
                                notes=notes)
        self._last_fit = (res, sol)
        return res

    # ------------------------------------------------------------------
    def status(self) -> dict:
        n = len(self.observations)
        need = max(2, self.cfg.min_observations)
        st = {"observations": n, "needed": need, "last_reason": self.last_reason,
              "error_mm": math.nan, "sigma_rotation_deg": math.nan, "sigma_translation_mm": math.nan,
              "done": False, "advice": "" if n >= need else f"collect {need - n} more observation(s)"}
        if n >= need:
            try:
                if self._last_fit is None:
                    self.fit()
                res, _sol = self._last_fit
            except Exception as e:  # noqa: BLE001 -- status must not raise
                st["advice"] = f"fit failed: {e}"
                return st
            sr, stt = res.sigma()
            err = res.metrics["point_to_line_mm"]
            st.update(error_mm=err, sigma_rotation_deg=sr, sigma_translation_mm=stt,
                      observability=res.metrics["observability"])
            st["done"] = bool(sr <= self.cfg.target_sigma_deg and stt <= self.cfg.target_sigma_mm
                              and err <= 1000 * self.cfg.error_threshold_m)
            st["advice"] = "" if st["done"] else (res.metrics["advice"] or
                                                   "add another observation from a different pose")
        return st


class StaticDetector:
    """Fires once per stop: ``update`` returns True the first time the scan has
    been static (median |range change| vs the scan at the start of the still
    period < ``range_tol_m``) for ``static_time_s``; re-arms after motion."""

    def __init__(self, static_time_s: float = 1.0, range_tol_m: float = 0.01):
        self.static_time_s = static_time_s
        self.range_tol_m = range_tol_m
        self._ref = None
        self._since = None
        self._fired = False

    def update(self, stamp_s: float, ranges) -> bool:
        r = np.asarray(ranges, dtype=float).ravel()
        if self._ref is None or self._ref.shape != r.shape:
            self._ref, self._since, self._fired = r, stamp_s, False
            return False
        ok = np.isfinite(r) & np.isfinite(self._ref)
        moved = (not np.any(ok)) or float(np.median(np.abs(r[ok] - self._ref[ok]))) > self.range_tol_m
        if moved:
            self._ref, self._since, self._fired = r, stamp_s, False
            return False
        if not self._fired and stamp_s - self._since >= self.static_time_s:
            self._fired = True
            return True
        return False
