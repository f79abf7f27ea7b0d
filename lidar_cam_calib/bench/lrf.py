"""Benchmark of the lrf solvers: paper (eq. 11) vs ours, same data, one run.

Two data sources:
* ``synthetic_observations`` -- analytic features straight from ground truth
  (ray-cast laser points with range noise, camera planes fitted to noisy
  depth samples with sigma = k z^2); no images, used by the solver tests.
* the simulator (lidar_cam_calib.sim) -- full frames through the real
  feature extraction (``run_bench``).

``main(argv)``: ``--observations N --seed S --repeats K --json FILE --sweep``;
``--family --seeds N [--stops K] [--frames F]``: scenes drawn from the seed
(:mod:`lidar_cam_calib.sim.lrf_family`), every stop through the stop
accumulator, paper vs ours on identical features beside the scene's
Cramer-Rao bound, Mahalanobis^2 of ours, per-seed rows and aggregate;
``--family --detection``: the single-frame detection rate.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time

import numpy as np

from ..core.fitting import fit_line_2d_lsq, fit_plane_lsq, intersect_lines_2d
from ..core.geometry import R_BODY_OPTICAL, R_from_rpy, inv_T, make_T, pose_errors
from ..lrf.features import (
    BoardModel,
    FeatureConfig,
    corner_covariance,
    make_observation,
)
from ..lrf.solvers import (
    LrfObservation,
    OursOptions,
    PlaneStats,
    point_to_line_error_m,
    reject_outlier_observations,
    resolve_assignment,
    solve_ours,
    solve_paper,
)


# ----------------------------------------------------------------------------
# Analytic generator
# ----------------------------------------------------------------------------
def default_T_camera_laser() -> np.ndarray:
    """Paper-like mount: camera 128 mm ahead, 60 mm left, 10 mm below the laser,
    with small misalignments."""
    R_laser_body_cam = R_from_rpy(*np.radians([1.0, -2.0, 1.5]))
    R_laser_cam = R_laser_body_cam @ R_BODY_OPTICAL
    T_laser_camera = make_T(R_laser_cam, [0.128, 0.060, -0.010])
    return inv_T(T_laser_camera)


def _ray_triangles(origin, dirs, tris):
    """Möller-Trumbore: distance along unit dirs (N,3) to each triangle (T,3,3) -> (N,) min (inf = miss)."""
    best = np.full(len(dirs), np.inf)
    for tri in tris:
        v0, v1, v2 = tri
        e1, e2 = v1 - v0, v2 - v0
        pv = np.cross(dirs, e2)
        det = pv @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = origin - v0
        u = (pv @ tv) * inv
        qv = np.cross(tv, e1)
        v = (dirs @ qv) * inv
        t = (qv @ e2) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
        best = np.where(hit & (t < best), t, best)
    return best


def _sample_triangle(tri, n, rng):
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    return tri[0] + a[:, None] * (tri[1] - tri[0]) + b[:, None] * (tri[2] - tri[0])


def random_board_pose_laser(rng, distance_m=(1.5, 4.0), lateral_m=(-0.8, 0.8), yaw_deg=(-30, 30),
                            tilt_deg=(-10, 10), cross_height_m=(0.28, 0.45)) -> np.ndarray:
    """T_laser_board for a board facing the laser; the scan plane (z = 0)
    crosses the board ``cross_height_m`` above its bottom edge."""
    R0 = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # board x->-y_l, y->z_l, z->-x_l
    yaw = np.radians(rng.uniform(*yaw_deg))
    tilt = np.radians(rng.uniform(*tilt_deg))
    Rz = R_from_rpy(0, 0, yaw)
    Rx = R_from_rpy(tilt, 0, 0)  # tilt about board x (applied in board frame)
    R = Rz @ R0 @ Rx
    h = rng.uniform(*cross_height_m)
    dist = rng.uniform(*distance_m)
    lat = rng.uniform(*lateral_m)
    # bottom-centre such that the point at board height h lies at (dist, lat, 0)
    p_h = np.array([dist, lat, 0.0])
    origin = p_h - R @ np.array([0.0, h, 0.0])
    return make_T(R, origin)


def synthetic_observation(T_camera_laser, T_laser_board, rng, board: BoardModel | None = None,
                          laser_sigma_m=0.0125, depth_k=0.0031, depth_floor_m=0.001,
                          angle_increment_deg=0.042, fx_px=268.5, pixel_stride=2,
                          trim_m=0.02, true_corners=False) -> LrfObservation:
    """One analytic observation: laser points ray-cast on the board faces
    (range noise), lines by TLS with the true face labels, corners by
    intersection; camera planes fitted (weighted LSQ) to noisy samples of
    each face (density of a ``fx_px`` camera at ``pixel_stride``)."""
    board = board or BoardModel()
    faces = board.face_triangles()
    Rlb, tlb = T_laser_board[:3, :3], T_laser_board[:3, 3]
    # laser ray casting
    c = tlb + Rlb @ np.array([0.0, 0.4, 0.0])
    ang0 = math.atan2(c[1], c[0])
    span = 0.8 / max(np.linalg.norm(c), 0.5)
    inc = math.radians(angle_increment_deg)
    ang = ang0 + np.arange(-span, span, inc)
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    dist = np.stack([_ray_triangles(np.zeros(3), dirs, [Rlb @ t.T + tlb[:, None] for t in []] or
                                    [(Rlb @ tri.T).T + tlb for tri in f]) for f in faces], axis=1)
    face = np.argmin(dist, axis=1)
    r = dist[np.arange(len(ang)), face]
    hit = np.isfinite(r)
    r = r + rng.normal(0, laser_sigma_m, len(r))
    xy = np.column_stack([r * np.cos(ang), r * np.sin(ang)])[hit][::-1]  # left to right
    face = face[hit][::-1]
    pts = [xy[face == f] for f in range(3)]
    lines = [fit_line_2d_lsq(p) for p in pts]
    F = intersect_lines_2d(*lines[0], *lines[1])
    G = intersect_lines_2d(*lines[1], *lines[2])
    H = intersect_lines_2d(*lines[2], *lines[0])
    corners = np.stack([F, G, H])
    pts = [p[np.min(np.stack([np.linalg.norm(p - q, axis=1) for q in corners]), axis=0) > trim_m] for p in pts]
    lines = [fit_line_2d_lsq(p) for p in pts]
    corners = np.stack([intersect_lines_2d(*lines[0], *lines[1]), intersect_lines_2d(*lines[1], *lines[2]),
                        intersect_lines_2d(*lines[2], *lines[0])])
    cov = np.stack([corner_covariance(lines[0], pts[0], lines[1], pts[1], laser_sigma_m, corners[0]),
                    corner_covariance(lines[1], pts[1], lines[2], pts[2], laser_sigma_m, corners[1]),
                    corner_covariance(lines[2], pts[2], lines[0], pts[0], laser_sigma_m, corners[2])])
    # camera planes
    T_cb = T_camera_laser @ T_laser_board
    Rcb, tcb = T_cb[:3, :3], T_cb[:3, 3]
    planes, stats = [], []
    for f, tris in enumerate(faces):
        if f == 0:  # visible base: rectangle minus the triangle ABD under the tent
            v = board.vertices
            samp = np.concatenate([_sample_triangle(t, 4000, rng) for t in tris])
            A, B, D = v["A"][:2], v["B"][:2], v["D"][:2]
            def _side(p, a, b):
                return (b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0])
            s1, s2, s3 = _side(samp[:, :2], A, B), _side(samp[:, :2], B, D), _side(samp[:, :2], D, A)
            inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
            samp = samp[~inside]
        else:
            samp = _sample_triangle(tris[0], 4000, rng)
        pc = samp @ Rcb.T + tcb
        # number of pixels this face covers
        area = 0.5 * sum(np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) for t in tris)
        if f == 0:
            area -= 0.5 * np.linalg.norm(np.cross(board.vertices["B"] - board.vertices["A"],
                                                  board.vertices["D"] - board.vertices["A"]))
        zc = float(np.median(pc[:, 2]))
        npx = int(np.clip(area * (fx_px / zc) ** 2 * 0.7 / pixel_stride ** 2, 50, len(pc)))
        pc = pc[:npx]
        sig = np.maximum(depth_k * pc[:, 2] ** 2, depth_floor_m)
        ray = pc / pc[:, 2:3]
        pc = pc + ray * rng.normal(0, 1, len(pc))[:, None] * sig[:, None]
        n, d = fit_plane_lsq(pc)
        ru = pc / np.linalg.norm(pc, axis=1, keepdims=True)
        sp = np.maximum(sig * np.abs(ru @ n), 1e-4)
        n, d = fit_plane_lsq(pc, weights=1.0 / sp ** 2)
        planes.append([*n, d])
        stats.append(PlaneStats.from_points(pc, n, d, weights=1.0 / sp ** 2))
    if true_corners:
        pass
    return LrfObservation(corners, np.array(planes), tuple(pts), tuple(stats), cov, 0.0, laser_sigma_m)


def synthetic_observations(n: int, seed: int, T_camera_laser=None, **kw) -> tuple[list, np.ndarray]:
    """``n`` analytic observations at random board poses and the true T_camera_laser."""
    rng = np.random.default_rng(seed)
    T = default_T_camera_laser() if T_camera_laser is None else np.asarray(T_camera_laser)
    pose_kw = {k: kw.pop(k) for k in list(kw) if k in ("distance_m", "lateral_m", "yaw_deg", "tilt_deg",
                                                        "cross_height_m")}
    obs = []
    while len(obs) < n:
        try:
            o = synthetic_observation(T, random_board_pose_laser(rng, **pose_kw), rng, **kw)
        except ValueError:  # a face got too few laser points: draw another pose
            continue
        if min(len(p) for p in o.face_points_laser_m) >= 10:
            obs.append(o)
    return obs, T


# ----------------------------------------------------------------------------
# Evaluation helpers
# ----------------------------------------------------------------------------
def evaluate_solvers(observations, T_true, options: OursOptions | None = None) -> dict:
    """Run paper and ours on the same observations; errors against ``T_true``."""
    out = {}
    t0 = time.perf_counter()
    R_raw, t, info = solve_paper(observations)
    rt = time.perf_counter() - t0
    e_r, e_t = pose_errors(info["T"], T_true)
    out["paper"] = {"rotation_error_deg": e_r, "translation_error_mm": e_t,
                    "point_to_line_mm": 1000 * point_to_line_error_m(R_raw, t, observations),
                    "orthonormality_error": info["orthonormality_error"], "runtime_s": rt,
                    "T": info["T"]}
    t0 = time.perf_counter()
    sol = solve_ours(observations, options=options)
    rt = time.perf_counter() - t0
    e_r, e_t = pose_errors(sol.T, T_true)
    sr, st = sol.sigma_deg_mm()
    out["ours"] = {"rotation_error_deg": e_r, "translation_error_mm": e_t,
                   "point_to_line_mm": 1000 * sol.metrics["point_to_line_m"], "runtime_s": rt,
                   "sigma_rotation_deg": sr, "sigma_translation_mm": st,
                   "observability": sol.observability["verdict"], "T": sol.T}
    return out


def _strip(d: dict) -> dict:
    return {k: v for k, v in d.items() if k != "T"}


# ----------------------------------------------------------------------------
# Simulator bench
# ----------------------------------------------------------------------------
def _sim_observations(n: int, seed: int, scenario=None, right: bool = False, cfg=None):
    from ..lrf.features import (
        FeatureError,
        extract_depth_features,
        extract_scan_features,
    )
    from ..lrf.frame import LrfFrame
    from ..sim.lrf_world import simulate
    from ..sim.scenario import load_scenario
    sc = load_scenario(scenario)
    sc.poses.n_poses = max(n, 2)
    run = simulate(sc, np.random.default_rng(seed))
    cfg = cfg or FeatureConfig(board=BoardModel.from_config(sc.board), laser_sigma_m=sc.laser.range_sigma_m)
    out = {False: [], True: []}
    failures = []
    feature_s = []
    for o in run.observations:
        try:
            per = {}
            for side in ((False, True) if right else (False,)):
                fr = LrfFrame.from_sim(o, right=side)
                t0 = time.perf_counter()
                per[side] = make_observation(extract_scan_features(fr, cfg), extract_depth_features(fr, cfg),
                                             fr.stamp_s, cfg.laser_sigma_m)
                if not side:
                    feature_s.append(time.perf_counter() - t0)
            for side, ob in per.items():
                out[side].append(ob)
        except FeatureError as e:
            failures.append(str(e))
    feature_median_s = float(np.median(feature_s)) if feature_s else float("nan")
    return out, run.truth, failures, feature_median_s


def _prepare(obs):
    if len(obs) < 2:
        return obs, []
    obs, _ = resolve_assignment(obs)
    kept, dropped, _ = reject_outlier_observations(obs)
    return kept, dropped


def run_bench(observations: int, seed: int, scenario=None, source: str = "sim") -> dict:
    """Paper vs ours on the same observations. ``source='sim'`` runs the
    simulator and the real feature extraction (frames whose features fail
    are skipped and counted); ``'synthetic'`` uses analytic features."""
    res = {"method": "lrf", "seed": seed, "observations": observations, "source": source}
    if source == "synthetic":
        obs, T = synthetic_observations(observations, seed)
        r = evaluate_solvers(obs, T)
        res["solvers"] = {k: _strip(v) for k, v in r.items()}
        return res
    out, truth, failures, feature_s = _sim_observations(observations, seed, scenario, right=True)
    res["feature_failures"] = failures
    res["features_ms_per_observation"] = 1000 * feature_s
    left, right = out[False], out[True]
    res["observations_used"] = len(left)
    if len(left) < 2:
        res["error"] = f"only {len(left)} frames with features"
        return res
    # What the node does before solving (both solvers then get the same data):
    # check the triangle pairing, leave out observations that disagree.
    left, dropped = _prepare(left)
    right, _ = _prepare(right)
    res["observations_rejected"] = len(dropped)
    rl = evaluate_solvers(left, truth.T_camera_laser)
    res["solvers"] = {k: _strip(v) for k, v in rl.items()}
    for v in res["solvers"].values():
        # what one observation costs the node: its features plus its share of the fit
        v["ms_per_observation"] = res["features_ms_per_observation"] + 1000 * v["runtime_s"] / len(left)
    if len(right) >= 2:
        rr = evaluate_solvers(right, truth.T_camera_right_laser)
        sb = {}
        for k in ("paper", "ours"):
            T_rl = rr[k]["T"] @ inv_T(rl[k]["T"])
            e_r, e_t = pose_errors(T_rl, truth.T_right_left)
            sb[k] = {"baseline_error_mm": e_t, "rotation_error_deg": e_r,
                     "baseline_mm": float(np.linalg.norm(T_rl[:3, 3]) * 1000)}
        res["stereo_baseline"] = sb
    return res


# ----------------------------------------------------------------------------
# Family bench: scenes drawn from the seed (lidar_cam_calib.sim.lrf_family)
# ----------------------------------------------------------------------------
def _true_noise_observations(obs, laser_sigma_m: float, depth_k: float, frames: int, quant_m: float,
                             scans: int | None = None):
    """Copies of ``obs`` whose noise model is the simulator's true one (for the
    Cramer-Rao bound): laser sigma / sqrt(frames); each plane's variance factor
    = (true sigma / the sigma its weights assumed)^2 at the plane's centroid."""
    out = []
    for o in obs:
        st = []
        for ps in o.plane_stats:
            z = float(ps.centroid[2])
            true = math.sqrt((depth_k * z * z) ** 2 / frames + quant_m ** 2 / frames)
            used = float(o.depth_noise.sigma(z)) if o.depth_noise is not None else true
            st.append(dataclasses.replace(ps, variance_factor=(true / used) ** 2))
        out.append(dataclasses.replace(o, laser_sigma_m=laser_sigma_m / math.sqrt(scans or frames),
                                       plane_stats=tuple(st)))
    return out


