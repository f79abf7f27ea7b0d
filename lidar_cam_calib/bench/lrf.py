"""Benchmark of the lrf solvers: paper (eq. 11) vs ours, same data, one run.

Two data sources:
* ``synthetic_observations`` -- analytic features straight from ground truth
  (ray-cast laser points with range noise, camera planes fitted to noisy
  depth samples with sigma = k z^2); no images, used by the solver tests.
* the simulator (lidar_cam_calib.sim) -- full frames through the real
  feature extraction (``run_bench``).

``main(argv)``: ``--observations N --seed S --repeats K --json FILE --sweep``.
"""
from __future__ import annotations

import argparse
import os
import json
import math
import sys
import time

import numpy as np

from ..core.geometry import R_BODY_OPTICAL, R_from_rpy, inv_T, make_T, pose_errors
from ..lrf.features import (BoardModel, FeatureConfig, corner_covariance, make_observation)
from ..core.fitting import fit_line_2d_lsq, fit_plane_lsq, intersect_lines_2d
from ..lrf.solvers import (LrfObservation, OursOptions, PlaneStats, point_to_line_error_m,
                      reject_outlier_observations, resolve_assignment, solve_ours, solve_paper)


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
    from ..sim.lrf_world import simulate
    from ..sim.scenario import load_scenario
    from ..lrf.features import FeatureError, extract_depth_features, extract_scan_features
    from ..lrf.frame import LrfFrame
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
    a = ap.parse_args(argv)
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
    for N, s, k, u, er, et, *_ in rows:
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
