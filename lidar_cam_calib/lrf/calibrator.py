"""LrfCalibrator: collects board observations and solves T_camera_laser (ROS-free).

Shape shared by all methods: ``add(frame) -> Verdict``, ``ready()``,
``fit() -> CalibrationResult``, plus ``status()`` and ``reset()``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.calibrator import Verdict, cfg_field
from ..core.errors import CalibError, NotReadyError
from ..core.result import CalibrationResult
from .features import (
    FeatureConfig,
    FeatureError,
    extract_depth_features,
    extract_scan_features,
    make_observation,
)
from .frame import LrfFrame
from .solvers import (
    OursOptions,
    covariance_left,
    reject_outlier_observations,
    resolve_assignment,
    solve_ours,
    solve_paper,
)
from .stop import StopAccumulator

__all__ = ["LrfCalibrator", "LrfConfig", "StaticDetector", "Verdict"]


@dataclasses.dataclass
class LrfConfig(FeatureConfig):
    """Calibration parameters (inherits the feature-extraction ones).

    Duplicate pose: an observation whose laser corners F, G, H are all within
    ``duplicate_distance_m`` and whose FH direction is within
    ``duplicate_angle_deg`` of an accepted one."""
    error_threshold_m: float = cfg_field(0.01, "Paper Algorithm 1 stop threshold on the eq. 12 point-to-line "
                                         "error (m); status says 'done' only below it.", range=(0.0, 1.0),
                                         exclusive_min=True)
    target_sigma_deg: float = cfg_field(0.3, "Status says 'done' when the rotation 1-sigma is below this (deg).",
                                        range=(0.0, 10.0), exclusive_min=True)
    target_sigma_mm: float = cfg_field(5.0, "Status says 'done' when the translation 1-sigma is below this (mm).",
                                       range=(0.0, 1000.0), exclusive_min=True)
    min_observations: int = cfg_field(2, "Observations (stops) needed before the first fit.", range=(2, 1000))
    max_observations: int = cfg_field(40, "Most observations kept; later ones are refused.", range=(2, 10000))
    duplicate_distance_m: float = cfg_field(0.03, "A stop whose laser corners all lie this close to an accepted "
                                            "one's is refused as the same pose (m).", range=(0.0, 1.0))
    duplicate_angle_deg: float = cfg_field(2.0, "... and whose F-H direction is within this angle (deg).",
                                           range=(0.0, 90.0))
    corner_weight: float = cfg_field(0.0, "Weight of the corner-on-line residuals in our solver (0 = off: the "
                                     "laser lines are already used).", range=(0.0, 100.0))
    plane_sigma_floor_m: float = cfg_field(0.0001, "Systematic floor on every camera plane's offset (m): "
                                           "calibration of the depth camera, mixed pixels at the folds.",
                                           range=(0.0, 0.1))
    laser_sigma_floor_m: float = cfg_field(0.0002, "Systematic floor on every laser line's offset (m).",
                                           range=(0.0, 0.1))
    solver: str = cfg_field("ours", "'ours' (SE(3) refinement with covariance) or 'paper' (eq. 11).",
                            choices=("ours", "paper"))


def _direction_deg(corners: np.ndarray) -> float:
    d = corners[2] - corners[0]
    return math.degrees(math.atan2(d[1], d[0]))


class LrfCalibrator:
    """Collects observations and solves T_camera_laser.

    Two ways in: ``add(frame)`` makes one observation of one frame (the
    single-frame ~/capture path); ``feed(frame)`` for every frame of a stop and
    ``end_stop()`` when the AGV moves on make one observation of the whole stop
    (the frames are averaged; see :mod:`lidar_cam_calib.lrf.stop`);
    ``add_stop(frames)`` does both at once."""

    def __init__(self, cfg: LrfConfig | None = None):
        self.cfg = cfg or LrfConfig()
        self.cfg.board.validate()
        self.reset()

    def reset(self) -> None:
        self.observations = []
        self.features = []
        self.stamps = []
        self.frames_meta = None
        self.last_reason = "waiting for the first observation"
        self._last_fit = None
        self._stop = StopAccumulator(self.cfg)
        self.stops_seen = 0
        self.stops_refused = 0

    # ------------------------------------------------------------------
    def _precheck(self, stamp_s: float) -> Verdict | None:
        if self.stamps and stamp_s <= self.stamps[-1]:
            return self._reject(f"stamp {stamp_s:.3f} s is not after the last accepted "
                                f"{self.stamps[-1]:.3f} s (out of order)")
        if len(self.observations) >= self.cfg.max_observations:
            return self._reject(f"already {self.cfg.max_observations} observations (max_observations)")
        return None

    def add(self, frame: LrfFrame) -> Verdict:
        """One observation from one frame."""
        bad = self._precheck(frame.stamp_s)
        if bad is not None:
            return bad
        try:
            sf = extract_scan_features(frame, self.cfg)
            df = extract_depth_features(frame, self.cfg)
        except FeatureError as e:
            return self._reject(str(e))
        return self._accept(sf, df, frame)

    def feed(self, frame: LrfFrame) -> Verdict:
        """One more frame of the current stop (the AGV stands still)."""
        return self._stop.add(frame)

    def feed_scan(self, ranges_m) -> bool:
        """One more scan of the current stop without a depth image (scans are
        stacked: they usually come faster than depth images)."""
        f = self._stop._first
        if f is None:
            return False
        return self._stop.add_scan(ranges_m, f.scan_range_min_m, f.scan_range_max_m)

    def end_stop(self) -> Verdict:
        """The stop is over: one observation from all its frames, or the reason why not."""
        acc = self._stop
        self._stop = StopAccumulator(self.cfg)
        if acc.n == 0:
            return self._reject("end_stop: no frame was fed in this stop")
        self.stops_seen += 1
        try:
            st = acc.finish()
        except FeatureError as e:
            self.stops_refused += 1
            return self._reject(str(e))
        bad = self._precheck(st.frame.stamp_s)
        if bad is not None:
            self.stops_refused += 1
            return bad
        v = self._accept(st.scan, st.depth, st.frame, f" ({st.frames_used} of {acc.n} frames averaged)")
        if not v.accepted:
            self.stops_refused += 1
        return v

    def drop_stop(self) -> None:
        """Forget the frames of the current stop (an input of it was refused)."""
        self._stop = StopAccumulator(self.cfg)

    def add_stop(self, frames, scans=()) -> Verdict:
        """All frames of one stop at once (``scans``: extra range arrays of the stop)."""
        for f in frames:
            self.feed(f)
        for r in scans:
            self.feed_scan(r)
        return self.end_stop()

    def _accept(self, sf, df, frame: LrfFrame, extra: str = "") -> Verdict:
        cfg = self.cfg
        C = sf.corners_m
        for k, o in enumerate(self.observations):
            dist = np.linalg.norm(o.corners_laser_m - C, axis=1).max()
            dang = abs((_direction_deg(o.corners_laser_m) - _direction_deg(C) + 180) % 360 - 180)
            if dist < cfg.duplicate_distance_m and dang < cfg.duplicate_angle_deg:
                return self._reject(f"pose too similar to observation {k + 1} "
                                    f"(corners within {dist * 100:.1f} cm, {dang:.1f} deg): move the AGV")
        obs = make_observation(sf, df, frame.stamp_s)
        self.observations.append(obs)
        self.features.append((sf, df))
        self.stamps.append(frame.stamp_s)
        self.frames_meta = (frame.laser_frame, frame.camera_frame)
        self._last_fit = None
        self.last_reason = f"observation {len(self.observations)} accepted{extra}"
        return Verdict(True, self.last_reason)

    def _reject(self, reason: str) -> Verdict:
        self.last_reason = reason
        return Verdict(False, reason)

    def ready(self) -> bool:
        return len(self.observations) >= max(2, self.cfg.min_observations)

    # ------------------------------------------------------------------
    def solver_options(self) -> OursOptions:
        return OursOptions(laser_sigma_m=None, corner_weight=self.cfg.corner_weight,
                           plane_sigma_floor_m=self.cfg.plane_sigma_floor_m,
                           laser_sigma_floor_m=self.cfg.laser_sigma_floor_m,
                           target_sigma_deg=self.cfg.target_sigma_deg, target_sigma_mm=self.cfg.target_sigma_mm)

    def fit(self, solver: str | None = None) -> CalibrationResult:
        """Solve with ``'ours'`` (default) or ``'paper'``. Raises NotReadyError
        when fewer than ``min_observations`` observations."""
        solver = solver or self.cfg.solver
        if solver not in ("ours", "paper"):
            raise CalibError(f"unknown solver {solver!r} (use 'ours' or 'paper')")
        if not self.ready():
            raise NotReadyError(f"need >= {max(2, self.cfg.min_observations)} observations, "
                                f"have {len(self.observations)}")
        obs, flags = resolve_assignment(self.observations)
        opt = self.solver_options()
        obs, dropped, _ = reject_outlier_observations(obs, options=opt)
        _, _, info = solve_paper(obs)
        paper = {"point_to_line_mm": 1000 * info["point_to_line_m"],
                 "point_to_line_so3_mm": 1000 * info["point_to_line_so3_m"],
                 "orthonormality_error": info["orthonormality_error"],
                 "condition_number": info["condition"]}
        laser_frame, camera_frame = self.frames_meta
        notes = []
        if dropped:
            notes.append(f"observations {[i + 1 for i in dropped]} disagree with the others (a laser segment lies "
                         "far from its camera plane: board mis-detected?) and were left out of the fit")
        if any(flags):
            notes.append(f"triangle correspondence swapped for observations "
                         f"{[i + 1 for i, f in enumerate(flags) if f]} (left/right check)")
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
            "laser_sigma_mm": [1000 * o.laser_sigma_m for o in obs],
            "depth_noise_k_per_m": [float(f[1].noise.k_per_m) for f in self.features
                                    if getattr(f[1], "noise", None) is not None],
        }
        if solver == "paper":
            T = info["T"]
            cov = covariance_left(sol.covariance, sol.T[:3, :3])  # the paper gives none; ours as a guide
            notes.append("paper solver: R projected to SO(3) (raw R orthonormality error "
                         f"{info['orthonormality_error']:.2e}); covariance from our solver")
            metrics["point_to_line_mm"] = paper["point_to_line_so3_mm"]
        else:
            T = sol.T
            # result convention: perturbation (exp(dtheta) R, t + dt), rotation in the camera frame
            cov = covariance_left(sol.covariance, sol.T[:3, :3])
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
        st = {"observations": n, "needed": need, "frames_collected": n, "frames_needed": need,
              "last_reason": self.last_reason, "stops_seen": self.stops_seen, "stops_refused": self.stops_refused,
              "frames_in_current_stop": self._stop.n,
              "error_mm": math.nan, "sigma_rotation_deg": math.nan, "sigma_translation_mm": math.nan,
              "sigma": [math.nan, math.nan],
              "done": False, "advice": "" if n >= need else f"collect {need - n} more observation(s)"}
        if n >= need:
            try:
                if self._last_fit is None:
                    self.fit()
                res, _sol = self._last_fit
            except (CalibError, ValueError, np.linalg.LinAlgError) as e:
                st["advice"] = f"fit failed: {e}"
                return st
            sr, stt = res.sigma()
            err = res.metrics["point_to_line_mm"]
            st.update(error_mm=err, sigma_rotation_deg=sr, sigma_translation_mm=stt, sigma=[sr, stt],
                      observability=res.metrics["observability"])
            st["done"] = bool(sr <= self.cfg.target_sigma_deg and stt <= self.cfg.target_sigma_mm
                              and err <= 1000 * self.cfg.error_threshold_m)
            st["advice"] = "" if st["done"] else (res.metrics["advice"] or
                                                   "add another observation from a different pose")
        return st


class StaticDetector:
    """Fires once per stop: ``update`` returns True the first time the scan has
    been static for ``static_time_s``; re-arms after motion. ``still`` says
    whether the last scan matched the stop's first one.

    Static means: the range change against the stop's first scan, smoothed along the
    beams over ``smooth_beams`` (a motion of the scanner changes neighbouring beams alike,
    noise does not), has a median magnitude below the larger of ``range_tol_m`` and
    ``noise_factor`` times the noise of that smoothed change, which is measured from the
    same two scans (the beam-to-beam scatter of the change). So a noisy laser does not read
    as moving, and a slowly creeping robot (a few mm per scan at the end of a deceleration)
    is not taken as stopped, whatever the laser's noise."""

    def __init__(self, static_time_s: float = 1.0, range_tol_m: float = 0.005, smooth_beams: int = 15,
                 noise_factor: float = 1.3):
        self.static_time_s = static_time_s
        self.range_tol_m = range_tol_m
        self.smooth_beams = max(1, int(smooth_beams))
        self.noise_factor = noise_factor
        self._ref = None
        self._since = None
        self._fired = False
        self.still = False
        self.last_change_m = math.nan     # the statistic and its threshold at the last update
        self.last_threshold_m = math.nan

    @property
    def since_s(self) -> float | None:
        """Stamp of the reference scan: the start of the current still period (if it lasts)."""
        return self._since

    def change(self, r: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
        """(median |smoothed range change|, threshold) between two scans; (inf, thr) when
        they share no valid beam."""
        d = r - ref
        ok = np.isfinite(d)
        if ok.sum() < 3:
            return math.inf, self.range_tol_m
        w = min(self.smooth_beams, int(ok.sum()))
        k = np.ones(w)
        dz = np.where(ok, d, 0.0)
        num = np.convolve(dz, k, mode="same")
        cnt = np.convolve(ok.astype(float), k, mode="same")
        good = ok & (cnt >= 0.5 * w)
        if not good.any():
            return math.inf, self.range_tol_m
        sm = num[good] / cnt[good]
        hf = d[good] - sm
        sig_d = 1.4826 * float(np.median(np.abs(hf - np.median(hf)))) * math.sqrt(w / max(w - 1, 1))
        thr = max(self.range_tol_m, self.noise_factor * sig_d / math.sqrt(w))
        return float(np.median(np.abs(sm))), thr

    def update(self, stamp_s: float, ranges) -> bool:
        r = np.asarray(ranges, dtype=float).ravel()
        r = np.where(np.isfinite(r), r, np.nan)
        self.still = False
        if self._ref is None or self._ref.shape != r.shape:
            self._ref, self._since, self._fired = r, stamp_s, False
            return False
        self.last_change_m, self.last_threshold_m = self.change(r, self._ref)
        if not self.last_change_m <= self.last_threshold_m:
            self._ref, self._since, self._fired = r, stamp_s, False
            return False
        self.still = True
        if not self._fired and stamp_s - self._since >= self.static_time_s:
            self._fired = True
            return True
        return False
