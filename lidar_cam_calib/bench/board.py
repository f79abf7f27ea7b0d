"""Benchmark of the board method: epnp, kabsch_3d3d, paper and ours on identical simulated data.

``lidar-cam-calib bench board --poses N --seed S [--lidar rs16|vlp16|vlp32|hdl64|os1]
[--family --seeds K [--first-seed S]] [--json FILE] [--plot FILE] [--half]``

One run: the simulator (:mod:`lidar_cam_calib.sim.board_world`) draws a session, its still
frames go through the real extraction (:class:`~lidar_cam_calib.board.calibrator.BoardCalibrator`),
and every solver runs on the same placements. Per camera: rotation / translation error against
the truth, eq. 24-25 normalised-plane error, reprojection, and the Mahalanobis^2 of the error
against ours' covariance; per solver the worst camera and the runtime; beside them the scene's
Cramer-Rao bound (information at the true poses with the simulator's noise). ``--family`` draws
``--seeds`` scenarios (LiDAR, cameras, board, noise, room) from consecutive seeds and reports
medians, 90th percentiles, detection rate and covariance consistency. ``--plot`` writes the
error against the number of poses (paper Fig. 11), ours against paper, drawn with cv2.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from ..board.calibrator import BoardCalibrator, BoardConfig
from ..board.frame import BoardFrame, CameraImage
from ..board.lidar_board import BoardNotFound, LidarBoard
from ..board.solvers import (Observation, OursOptions, SolveError, camera_metrics, resolve_symmetry, solve_epnp,
                             solve_kabsch, solve_ours, solve_paper)
from ..core.errors import CalibError
from ..core.geometry import pose_errors, so3_log

SOLVER_NAMES = ("epnp", "kabsch_3d3d", "paper", "ours")


def frame_from_sim(f, run) -> BoardFrame:
    """A simulator frame as the node would build it."""
    images = {}
    for name, (stamp, img) in f.images.items():
        cam = run.cameras[name]
        images[name] = CameraImage(float(stamp), img, cam.model, cam.frame_id)
    return BoardFrame.from_cloud(float(f.stamp_s), f.cloud, run.lidar_frame, images)


def _rings_on_true_board(f, board) -> int:
    c = f.cloud
    if "ring" not in c:
        return -1
    P = np.column_stack([c["x"], c["y"], c["z"]]).astype(float)
    T = f.T_lidar_board
    loc = (P - T[:3, 3]) @ T[:3, :3]
    a, b = board.size_m[0] / 2, board.size_m[1] / 2
    on = (np.abs(loc[:, 2]) < 0.05) & (np.abs(loc[:, 0]) < a) & (np.abs(loc[:, 1]) < b)
    return int(len(np.unique(np.asarray(c["ring"])[on])))


def _maha2(T_est, T_true, cov) -> float:
    d = np.concatenate([so3_log(T_est[:3, :3] @ T_true[:3, :3].T), T_est[:3, 3] - T_true[:3, 3]])
    try:
        return float(d @ np.linalg.solve(cov, d))
    except np.linalg.LinAlgError:
        return math.nan


def _crb(obs, board, models, truth, true_poses, noise_px: dict, range_sigma_m: float, edge_sigma_m: float) -> dict:
    """Cramer-Rao bound per camera: our information matrix at the true extrinsics and board poses
    with the given noise (no fitting, no variance re-estimation)."""
    Rz = np.diag([-1.0, -1.0, 1.0, 1.0])
    obs_t = []
    for o in obs:
        Tt = true_poses[o.stamp_s]
        T = Tt if pose_errors(o.lidar.T_lidar_board, Tt)[0] < pose_errors(o.lidar.T_lidar_board, Tt @ Rz)[0] \
            else Tt @ Rz
        lb = LidarBoard(T, o.lidar.points, o.lidar.edge_points, o.lidar.edge_step_m, o.lidar.edge_dir,
                        o.lidar.edge_range_m, o.lidar.rings_on_board, 0.0, 0.0, o.lidar.shrink_m, o.lidar.mode)
        obs_t.append(Observation(o.stamp_s, lb, o.images))
    cams = [c for c in truth if any(c in o.images for o in obs_t)]
    if not cams:
        return {}
    opt = OursOptions(pixel_sigma_px=1.0, range_sigma_m=range_sigma_m, edge_sigma_m=edge_sigma_m,
                      variance_rounds=0, max_iter=0, fixed_pixel_sigma=noise_px, robust_covariance=False,
                      placement_offset_sigma=None)
    sol = solve_ours(obs_t, board, {c: models[c] for c in cams}, {c: truth[c] for c in cams}, opt)
    out = {}
    for c in cams:
        cov = sol.covariance[c]
        out[c] = {"rotation_deg": float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))),
                  "translation_mm": float(1000 * np.sqrt(np.trace(cov[3:, 3:])))}
    return out


def run_once(seed: int, poses: int | None, lidar: str | None, family: bool, full_size: bool = True,
             curve: list | None = None, verbose: bool = True) -> dict:
    """One simulated session through every solver; the JSON dict of one run."""
    from ..sim.board_world import default_board_scenario, sample_board_family, simulate_board
    if family:
        sc = sample_board_family(seed, poses=poses, lidar=lidar)
    else:
        sc = default_board_scenario()
        sc.seed = int(seed)
        if poses is not None:
            sc.poses.n_poses = int(poses)
        if lidar is not None:
            sc.lidar.preset = lidar
    t0 = time.time()
    run = simulate_board(sc, np.random.default_rng(seed), full_size=full_size)
    t_sim = time.time() - t0
    b = run.board
    cfg = BoardConfig(camera_names=list(run.cameras), board_size_m=list(b.size_m), board_squares=list(b.squares),
                      board_square_m=float(b.square_m))
    cal = BoardCalibrator(cfg)
    eligible = found = 0
    t_lidar = t_img = c_lidar = 0.0
    true_poses = {}  # placement stamp -> true T_lidar_board
    reasons = []
    for f in run.frames:
        if not f.still:
            continue
        fr = frame_from_sim(f, run)
        in_view = any(f.board_in_view.values())
        nr = _rings_on_true_board(f, b)
        elig = in_view and (nr < 0 or nr >= 5)
        eligible += int(elig)
        t1, c1 = time.time(), time.process_time()
        try:
            lb = cal.detect_lidar(fr)
            ok = True
        except BoardNotFound as e:
            lb, ok = None, False
            reasons.append(str(e)[:200])
        t_lidar += time.time() - t1
        c_lidar += time.process_time() - c1
        found += int(ok and elig)
        if lb is None:
            continue
        t1 = time.time()
        n_before = len(cal.observations)
        cal.add(fr, lidar_board=lb)
        t_img += time.time() - t1
        if len(cal.observations) > n_before:
            true_poses[float(fr.stamp_s)] = f.T_lidar_board
    out = {"method": "board", "seed": int(seed), "poses": int(sc.poses.n_poses), "lidar": sc.lidar.preset,
           "family": bool(family), "cameras": list(run.cameras), "placements": len(cal.observations),
           "detection": {"eligible_still_frames": eligible, "found": found,
                         "rate": found / eligible if eligible else math.nan},
           "timing_s": {"simulate": t_sim, "lidar_extraction": t_lidar, "image_corners_and_add": t_img},
           "solvers": {}}
    if len(cal.observations) < 2:
        out["error"] = "fewer than 2 placements: " + "; ".join(reasons[:3])
        return out
    obs, _init, refused = resolve_symmetry(cal.observations, cal.board)
    out["refused_by_symmetry"] = refused
    models = cal.cameras
    t1 = time.time()
    ep = solve_epnp(obs, cal.board)
    t_ep = time.time() - t1
    res = {"epnp": (ep, None, t_ep)}
    t1 = time.time()
    res["kabsch_3d3d"] = (solve_kabsch(obs, cal.board), None, time.time() - t1)
    t1 = time.time()
    pT, pP = solve_paper(obs, cal.board, ep)
    res["paper"] = (pT, pP, time.time() - t1 + t_ep)
    t1, c1 = time.time(), time.process_time()
    try:
        sol = solve_ours(obs, cal.board, models, ep, OursOptions())
        c_ours = time.process_time() - c1
    except SolveError as e:
        out["error"] = str(e)
        return out
    Pb = cal.board.inner_corners_board()
    res["ours"] = (sol.T, {i: Pb @ P[:3, :3].T + P[:3, 3] for i, P in enumerate(sol.board_poses)},
                   time.time() - t1 + t_ep)
    for name, (Ts, pts, rt) in res.items():
        cams = {}
        for c, T in Ts.items():
            rot, tr = pose_errors(T, run.truth[c])
            m = camera_metrics(obs, c, T, models[c], cal.board, pts)
            mv = camera_metrics(obs, c, T, models[c], cal.board)
            cams[c] = {"rotation_error_deg": rot, "translation_error_mm": tr,
                       "normalized_plane_error_mm": m["normalized_plane_error_mm"],
                       "normalized_plane_error_virtual_mm": mv["normalized_plane_error_mm"],
                       "reprojection_px": m["reprojection_px"], "frames": m["frames"],
                       "mahalanobis2": _maha2(T, run.truth[c], sol.covariance[c]) if c in sol.covariance else math.nan}
            if name == "ours":
                cov = sol.covariance[c]
                cams[c]["sigma_rotation_deg"] = float(np.degrees(np.sqrt(np.diag(cov)[:3]).max()))
                cams[c]["sigma_translation_mm"] = float(1000 * np.sqrt(np.diag(cov)[3:]).max())
        worst_r = max((v["rotation_error_deg"] for v in cams.values()), default=math.nan)
        worst_t = max((v["translation_error_mm"] for v in cams.values()), default=math.nan)
        out["solvers"][name] = {"cameras": cams, "rotation_error_deg": worst_r, "translation_error_mm": worst_t,
                                "runtime_s": rt}
    out["solvers"]["ours"]["noise_estimated"] = sol.noise
    out["whole_fit_s"] = t_lidar + out["solvers"]["ours"]["runtime_s"]
    # CPU seconds of the same (all threads): less sensitive to other load on the machine than wall time
    out["whole_fit_cpu_s"] = c_lidar + c_ours + t_ep
    # scene limit
    try:
        px = {c: sol.noise["pixel_sigma_px"][c] for c in sol.cams}
        out["cramer_rao"] = _crb(obs, cal.board, models, run.truth, true_poses, px,
                                 float(run.noise.get("range_sigma_m", 0.02)), sol.noise["edge_sigma_m"])
        out["cramer_rao_note"] = ("information at the true poses; range noise from the simulator, pixel and "
                                  "edge noise as estimated (the simulator's noise is in image DN)")
    except CalibError as e:
        out["cramer_rao"] = {"error": str(e)}
    if curve:
        out["curve"] = _curve(obs, cal.board, models, run.truth, curve)
    if verbose:
        print(_summary(out), flush=True)
    return out


def _curve(obs, board, models, truth, counts) -> dict:
    """Worst-camera error against the number of poses for paper and ours."""
    rows = {"poses": [], "paper_mm": [], "ours_mm": [], "paper_deg": [], "ours_deg": []}
    for n in counts:
        if n > len(obs):
            break
        sub = obs[:n]
        try:
            ep = solve_epnp(sub, board)
            pT, _ = solve_paper(sub, board, ep)
            sol = solve_ours(sub, board, models, ep)
        except (CalibError, np.linalg.LinAlgError):
            continue
        rows["poses"].append(n)
        for key, Ts in (("paper", pT), ("ours", sol.T)):
            e = [pose_errors(Ts[c], truth[c]) for c in Ts]
            rows[f"{key}_mm"].append(max(x[1] for x in e))
            rows[f"{key}_deg"].append(max(x[0] for x in e))
    return rows


def plot_curve(rows: dict, path: str, title: str = "board: worst-camera error vs poses") -> None:
    """PNG of the error against the number of poses (two panels: mm and deg), cv2 only."""
    import cv2
    W, H = 900, 420
    img = np.full((H, W, 3), 255, np.uint8)
    cv2.putText(img, title, (10, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    n = rows.get("poses", [])
    if not n:
        cv2.imwrite(path, img)
        return
    for unit, x0 in (("mm", 60), ("deg", 510)):
        w, h, y0 = 360, 300, 60
        vals = rows[f"paper_{unit}"] + rows[f"ours_{unit}"]
        top = max(max(vals), 1e-9) * 1.1
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), (0, 0, 0), 1)
        cv2.putText(img, f"worst-camera error ({unit})", (x0, y0 - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0),
                    1, cv2.LINE_AA)
        for k in range(5):
            yv = top * k / 4
            yy = int(y0 + h - h * k / 4)
            cv2.line(img, (x0 - 4, yy), (x0, yy), (0, 0, 0), 1)
            cv2.putText(img, f"{yv:.3g}", (x0 - 50, yy + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        nmax = max(n)

        def px(i, v, x0=x0, w=w, nmax=nmax, y0=y0, h=h, top=top):
            return (int(x0 + w * i / nmax), int(y0 + h - h * v / top))
        for i in n:
            cv2.putText(img, str(i), (px(i, 0)[0] - 6, y0 + h + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        for key, col in (("paper", (0, 0, 220)), ("ours", (200, 90, 0))):
            pts = [px(i, v) for i, v in zip(n, rows[f"{key}_{unit}"])]
            for a, b in zip(pts, pts[1:]):
                cv2.line(img, a, b, col, 2, cv2.LINE_AA)
            for q in pts:
                cv2.circle(img, q, 3, col, -1)
        cv2.putText(img, "paper", (x0 + w - 90, y0 + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 220), 1)
        cv2.putText(img, "ours", (x0 + w - 90, y0 + 36), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 90, 0), 1)
        cv2.putText(img, "poses", (x0 + w // 2 - 20, y0 + h + 32), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.imwrite(path, img)


def _summary(out: dict) -> str:
    lines = [f"board bench seed {out['seed']} lidar {out['lidar']} poses {out['poses']} placements "
             f"{out['placements']} cameras {out['cameras']} detection {out['detection']['found']}/"
             f"{out['detection']['eligible_still_frames']}"]
    for name, s in out.get("solvers", {}).items():
        cams = " ".join(f"{c}: {v['rotation_error_deg']:.4f} deg {v['translation_error_mm']:.2f} mm "
                        f"m2 {v['mahalanobis2']:.1f}" for c, v in s["cameras"].items())
        lines.append(f"  {name:12s} worst {s['rotation_error_deg']:.4f} deg {s['translation_error_mm']:.2f} mm "
                     f"({s['runtime_s']:.2f} s)  {cams}")
    if "cramer_rao" in out:
        lines.append(f"  CRB {out['cramer_rao']}")
    if "whole_fit_s" in out:
        lines.append(f"  whole fit (LiDAR extraction + ours) {out['whole_fit_s']:.2f} s wall, "
                     f"{out.get('whole_fit_cpu_s', math.nan):.2f} s CPU")
    return "\n".join(lines)


def _solver_family(runs: list, name: str) -> dict:
    """Aggregate of one solver over the family's runs."""
    wr, wt, m2 = [], [], []
    for r in runs:
        s = r.get("solvers", {}).get(name)
        if not s:
            continue
        wr.append(s["rotation_error_deg"])
        wt.append(s["translation_error_mm"])
        m2 += [v["mahalanobis2"] for v in s["cameras"].values() if math.isfinite(v["mahalanobis2"])]
    f = {"fitted": len(wr)}
    if wr:
        f.update(median_worst_rotation_deg=float(np.median(wr)), p90_worst_rotation_deg=float(np.percentile(wr, 90)),
                 median_worst_translation_mm=float(np.median(wt)),
                 p90_worst_translation_mm=float(np.percentile(wt, 90)))
    if m2:
        f.update(mahalanobis2_mean=float(np.mean(m2)), mahalanobis2_median=float(np.median(m2)),
                 mahalanobis2_above_16_8=float(np.mean(np.array(m2) > 16.8)), mahalanobis2_n=len(m2))
    return f


