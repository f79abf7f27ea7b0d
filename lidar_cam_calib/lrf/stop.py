"""One AGV stop, one observation: every frame of a static stop is used (ROS-free).

While the AGV stands still the scene does not change, so the frames of a stop are
averaged: depth per pixel (mean over the frames where the pixel is valid; a pixel
valid in fewer than half of them is dropped) and ranges per beam (same rule). The
noise of the average falls with the number of frames; the feature extraction
estimates it from the averaged data itself, so nothing has to be told.

:class:`StopAccumulator` takes the frames one by one (``add``), tries the features
on the running average after 1, 2, 4, 8, ... frames until the board is found (so a
bad first frame does not lose the stop), and ``finish`` returns the features of the
whole stop or raises :class:`~lidar_cam_calib.lrf.features.FeatureError` with the
reason when the whole stop failed. A frame whose scan differs from the stop's
average (the AGV or the board moved) restarts the stop.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..core.calibrator import Verdict
from .features import (
    DepthFeatures,
    FeatureConfig,
    FeatureError,
    ScanFeatures,
    extract_depth_features,
    extract_scan_features,
)
from .frame import LrfFrame


@dataclasses.dataclass
class StopFeatures:
    """What one stop yields: the features, the averaged frame, how many frames went in."""
    scan: ScanFeatures
    depth: DepthFeatures
    frame: LrfFrame
    frames_used: int
    attempts: int


class StopAccumulator:
    """Average the frames of one stop and find the board in the average."""

    def __init__(self, cfg: FeatureConfig | None = None, motion_tol_m: float = 0.03, max_frames: int = 64):
        self.cfg = cfg or FeatureConfig()
        self.motion_tol_m = float(motion_tol_m)
        self.max_frames = int(max_frames)
        self.restarts = 0
        self.reset()

    def reset(self) -> None:
        self.n = 0
        self._dsum = self._dcnt = self._rsum = self._rcnt = None
        self._first = None
        self._last_stamp = None
        self._found: StopFeatures | None = None
        self._found_n = 0
        self.attempts = 0
        self.n_scans = 0
        self.last_reason = "no frame in this stop yet"

    # ------------------------------------------------------------------
    def add(self, frame: LrfFrame) -> Verdict:
        """Add one frame of the stop. The verdict says whether the board has been
        found in the average so far (the stop is not over: call :meth:`finish`)."""
        d = np.asarray(frame.depth_m, dtype=np.float32)
        r = np.asarray(frame.scan_ranges_m, dtype=np.float32)
        if self.n and (d.shape != self._dsum.shape or r.shape != self._rsum.shape):
            self.reset()
            self.restarts += 1
            self.last_reason = "image size or scan length changed: stop restarted"
        if self.n:
            mean_r = self._mean_ranges()
            ok = np.isfinite(mean_r) & np.isfinite(r)
            if ok.sum() > 10 and float(np.median(np.abs(r[ok] - mean_r[ok]))) > self.motion_tol_m:
                self.reset()
                self.restarts += 1
                self.last_reason = "the scan changed (AGV or board moved): stop restarted"
        if self.n >= self.max_frames:
            return Verdict(self._found is not None, f"stop already has {self.max_frames} frames")
        dv = np.isfinite(d) & (d > 0)
        rv = np.isfinite(r) & (r >= frame.scan_range_min_m) & (r <= frame.scan_range_max_m)
        if self.n == 0:
            self._dsum = np.zeros(d.shape, np.float32)
            self._dcnt = np.zeros(d.shape, np.int16)
            self._rsum = np.zeros(r.shape, np.float64)
            self._rcnt = np.zeros(r.shape, np.int32)
            self._first = frame
        self._dsum += np.where(dv, d, np.float32(0.0))
        self._dcnt += dv
        self._rsum += np.where(rv, r, 0.0)
        self._rcnt += rv
        self._last_stamp = float(frame.stamp_s)
        self.n += 1
        self.n_scans += 1
        # try on the running average after 1, 2, 4, 8, ... frames until the board is found
        if self._found is None and (self.n & (self.n - 1)) == 0:
            self._attempt()
        if self._found is not None:
            return Verdict(True, f"board found after {self._found_n} frame(s) of this stop")
        return Verdict(False, self.last_reason)

    def add_scan(self, ranges_m, range_min_m: float = 0.0, range_max_m: float = np.inf) -> bool:
        """Stack one more scan of the stop (scans usually come faster than depth
        images). Needs a frame first (for the scan geometry); a scan of another
        length or one that moved is ignored (returns False)."""
        if self.n == 0:
            return False
        r = np.asarray(ranges_m, dtype=np.float32).ravel()
        if r.shape != self._rsum.shape:
            return False
        mean_r = self._mean_ranges()
        ok = np.isfinite(mean_r) & np.isfinite(r)
        if ok.sum() > 10 and float(np.median(np.abs(r[ok] - mean_r[ok]))) > self.motion_tol_m:
            return False
        rv = np.isfinite(r) & (r >= range_min_m) & (r <= range_max_m) & (r > 0)
        self._rsum += np.where(rv, r, 0.0)
        self._rcnt += rv
        self.n_scans += 1
        return True

    def _mean_ranges(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            m = (self._rsum / self._rcnt).astype(np.float32)
        m[self._rcnt * 2 < self.n_scans] = np.nan
        return m

    def average(self) -> LrfFrame:
        """The stop's averaged frame (stamp of the middle of the stop)."""
        if self.n == 0:
            raise FeatureError("stop: no frame was added")
        with np.errstate(invalid="ignore", divide="ignore"):
            depth = (self._dsum / self._dcnt).astype(np.float32)
        depth[self._dcnt * 2 < self.n] = np.nan
        f = self._first
        stamp = 0.5 * (float(f.stamp_s) + float(self._last_stamp))
        return LrfFrame(stamp, self._mean_ranges(), f.scan_angle_min_rad, f.scan_angle_increment_rad,
                        f.scan_range_min_m, f.scan_range_max_m, depth, f.camera, f.laser_frame, f.camera_frame)

    def _attempt(self, prior: StopFeatures | None = None) -> StopFeatures | None:
        self.attempts += 1
        fr = self.average()
        try:
            sf = extract_scan_features(fr, self.cfg)
            df = None
            if prior is not None:  # the scene is static: refit the planes found before, no search
                try:
                    df = extract_depth_features(fr, self.cfg, prior=prior.depth)
                except FeatureError:
                    df = None
            if df is None:
                df = extract_depth_features(fr, self.cfg)
        except FeatureError as e:
            self.last_reason = f"{e} (average of {self.n} frame(s))"
            return None
        self._found = StopFeatures(sf, df, fr, self.n, self.attempts)
        self._found_n = self.n
        self.last_reason = f"board found in the average of {self.n} frame(s)"
        return self._found

    def finish(self) -> StopFeatures:
        """Features of the whole stop (from the average of all its frames when
        more came in since the board was found). Raises FeatureError with the
        reason when the board was found in no average of this stop."""
        if self.n == 0:
            raise FeatureError("stop: no frame was added")
        if self._found is None or self._found_n < self.n:
            prev = self._found
            got = self._attempt(prior=prev)
            if got is None and prev is not None:
                self._found = prev  # the full average failed where a shorter one worked: keep that
            elif got is None:
                raise FeatureError(f"stop of {self.n} frame(s): {self.last_reason}")
        self._found.attempts = self.attempts
        return self._found