def _rms_deg_mm(cov_left: np.ndarray) -> tuple[float, float]:
    """Expected error magnitudes sqrt(trace) of the rotation / translation blocks."""
    d = np.clip(np.diag(cov_left), 0.0, None)
    return float(np.degrees(np.sqrt(d[:3].sum()))), float(1000.0 * np.sqrt(d[3:].sum()))


def run_family_seed(seed: int, n_stops: int | None = None, frames_per_stop: int | None = None,
                    stack_scans: bool = True) -> dict:
    """One scene of the family: every stop through the StopAccumulator (all its
    frames), then paper and ours on identical features; errors, Mahalanobis^2
    of ours against its covariance, and the scene's Cramer-Rao bound."""
    from ..lrf.calibrator import LrfCalibrator, LrfConfig
    from ..lrf.frame import LrfFrame
    from ..lrf.solvers import covariance_left, information_at, mahalanobis2
    from ..sim.lrf_family import draw_scenario, simulate_stops
    sc, fd = draw_scenario(seed, n_stops)
    F = int(frames_per_stop or fd.frames_per_stop)
    NS = max(F, fd.scans_per_stop) if stack_scans else F
    row = {"seed": seed, "stops": sc.poses.n_poses, "frames_per_stop": F, "apex": fd.apex,
           "camera": f"{sc.camera.width_px}x{sc.camera.height_px} fx {sc.camera.fx_px:.0f} "
                     f"k {fd.depth_k_per_m:.4f} {sc.camera.depth_encoding}",
           "laser": f"{sc.laser.resolution_deg:.2f} deg {1000 * fd.laser_sigma_m:.0f} mm"}
    row["scans_per_stop"] = NS
    stops, truth, _world = simulate_stops(sc, F, np.random.default_rng(np.random.SeedSequence([7, seed])),
                                          scans_per_stop=NS)
    board = BoardModel.from_config(sc.board)
    cal = LrfCalibrator(LrfConfig(board=board))   # priors only: the noise comes from the data
    t_feat, reasons = [], []
    for st in stops:
        t0 = time.perf_counter()
        v = cal.add_stop([LrfFrame.from_sim(o) for o in st.frames], st.scans)
        t_feat.append(time.perf_counter() - t0)
        if not v.accepted:
            reasons.append(v.reason)
    row["accepted"] = len(cal.observations)
    row["refusals"] = reasons
    row["ms_per_frame"] = 1000.0 * float(np.sum(t_feat)) / max(1, F * len(stops))
    T_true = truth.T_camera_laser
    if len(cal.observations) < 2:
        row["error"] = f"only {len(cal.observations)} observations"
        return row
    opt = cal.solver_options()
    obs, _flags = resolve_assignment(cal.observations)
    obs, dropped, _ = reject_outlier_observations(obs, options=opt)
    row["dropped"] = len(dropped)
    t0 = time.perf_counter()
    _, _, info = solve_paper(obs)
    t_paper = time.perf_counter() - t0
    er, et = pose_errors(info["T"], T_true)
    row["paper"] = {"rot_deg": er, "trans_mm": et, "runtime_s": t_paper}
    t0 = time.perf_counter()
    sol = solve_ours(obs, options=opt)
    t_ours = time.perf_counter() - t0
    er, et = pose_errors(sol.T, T_true)
    cov = covariance_left(sol.covariance, sol.T[:3, :3])
    sr, stt = _rms_deg_mm(cov)
    row["ours"] = {"rot_deg": er, "trans_mm": et, "runtime_s": t_ours, "sigma_rot_deg": sr, "sigma_trans_mm": stt,
                   "mahalanobis2": mahalanobis2(sol.T, cov, T_true)}
    quant = 0.001 / math.sqrt(12.0) if sc.camera.depth_encoding == "16UC1" else 0.0
    tobs = _true_noise_observations(obs, fd.laser_sigma_m, fd.depth_k_per_m, F, quant, NS)
    crb_opt = dataclasses.replace(opt, laser_sigma_floor_m=0.0, plane_sigma_floor_m=0.0, laser_sigma_m=None)
    info_true = information_at(tobs, T_true, crb_opt)
    try:
        crb = covariance_left(np.linalg.inv(info_true), T_true[:3, :3])
        row["crb"] = dict(zip(("rot_deg", "trans_mm"), _rms_deg_mm(crb)))
    except np.linalg.LinAlgError:
        row["crb"] = {"rot_deg": float("nan"), "trans_mm": float("nan")}
    return row