def _family_summary(runs: list) -> dict:
    """Family aggregate: detection rate, and per solver the median / 90th percentile of the
    worst-camera error and the Mahalanobis^2 statistics (every solver's error is measured
    against ours' covariance: the other solvers report none)."""
    det_e = sum(r["detection"]["eligible_still_frames"] for r in runs)
    det_f = sum(r["detection"]["found"] for r in runs)
    f = {"runs": len(runs), "seeds": [r["seed"] for r in runs],
         "detection_rate": det_f / det_e if det_e else math.nan}
    ours = _solver_family(runs, "ours")
    f["fitted"] = ours.pop("fitted")
    f.update(ours)  # ours at the top level
    f["solvers"] = {name: _solver_family(runs, name) for name in SOLVER_NAMES}
    for name in SOLVER_NAMES:
        if "median_worst_translation_mm" in f["solvers"][name]:
            f[f"{name}_median_worst_translation_mm"] = f["solvers"][name]["median_worst_translation_mm"]
    return f


def _family_table(runs: list) -> str:
    """One row per seed: worst-camera error and the largest Mahalanobis^2, ours and paper."""
    lines = ["seed  lidar  plc | ours deg   mm    max m2 | paper deg  mm    max m2"]
    for r in runs:
        row = f"{r['seed']:4d}  {r.get('lidar', '?'):6s} {r.get('placements', 0):3d} |"
        for name in ("ours", "paper"):
            s = r.get("solvers", {}).get(name)
            if not s:
                row += "      (no fit)         |"
                continue
            m2 = [v["mahalanobis2"] for v in s["cameras"].values() if math.isfinite(v["mahalanobis2"])]
            row += (f" {s['rotation_error_deg']:.4f} {s['translation_error_mm']:5.2f} "
                    f"{max(m2) if m2 else math.nan:7.1f} |")
        lines.append(row)
    return "\n".join(lines)


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lidar-cam-calib bench board", description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=None, help="board poses per session (default: scenario's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lidar", choices=("rs16", "vlp16", "vlp32", "hdl64", "os1"), default=None)
    ap.add_argument("--family", action="store_true", help="draw scenarios from the family")
    ap.add_argument("--seeds", type=int, default=1, help="with --family: number of consecutive seeds")
    ap.add_argument("--first-seed", type=int, default=None,
                    help="with --family: the first of the consecutive seeds (default: --seed)")
    ap.add_argument("--json", default=None, help="write the result JSON here")
    ap.add_argument("--plot", default=None, help="write the error-vs-poses PNG here (ours vs paper)")
    ap.add_argument("--half", action="store_true", help="render images at half size (faster)")
    a = ap.parse_args(argv)
    curve = None
    if a.plot:
        n = a.poses or 20
        curve = sorted({k for k in (3, 5, 8, 10, 15, 20, 30, 40, 60, n) if k <= n})
    runs = []
    first = a.seed if a.first_seed is None else a.first_seed
    seeds = [first + k for k in range(a.seeds)] if a.family else [first]
    for s in seeds:
        runs.append(run_once(s, a.poses, a.lidar, a.family, full_size=not a.half, curve=curve))
    out = runs[0] if len(runs) == 1 else {"method": "board", "seed": first, "poses": a.poses, "family": True,
                                          "runs": runs, "summary": _family_summary(runs)}
    if len(runs) > 1:
        print(_family_table(runs))
        print(json.dumps(out["summary"], indent=1))
    if a.plot and runs[0].get("curve"):
        plot_curve(runs[0]["curve"], a.plot)
        print(f"wrote {a.plot}")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1, default=float)
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
