"""BoardCalibrator: collects board placements and solves every camera at once (ROS-free).

``add(BoardFrame) -> Verdict`` finds the board in the LiDAR sweep and in every
camera image, ``fit() -> CalibrationSet`` returns one
:class:`~lidar_cam_calib.core.result.CalibrationResult` per calibrated camera
(``T_camera_lidar``, covariance from the joint fit, metrics, observability
and advice), the camera-to-camera transforms in ``extras`` and, in
``refused``, each camera that could not be calibrated with the reason.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.calibrator import Verdict, cfg_field, validate_config
from ..core.errors import CalibError, NotReadyError
from ..core.result import CalibrationResult, CalibrationSet
from .frame import BoardFrame, BoardGeometry
from .image_corners import CornersNotFound, detect_image_corners
from .lidar_board import BoardNotFound, LidarDetectConfig, StillBoardDetector, detect_board
from .solvers import (SOLVERS, Observation, OursOptions, SolveError, camera_metrics, missing_placements,
                      observability, placement_coverage, plane_only_start, relative_transform, resolve_symmetry,
                      solve_epnp, solve_kabsch, solve_ours, solve_paper)


@dataclasses.dataclass
class BoardConfig:
    """Parameters of the board method (each one a described ROS parameter)."""
    camera_names: list = cfg_field(["cam0"], "names of the cameras to calibrate; each name N has its own "
                                   "N.image_topic, N.camera_info_topic and optional N.frame_id", length=(1, 8),
                                   read_only=True)
    board_size_m: list = cfg_field([1.0, 0.7], "outer size of the board (long, short side) in metres, "
                                   "reflective border included", range=(0.1, 5.0), length=2)
    board_squares: list = cfg_field([10, 7], "number of checker squares (long, short side); inner corners "
                                    "are one fewer each", range=(3, 40), length=2)
    board_square_m: float = cfg_field(0.055, "side of one checker square in metres", range=(0.005, 0.5),
                                      exclusive_min=True)
    intensity_threshold: float = cfg_field(0.0, "LiDAR intensity above which a point is on the reflective "
                                           "border; 0 = automatic from the intensity histogram (the paper "
                                           "uses 250 on a 0-255 RS-16 scale)", range=(0.0, 1e9))
    min_rings: int = cfg_field(4, "fewest LiDAR rings that must cross the board", range=(2, 256))
    range_min_m: float = cfg_field(0.5, "ignore LiDAR points nearer than this", range=(0.0, 100.0))
    range_max_m: float = cfg_field(15.0, "ignore LiDAR points farther than this", range=(1.0, 500.0))
    min_placements: int = cfg_field(3, "placements needed before the first fit", range=(1, 1000))
    min_frames_per_camera: int = cfg_field(4, "placements a camera must share with the LiDAR to be "
                                           "calibrated (fewer: refused with the reason)", range=(2, 1000))
    max_placements: int = cfg_field(200, "stop collecting after this many placements", range=(1, 10000))
    duplicate_distance_m: float = cfg_field(0.05, "a placement whose board centre is within this of an "
                                            "accepted one (and normal within duplicate_angle_deg) is a "
                                            "duplicate", range=(0.0, 2.0))
    duplicate_angle_deg: float = cfg_field(3.0, "see duplicate_distance_m", range=(0.0, 90.0))
    max_image_skew_s: float = cfg_field(0.2, "largest |image stamp - sweep stamp| for an image to be used "
                                        "with a sweep", range=(0.0, 10.0))
    pixel_sigma_px: float = cfg_field(0.3, "prior corner noise in pixels (re-estimated from the data)",
                                      range=(0.01, 10.0), exclusive_min=True)
    range_sigma_m: float = cfg_field(0.02, "prior LiDAR range noise in metres (re-estimated from the data)",
                                     range=(0.0005, 0.5), exclusive_min=True)
    max_sigma_deg: float = cfg_field(0.3, "a camera whose rotation 1-sigma is above this is refused, not "
                                     "published", range=(0.0, 90.0), exclusive_min=True)
    max_sigma_mm: float = cfg_field(15.0, "a camera whose translation 1-sigma is above this is refused",
                                    range=(0.0, 10000.0), exclusive_min=True)
    target_sigma_deg: float = cfg_field(0.05, "'done' when every camera's rotation 1-sigma is below this",
                                        range=(0.0, 90.0), exclusive_min=True)
    target_sigma_mm: float = cfg_field(2.0, "'done' when every camera's translation 1-sigma is below this",
                                       range=(0.0, 10000.0), exclusive_min=True)
    still_time_s: float = cfg_field(1.0, "the board must stay still this long before a placement is taken",
                                    range=(0.0, 60.0))
    still_tolerance_m: float = cfg_field(0.02, "board centre movement still counted as still",
                                         range=(0.0, 1.0))
    use_ring_ends: bool = cfg_field(True, "use where each LiDAR ring enters and leaves the board (the board's "
                                    "outline); false for a dense scanner without rings: the board plane only")
    solver: str = cfg_field("ours", "solver used for the published result", choices=SOLVERS)

    def board(self) -> BoardGeometry:
        return BoardGeometry(tuple(int(v) for v in self.board_squares), float(self.board_square_m),
                             tuple(float(v) for v in self.board_size_m))

    def detect_config(self) -> LidarDetectConfig:
        return LidarDetectConfig(intensity_threshold=self.intensity_threshold or None, min_rings=int(self.min_rings),
                                 range_min_m=float(self.range_min_m), range_max_m=float(self.range_max_m),
                                 use_edges=bool(self.use_ring_ends))


class BoardCalibrator:
    """Collects placements (``add``) and solves all cameras (``fit``)."""

    def __init__(self, cfg: BoardConfig | None = None):
        self.cfg = cfg or BoardConfig()
        validate_config(self.cfg)
        self.board = self.cfg.board()
        self.reset()

    def reset(self) -> None:
        self.observations: list = []
        self.cameras: dict = {}     # name -> CameraModel (last seen)
        self.frame_ids: dict = {}   # name -> optical frame id
        self.lidar_frame = "lidar"
        self.last_reason = "waiting for the first placement"
        self.camera_reasons: dict = {}
        self._last = None
        self._failed: tuple | None = None  # (placements, reason) of the last failed fit
        self.still = StillBoardDetector(self.cfg.still_time_s, self.cfg.still_tolerance_m)

    # ------------------------------------------------------------------
    def detect_lidar(self, frame: BoardFrame):
        """The LiDAR board of a frame (raises BoardNotFound); the node uses it
        with :attr:`still` to decide when to capture."""
        return detect_board(frame.points, frame.intensity, frame.ring, self.board, self.cfg.detect_config())

    def add(self, frame: BoardFrame, lidar_board=None) -> Verdict:
        cfg = self.cfg
        if len(self.observations) >= cfg.max_placements:
            return self._reject(f"already {cfg.max_placements} placements (max_placements): fit or recalibrate")
        names = list(cfg.camera_names) or list(frame.images)
        try:
            lb = lidar_board if lidar_board is not None else self.detect_lidar(frame)
        except BoardNotFound as e:
            return self._reject(str(e))
        for k, o in enumerate(self.observations):
            dc = float(np.linalg.norm(o.lidar.centre - lb.centre))
            da = math.degrees(math.acos(min(1.0, abs(float(o.lidar.normal @ lb.normal)))))
            if dc < cfg.duplicate_distance_m and da < cfg.duplicate_angle_deg:
                return self._reject(f"the board is where it was in placement {k + 1} ({100 * dc:.1f} cm, "
                                    f"{da:.1f} deg): move or tilt it to a new place")
        found, why = {}, {}
        for n in names:
            ci = frame.images.get(n)
            if ci is None:
                why[n] = f"no image from camera {n} with this sweep"
                continue
            if ci.camera is None:
                why[n] = f"camera {n}: no CameraInfo received yet (intrinsics needed)"
                continue
            if abs(ci.stamp_s - frame.stamp_s) > cfg.max_image_skew_s:
                why[n] = (f"camera {n}: image {ci.stamp_s - frame.stamp_s:+.3f} s from the sweep "
                          f"(max_image_skew_s {cfg.max_image_skew_s})")
                continue
            try:
                found[n] = detect_image_corners(ci.image, ci.camera, self.board)
            except (CornersNotFound, CalibError) as e:
                why[n] = f"camera {n}: {e}"
                continue
            self.cameras[n] = ci.camera
            self.frame_ids[n] = ci.frame_id
        self.camera_reasons.update(why)
        if not found:
            return self._reject("board found by the LiDAR but in no camera image (" + "; ".join(why.values()) + ")")
        self.lidar_frame = frame.lidar_frame
        self.observations.append(Observation(float(frame.stamp_s), lb, found))
        self._last = None
        miss = f"; not in {', '.join(sorted(why))}" if why else ""
        self.last_reason = (f"placement {len(self.observations)} accepted (LiDAR {lb.rings_on_board} rings, "
                            f"cameras {', '.join(sorted(found))}{miss})")
        return Verdict(True, self.last_reason)

    def _reject(self, reason: str) -> Verdict:
        self.last_reason = reason
        return Verdict(False, reason)

    def frames_per_camera(self) -> dict:
        out = {n: 0 for n in self.cfg.camera_names}
        for o in self.observations:
            for n in o.images:
                out[n] = out.get(n, 0) + 1
        return out

    def ready(self) -> bool:
        return (len(self.observations) >= self.cfg.min_placements and
                max(self.frames_per_camera().values(), default=0) >= self.cfg.min_frames_per_camera)

    # ------------------------------------------------------------------
    def solve_all(self, solver: str | None = None) -> dict:
        """Every solver (or one) on the collected placements: {solver: {cam: T}} plus
        '_obs' (resolved observations), '_refused', '_ours' (OursSolution)."""
        if self.cfg.use_ring_ends:
            obs, _init, refused = resolve_symmetry(self.observations, self.board, min_frames=2)
        else:
            obs, _init = plane_only_start(self.observations, self.board)
            refused = {}
        out = {"_obs": obs, "_refused": refused}
        cams = {n: m for n, m in self.cameras.items() if any(n in o.images for o in obs)}
        if not cams:
            return out
        ep = solve_epnp(obs, self.board) if self.cfg.use_ring_ends else \
            {c: _init[c] for c in cams if c in _init}
        out["epnp"] = ep
        if solver in (None, "kabsch_3d3d"):
            out["kabsch_3d3d"] = solve_kabsch(obs, self.board)
        if solver in (None, "paper"):
            out["paper"], out["_paper_points"] = solve_paper(obs, self.board, ep)
        # ours always runs: it gives every solver's covariance and the advice
        opt = OursOptions(pixel_sigma_px=self.cfg.pixel_sigma_px, range_sigma_m=self.cfg.range_sigma_m,
                          use_edges=bool(self.cfg.use_ring_ends))
        sol = solve_ours(obs, self.board, cams, ep, opt)
        out["ours"] = sol.T
        out["_ours"] = sol
        return out

    def fit(self, solver: str | None = None) -> CalibrationSet:
        try:
            cs = self._fit(solver)
        except CalibError as e:
            self._failed = (len(self.observations), str(e))
            raise
        self._failed = None
        return cs

    def _fit(self, solver: str | None = None) -> CalibrationSet:
        cfg = self.cfg
        solver = solver or cfg.solver
        if solver not in SOLVERS:
            raise CalibError(f"unknown solver {solver!r}: use one of {', '.join(SOLVERS)}")
        if not self.ready():
            fpc = self.frames_per_camera()
            raise NotReadyError(f"need {cfg.min_placements} placements and one camera with "
                                f"{cfg.min_frames_per_camera}; have {len(self.observations)} placements, per "
                                f"camera {fpc}")
        refused = {}
        fpc = self.frames_per_camera()
        for n in cfg.camera_names:
            if fpc.get(n, 0) == 0:
                refused[n] = (f"camera {n} never saw the board together with the LiDAR"
                              + (f" (last: {self.camera_reasons[n]})" if n in self.camera_reasons else ""))
        # cameras with too few placements or all placements alike are left out before solving
        keep = []
        for n, k in fpc.items():
            if k == 0 or n in refused:
                continue
            if k < cfg.min_frames_per_camera:
                refused[n] = (f"camera {n} saw the board in {k} placement(s); {cfg.min_frames_per_camera} "
                              "needed (min_frames_per_camera)")
                continue
            cs = np.array([o.lidar.centre for o in self.observations if n in o.images])
            ns = np.array([o.lidar.normal for o in self.observations if n in o.images])
            spread_m = float(np.max(np.linalg.norm(cs - cs.mean(0), axis=1)))
            spread_deg = float(np.degrees(np.arccos(np.clip(np.abs(ns @ ns.mean(0) / np.linalg.norm(ns.mean(0))),
                                                            -1, 1))).max())
            if spread_m < 0.15 and spread_deg < 5.0:
                refused[n] = (f"camera {n}: all {k} placements are nearly the same (centres within "
                              f"{100 * spread_m:.0f} cm, normals within {spread_deg:.1f} deg): move the board "
                              "around the image and tilt it")
                continue
            keep.append(n)
        saved_obs = self.observations
        self.observations = [Observation(o.stamp_s, o.lidar, {c: v for c, v in o.images.items() if c in keep})
                             for o in saved_obs]
        self.observations = [o for o in self.observations if o.images]
        try:
            if not self.observations:
                raise SolveError("no camera has enough placements: " + "; ".join(refused.values()))
            sols = self.solve_all(solver)
        finally:
            self.observations = saved_obs
        refused.update(sols.get("_refused", {}))
        obs = sols["_obs"]
        sol = sols.get("_ours")
        if sol is None or solver not in sols:
            raise SolveError("no camera could be calibrated: " + "; ".join(f"{k}: {v}" for k, v in refused.items()))
        results = {}
        for n in sol.cams:
            T = sols[solver][n]
            cov = sol.covariance[n]
            obsv = observability(cov, cfg.max_sigma_deg, cfg.max_sigma_mm)
            cover = placement_coverage(obs, n, self.cameras[n])
            advice = missing_placements(cover, n)
            points = None
            if solver == "paper":
                points = sols["_paper_points"]
            elif solver == "ours":
                Pb = self.board.inner_corners_board()
                points = {i: Pb @ P[:3, :3].T + P[:3, 3] for i, P in enumerate(sol.board_poses)}
            m_own = camera_metrics(obs, n, T, self.cameras[n], self.board, points)
            m_virt = camera_metrics(obs, n, T, self.cameras[n], self.board)
            sr = max(obsv["sigma_rotation_deg"])
            st = max(obsv["sigma_translation_mm"])
            if not (math.isfinite(sr) and math.isfinite(st)) or sr > cfg.max_sigma_deg or st > cfg.max_sigma_mm:
                refused[n] = (f"camera {n}: too little information (1-sigma {sr:.3f} deg / {st:.1f} mm, limits "
                              f"{cfg.max_sigma_deg} deg / {cfg.max_sigma_mm} mm; weakest: "
                              f"{obsv['weakest_direction']}). " + ("; ".join(advice) or "add placements"))
                continue
            metrics = {
                "reprojection_px": m_own["reprojection_px"],
                "normalized_plane_error_mm": m_own["normalized_plane_error_mm"],
                "reprojection_virtual_corners_px": m_virt["reprojection_px"],
                "normalized_plane_error_virtual_mm": m_virt["normalized_plane_error_mm"],
                "frames_used": m_own["frames"],
                "frames_dropped": [int(i) + 1 for i in sol.dropped.get(n, [])],
                "observability": obsv["verdict"],
                "weakest_direction": obsv["weakest_direction"],
                "advice": advice,
                "noise_pixel_sigma_px": sol.noise["pixel_sigma_px"].get(n, math.nan),
                "noise_range_sigma_mm": 1000 * sol.noise["range_sigma_m"],
                "noise_edge_sigma_mm": 1000 * sol.noise["edge_sigma_m"],
                "shrink_median_mm": sol.metrics["shrink_median_mm"],
            }
            notes = []
            if solver != "ours":
                notes.append(f"{solver} solver: covariance from the ours solver on the same data")
            results[n] = CalibrationResult(
                method="board", parent_frame=self.lidar_frame, child_frame=self.frame_ids.get(n, f"{n}_optical_frame"),
                T_child_parent=T, covariance=cov, metrics=metrics, observations_used=m_own["frames"],
                stamps=[o.stamp_s for o in obs if n in o.images], solver=solver, notes=notes)
        if not results:
            raise SolveError("no camera could be calibrated: " + "; ".join(f"{k}: {v}" for k, v in refused.items()))
        extras = {"camera_to_camera": self._camera_to_camera(sol, results, obs, sols[solver]),
                  "placements": len(self.observations)}
        cs = CalibrationSet("board", results, extras, refused)
        self._last = cs
        return cs

    def _camera_to_camera(self, sol, results: dict, obs: list, Ts: dict) -> dict:
        out = {}
        names = [n for n in sol.cams if n in results]
        k = {n: sol.cams.index(n) for n in names}
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                ia, ib = k[a], k[b]
                idx = np.r_[6 * ia:6 * ia + 6, 6 * ib:6 * ib + 6]
                T_ba, cov = relative_transform(Ts[a], Ts[b], sol.joint_covariance[np.ix_(idx, idx)])
                shared = [o for o in obs if a in o.images and b in o.images]
                entry = {"T": [[float(v) for v in row] for row in T_ba],
                         "sigma_rotation_deg": float(np.degrees(np.sqrt(np.diag(cov)[:3]).max())),
                         "sigma_translation_mm": float(1000 * np.sqrt(np.diag(cov)[3:]).max()),
                         "shared_placements": len(shared)}
                if shared:
                    # what the shared boards alone say (camera-only, per placement)
                    from ..core.geometry import inv_T, so3_log
                    d_rot, d_tr = [], []
                    for o in shared:
                        Tb = o.images[b].T_camera_board @ inv_T(o.images[a].T_camera_board)
                        d_rot.append(math.degrees(float(np.linalg.norm(so3_log(Tb[:3, :3] @ T_ba[:3, :3].T)))))
                        d_tr.append(1000 * float(np.linalg.norm(Tb[:3, 3] - T_ba[:3, 3])))
                    entry["shared_boards_median_deviation_deg"] = float(np.median(d_rot))
                    entry["shared_boards_median_deviation_mm"] = float(np.median(d_tr))
                out[f"{a}->{b}"] = entry
        return out

    # ------------------------------------------------------------------
    def status(self) -> dict:
        cfg = self.cfg
        fpc = self.frames_per_camera()
        st = {"placements": len(self.observations), "needed": cfg.min_placements,
              "frames_per_camera": fpc, "needed_per_camera": cfg.min_frames_per_camera,
              "last_reason": self.last_reason, "sigma": {}, "missing": {}, "done": False, "advice": ""}
        obs = self.observations
        for n in cfg.camera_names:
            m = self.cameras.get(n)
            st["missing"][n] = missing_placements(placement_coverage(obs, n, m) if m is not None else {"frames": 0}, n)
        # a failed fit is not repeated on every status refresh: only when a placement was added since
        if self._last is None and self.ready() and (self._failed is None or self._failed[0] != len(obs)):
            try:
                self.fit()
            except CalibError:
                pass
        if self._last is None and self._failed is not None:
            st["advice"] = f"fit failed: {self._failed[1]}"
        if self._last is not None:
            done = True
            for n in cfg.camera_names:
                r = self._last.results.get(n)
                if r is None:
                    done = False
                    st["sigma"][n] = {"refused": self._last.refused.get(n, "not calibrated")}
                    continue
                sr, stt = r.sigma()
                st["sigma"][n] = {"rotation_deg": sr, "translation_mm": stt}
                done = done and sr <= cfg.target_sigma_deg and stt <= cfg.target_sigma_mm
            st["done"] = bool(done)
        adv = []
        for n in cfg.camera_names:
            if fpc.get(n, 0) < cfg.min_frames_per_camera:
                adv.append(f"camera {n}: {cfg.min_frames_per_camera - fpc.get(n, 0)} more placement(s) needed")
            adv += st["missing"][n][:2]
        if not st["advice"]:
            st["advice"] = "" if st["done"] else "; ".join(adv[:6])
        return st


__all__ = ["BoardCalibrator", "BoardConfig"]