def detection_rate(seeds: int, seed0: int, min_face_px: int = 2000) -> dict:
    """Single frames (no averaging) of family scenes: in how many of the frames
    whose every face shows >= ``min_face_px`` pixels is the board found in the
    depth image and in the scan; per-frame feature time."""
    from ..lrf.features import FeatureError, extract_depth_features, extract_scan_features
    from ..lrf.frame import LrfFrame
    from ..sim.lrf_family import draw_scenario, simulate_stops
    n = ok_d = ok_s = 0
    times, fails = [], []
    for k in range(seeds):
        sc, _fd = draw_scenario(seed0 + k)
        try:
            stops, _truth, _ = simulate_stops(sc, 1, np.random.default_rng(np.random.SeedSequence([11, seed0 + k])))
        except RuntimeError:
            continue
        cfg = FeatureConfig(board=BoardModel.from_config(sc.board))
        for st in stops:
            if min(st.visibility["camera"].values()) < min_face_px:
                continue
            n += 1
            fr = LrfFrame.from_sim(st.frames[0])
            t0 = time.perf_counter()
            try:
                extract_depth_features(fr, cfg)
                ok_d += 1
            except FeatureError as e:
                fails.append(f"seed {seed0 + k}: {e}")
            try:
                extract_scan_features(fr, cfg)
                ok_s += 1
            except FeatureError as e:
                fails.append(f"seed {seed0 + k}: {e}")
            times.append(time.perf_counter() - t0)
    out = {"frames": n, "depth_found": ok_d, "scan_found": ok_s,
           "depth_rate": ok_d / max(n, 1), "scan_rate": ok_s / max(n, 1),
           "ms_per_frame_median": 1000 * float(np.median(times)) if times else float("nan"),
           "ms_per_frame_p90": 1000 * float(np.percentile(times, 90)) if times else float("nan"),
           "failures": fails}
    print(f"single frames with every face >= {min_face_px} px: {n}; board found in depth {ok_d} "
          f"({100 * out['depth_rate']:.1f} %), in the scan {ok_s} ({100 * out['scan_rate']:.1f} %); "
          f"features {out['ms_per_frame_median']:.0f} ms/frame median, {out['ms_per_frame_p90']:.0f} p90")
    for f in fails[:20]:
        print("  " + f)
    return out


def _pct(v, q):
    v = [x for x in v if np.isfinite(x)]
    return float(np.percentile(v, q)) if v else float("nan")


def family_main(seeds: int, seed0: int, n_stops: int | None, frames: int | None, json_path: str | None) -> dict:
    rows = []
    print(f"{'seed':>5} {'stops':>5} {'acc':>4} {'F':>2} {'apex':>8} {'p_rot':>6} {'p_mm':>6} {'o_rot':>6} "
          f"{'o_mm':>6} {'crb_rot':>7} {'crb_mm':>6} {'maha2':>7} {'ms/fr':>6}  camera / laser")
    for k in range(seeds):
        s = seed0 + k
        try:
            r = run_family_seed(s, n_stops, frames)
        except RuntimeError as e:  # a scene the pose sampler could not build
            r = {"seed": s, "error": f"scene: {e}", "stops": 0, "accepted": 0}
        rows.append(r)
        if "ours" in r:
            p, o, c = r["paper"], r["ours"], r["crb"]
            print(f"{s:>5} {r['stops']:>5} {r['accepted']:>4} {r['frames_per_stop']:>2} {r['apex']:>8} "
                  f"{p['rot_deg']:6.3f} {p['trans_mm']:6.2f} {o['rot_deg']:6.3f} {o['trans_mm']:6.2f} "
                  f"{c['rot_deg']:7.3f} {c['trans_mm']:6.2f} {o['mahalanobis2']:7.2f} {r['ms_per_frame']:6.1f}  "
                  f"{r['camera']} / {r['laser']}", flush=True)
        else:
            print(f"{s:>5} {r.get('stops', 0):>5} {r.get('accepted', 0):>4}  {r.get('error', '')}", flush=True)
    ok = [r for r in rows if "ours" in r]
    agg = {"seeds": seeds, "with_result": len(ok),
           "stops_accepted_fraction": float(sum(r.get("accepted", 0) for r in rows)
                                            / max(1, sum(r.get("stops", 0) for r in rows)))}
    for key in ("paper", "ours", "crb"):
        for m in ("rot_deg", "trans_mm"):
            v = [r[key][m] for r in ok]
            agg[f"{key}_{m}_median"] = _pct(v, 50)
            agg[f"{key}_{m}_p90"] = _pct(v, 90)
    m2 = [r["ours"]["mahalanobis2"] for r in ok]
    agg["mahalanobis2_mean"] = float(np.mean(m2)) if m2 else float("nan")
    agg["mahalanobis2_median"] = _pct(m2, 50)
    agg["mahalanobis2_above_16.8_fraction"] = float(np.mean(np.array(m2) > 16.8)) if m2 else float("nan")
    agg["ms_per_frame_median"] = _pct([r["ms_per_frame"] for r in ok], 50)
    print("aggregate: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in agg.items()))
    if ok:
        pr, pt = agg["paper_rot_deg_median"], agg["paper_trans_mm_median"]
        orr, ot = agg["ours_rot_deg_median"], agg["ours_trans_mm_median"]
        print(f"ours vs paper (medians): {pr / max(orr, 1e-12):.2f}x rotation, {pt / max(ot, 1e-12):.2f}x translation; "
              f"ours vs CRB: {orr / max(agg['crb_rot_deg_median'], 1e-12):.2f}x rotation, "
              f"{ot / max(agg['crb_trans_mm_median'], 1e-12):.2f}x translation")
    out = {"method": "lrf", "family": True, "aggregate": agg, "rows": rows}
    if json_path:
        os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=1, default=float)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="lidar-cam-calib bench lrf", description=__doc__.splitlines()[0])
    ap.add_argument("--observations", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=1, help="seeds seed, seed+1, ... (mean reported)")
    ap.add_argument("--sweep", action="store_true", help="N in {2, 5, 10, 20}")
    ap.add_argument("--source", choices=("sim", "synthetic"), default="sim",
                    help="sim: simulator + real feature extraction (default); synthetic: analytic features")
    ap.add_argument("--scenario", default=None, help="scenario YAML (sim source; default: paper 003 sensors)")
    ap.add_argument("--json", default=None, help="write the run (one) or all runs (sweep/repeats) as JSON")
    ap.add_argument("--family", action="store_true",
                    help="scenes drawn from the seed (camera, board, laser, mount, stops, clocks): per-seed rows "
                         "and aggregate, paper vs ours vs the Cramer-Rao bound")
    ap.add_argument("--seeds", type=int, default=10, help="--family: number of scenes (seed, seed+1, ...)")
    ap.add_argument("--stops", type=int, default=None, help="--family: stops per scene (default: drawn, 6-20)")
    ap.add_argument("--frames", type=int, default=None, help="--family: frames per stop (default: drawn)")
    ap.add_argument("--detection", action="store_true",
                    help="--family: single-frame detection rate (frames whose faces show >= 2000 px)")
    a = ap.parse_args(argv)
    if a.family and a.detection:
        out = detection_rate(a.seeds, a.seed)
        if a.json:
            os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
            with open(a.json, "w") as fh:
                json.dump(out, fh, indent=1, default=float)
        return 0
    if a.family:
        family_main(a.seeds, a.seed, a.stops, a.frames, a.json)
        return 0
    Ns = [2, 5, 10, 20] if a.sweep else [a.observations]
    rows, runs = [], []
    for N in Ns:
        acc = {"paper": [], "ours": []}
        base = {"paper": [], "ours": []}
        used = []
        for k in range(a.repeats):
            r = run_bench(N, a.seed + k, a.scenario, a.source)
            runs.append(r)
            used.append(r.get("observations_used", N))
            for s in acc:
                if "solvers" in r:
                    v = r["solvers"][s]
                    acc[s].append([v["rotation_error_deg"], v["translation_error_mm"], v["point_to_line_mm"],
                                   v.get("ms_per_observation", 1000 * v["runtime_s"] / N)])
                if "stereo_baseline" in r:
                    base[s].append(r["stereo_baseline"][s]["baseline_error_mm"])
        for s, v in acc.items():
            if v:
                m = np.mean(v, axis=0)
                rows.append((N, s, len(v), float(np.mean(used)), *m,
                             float(np.mean(base[s])) if base[s] else float("nan")))
    print(f"{'N':>3} {'solver':>6} {'runs':>4} {'used':>5} {'rot_deg':>8} {'trans_mm':>9} {'p2l_mm':>7} "
          f"{'ms/obs':>7} {'stereo_baseline_err_mm':>22}")
    for N, s, k, u, er, et, pl, rt, be in rows:
        print(f"{N:>3} {s:>6} {k:>4} {u:5.1f} {er:8.3f} {et:9.2f} {pl:7.2f} {rt:7.1f} {be:22.2f}")
    by = {}
    for N, s, _k, _u, er, et, *_ in rows:
        by.setdefault(N, {})[s] = (er, et)
    for N, d in by.items():
        if "paper" in d and "ours" in d and d["ours"][0] > 0 and d["ours"][1] > 0:
            print(f"N={N}: ours is {d['paper'][0] / d['ours'][0]:.1f}x (rotation) and "
                  f"{d['paper'][1] / d['ours'][1]:.1f}x (translation) more accurate than paper")
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as fh:
            json.dump(runs[0] if len(runs) == 1 else {"runs": runs, "table": rows}, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
