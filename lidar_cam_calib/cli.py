"""`lidar-cam-calib`: calibrate (a bag replayed through the method's real
node), simulate (a synthetic bag and its truth), bench (accuracy and speed
figures). Every method comes from the registry (lidar_cam_calib.methods)."""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import yaml

from . import methods
from .core.calibrator import collected_count
from .core.geometry import inv_T, pose_errors, rpy_from_R

EXIT_CODES = """exit codes:
  0  a calibration is in effect and was printed (also when the file on disk
     held a better one, which is kept and printed)
  1  internal error (a bug: please report it with the output)
  2  bad usage or input: bag or params file missing, a bad parameter value,
     bag topics of the wrong type, the node did not start
  3  no calibration: too few observations were accepted (the reasons are printed)
  4  the bag is truncated or damaged: what could be read was replayed, and the
     result of that part is printed and saved
  5  the result was not saved or not adopted: the output file cannot be
     written, or holds another method's or another frame pair's calibration
"""


def load_truth(path: str) -> dict:
    """Truth YAML -> {name: 4x4 T_child_parent}; '' for a single camera
    (``T_camera_laser`` / ``T_camera_lidar`` / ``T_child_parent``), or one per
    camera under ``cameras: {name: {T_camera_lidar: ...}}``."""
    with open(path, "r", encoding="utf-8") as f:
        d = yaml.safe_load(f)
    if not isinstance(d, dict):
        raise SystemExit(f"error: {path} is not a truth YAML")
    for key in ("T_camera_laser", "T_child_parent", "T_camera_lidar"):
        if key in d:
            return {"": np.array(d[key], dtype=float).reshape(4, 4)}
    if isinstance(d.get("cameras"), dict):
        return {k: np.array(v["T_camera_lidar"], dtype=float).reshape(4, 4) for k, v in d["cameras"].items()}
    raise SystemExit(f"error: {path} has no T_camera_laser / T_camera_lidar / cameras matrix")


def _print_result(name: str, r, spec, truth: dict | None) -> None:
    head = f"[{name}] " if name else ""
    rs, ts = r.sigma()
    t = r.t
    rpy = np.degrees(rpy_from_R(r.R))
    print(f"{head}T_{r.child_frame}_{r.parent_frame} (p_{r.child_frame} = T @ p_{r.parent_frame}), solver {r.solver}:")
    print("  " + np.array2string(r.T_child_parent, precision=5, suppress_small=True).replace("\n", "\n  "))
    print(f"  translation [m] {t[0]:+.4f} {t[1]:+.4f} {t[2]:+.4f}   "
          f"rpy [deg] {rpy[0]:+.3f} {rpy[1]:+.3f} {rpy[2]:+.3f}")
    print(f"  1-sigma: {rs:.3f} deg, {ts:.2f} mm   observations: {r.observations_used}")
    m = r.metrics
    for key, label, unit in spec.metrics:
        if isinstance(m.get(key), (int, float)):
            print(f"  {label}: {m[key]:.2f} {unit}")
    if m.get("observability"):
        print(f"  observability: {m['observability']}"
              + (f" (weakest: {m['weakest_direction']})" if m.get("weakest_direction") else ""))
    if truth and name in truth:
        er, et = pose_errors(r.T_child_parent, truth[name])
        print(f"{head}error vs truth: rotation {er:.3f} deg, translation {et:.2f} mm")
        tp = inv_T(truth[name])[:3, 3]
        print(f"  truth tf {r.parent_frame}->{r.child_frame} translation [m] {tp[0]:+.4f} {tp[1]:+.4f} {tp[2]:+.4f}")


def _cmd_calibrate(a: argparse.Namespace) -> int:
    from .ros.replay import ReplayError, replay

    spec = methods.get(a.method)
    out = a.output or os.path.join("out", f"{a.method}_result.yaml")
    extra = {"solver": a.solver} if a.solver else {}
    if a.force:
        extra["force_overwrite"] = True
    try:
        oc = replay(a.method, a.bag, params_file=a.params, output_path=out, overlay_path=a.overlay,
                    extra_params=extra, domain_id=a.domain_id, progress=None if not a.quiet else False)
    except ReplayError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    st = oc.status
    print(f"replayed {oc.messages_sent} messages in {oc.wall_time_s:.1f} s "
          f"({', '.join(f'{k}: {v}' for k, v in sorted(oc.messages_in_bag_topics.items()))})")
    truth = load_truth(a.truth) if a.truth else None
    cand = st.get("candidate")
    code = 0
    if oc.result is None:
        n = collected_count(st)
        print(f"error: no calibration: {n} observation(s) accepted; last reason: "
              f"{st.get('last_reason') or 'none given'}", file=sys.stderr)
        if st.get("last_fit_failure"):
            print(f"  last {st['last_fit_failure']}", file=sys.stderr)
        code = 3
    else:
        eff = st.get("in_effect") or {}
        if eff.get("source") == "file":
            print(f"calibration in effect (from {out}, an earlier run):")
        for name, r in oc.result.results.items():
            _print_result(name, r, spec, truth)
        for name, why in (oc.result.refused or {}).items():
            print(f"[{name}] not calibrated: {why}")
        extras = oc.result.extras.get("camera_to_camera") if oc.result.extras else None
        if extras:
            print("camera-to-camera: " + ", ".join(sorted(extras)))
        if st.get("advice"):
            print(f"  advice: {st['advice']}")
        overlays = ""
        if a.overlay:
            # the node writes one PNG per named camera: OVERLAY with _<camera> before the extension
            stem, ext = os.path.splitext(a.overlay)
            names = [n for n in oc.result.results if n]
            overlays = "; overlay: " + ", ".join([f"{stem}_{n}{ext or '.png'}" for n in names] or [a.overlay])
        print(f"  result file: {st.get('result_file') or out}{overlays}")
    if cand:
        print(f"error: the new calibration was not adopted: {cand['reason']} "
              f"(candidate sigma {cand.get('sigma')}, observations {cand.get('observations')})", file=sys.stderr)
        reason = cand["reason"]
        if "holds a better" not in reason:
            code = max(code, 5)
    if str(st.get("result_file", "")).startswith("result NOT saved"):
        print(f"error: {st['result_file']}", file=sys.stderr)
        code = max(code, 5)
    if oc.bag_error:
        print(f"error: {oc.bag_error} (replayed the {oc.messages_sent} messages before it)", file=sys.stderr)
        code = 4 if code in (0, 5) else code
    return code


def _cmd_simulate(a: argparse.Namespace) -> int:
    spec = methods.get(a.method)
    load_scenario = methods.load(spec.load_scenario)
    sc = load_scenario(a.scenario or _config_path("scenarios", spec.scenario))
    bag, truth = methods.load(spec.simulate)(sc, a.out, seed=a.seed, overwrite=a.overwrite)
    print(f"wrote {bag}\ntruth {truth}")
    return 0


def _cmd_kitti2bag(a: argparse.Namespace) -> int:
    from .io.bag import BagError
    from .io.kitti import kitti_to_bag

    try:
        bag, truth = kitti_to_bag(a.kitti_dir, a.out, overwrite=a.overwrite, max_frames=a.max_frames)
    except (BagError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {bag}\ntruth {truth}")
    return 0


def _cmd_lcct2bag(a: argparse.Namespace) -> int:
    from .io.bag import BagError
    from .io.lcct import write_lcct_bag

    try:
        bag, truth = write_lcct_bag(a.folder, a.out, overwrite=a.overwrite,
                                    encoding="mono8" if a.mono else "bgr8")
    except (BagError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {bag}\ntruth {truth} (the toolbox's own result, not an independent truth)")
    return 0


def _config_path(*parts: str) -> str:
    here = os.path.dirname(os.path.abspath(__file__))
    p = os.path.join(here, "..", "config", *parts)
    if os.path.isfile(p):
        return p
    try:
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        return os.path.join(get_package_share_directory("lidar_cam_calib"), "config", *parts)
    except Exception:  # noqa: BLE001 - not installed with colcon
        raise SystemExit(f"error: {os.path.join('config', *parts)} not found") from None


def _benches() -> dict:
    out = {name: (spec.bench, spec.summary) for name, spec in methods.METHODS.items()}
    out.update(methods.EXTRA_BENCHES)
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lidar-cam-calib", description=__doc__, epilog=EXIT_CODES,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True, metavar="{calibrate,simulate,kitti2bag,lcct2bag,bench}")
    names = list(methods.METHODS)
    listing = "\n".join(f"  {n:<11} {s.summary}" for n, s in methods.METHODS.items())

    c = sub.add_parser("calibrate", help="replay a bag through the method's node and print the extrinsic",
                       description="Replay BAG through the method's real node (its own process, DDS on loopback, "
                                   "lock-step) and print the calibration in effect.\nmethods:\n" + listing,
                       epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("method", choices=names)
    c.add_argument("bag", help="rosbag2 MCAP bag directory or single .mcap file")
    c.add_argument("--params", help="node parameter file (config/<node>.yaml)")
    c.add_argument("--output", help="result YAML path (default out/<method>_result.yaml)")
    c.add_argument("--overlay", help="write the overlay PNG here")
    c.add_argument("--truth", help="ground-truth YAML: print the error against it")
    c.add_argument("--solver", choices=["ours", "paper"], help="solver for the published result (default ours)")
    c.add_argument("--force", action="store_true", help="replace the output file whatever it holds")
    c.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: the environment's, else 0); the replay "
                   "is private to its node on any domain")
    c.add_argument("--quiet", action="store_true", help="no progress line (it is shown only on a terminal anyway)")

    s = sub.add_parser("simulate", help="write a synthetic bag and its ground truth",
                       description="Write a synthetic bag and its truth YAML.\nmethods:\n" + listing,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("method", choices=names)
    s.add_argument("--scenario", help="scenario YAML (default config/scenarios/<method>_default.yaml)")
    s.add_argument("--out", required=True, help="output folder: the bag is written to OUT/<scenario name>/")
    s.add_argument("--seed", type=int)
    s.add_argument("--overwrite", action="store_true", help="replace an existing bag of the same name")

    k = sub.add_parser("kitti2bag", help="turn a KITTI raw drive into an MCAP bag and a truth YAML",
                       description="A KITTI raw folder (image_02/data, velodyne_points/data, calib files) -> "
                                   "OUT/<name>/ with PointCloud2, Image, CameraInfo (P_rect_02) at 10 Hz and "
                                   "truth.yaml with T_camera_lidar to the rectified cam2.")
    k.add_argument("kitti_dir")
    k.add_argument("out")
    k.add_argument("--max-frames", type=int)
    k.add_argument("--overwrite", action="store_true")

    lc = sub.add_parser("lcct2bag", help="turn the CMU LCCT checkerboard + 3D laser sample into an MCAP bag",
                        description="The lcct_checkerboard_3dlaser folder (15 poses, .xyz scans, images, Bouguet "
                                    "calibration) -> OUT/lcct_checkerboard_3dlaser/ with PointCloud2 (x, y, z), "
                                    "Image and CameraInfo, each pose held for 3 sweeps, and truth.yaml with the "
                                    "toolbox's own result. Calibrate it with --params config/board_lcct.yaml.")
    lc.add_argument("folder")
    lc.add_argument("out")
    lc.add_argument("--mono", action="store_true", help="mono8 images instead of bgr8")
    lc.add_argument("--overwrite", action="store_true")

    benches = _benches()
    b = sub.add_parser("bench", add_help=False, help="benchmarks: " + ", ".join(benches),
                       description="Run a benchmark; `lidar-cam-calib bench NAME --help` shows its options.\n"
                                   + "\n".join(f"  {n:<11} {d}" for n, (_, d) in benches.items()),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    b.add_argument("what", nargs="?", choices=list(benches))
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = build_parser()
    if argv and argv[0] == "bench":
        # everything after the benchmark's name is the benchmark's own, --help included
        benches = _benches()
        if len(argv) < 2 or argv[1].startswith("-"):
            bench_parser = p._subparsers._group_actions[0].choices["bench"] # argparse has no API for it
            bench_parser.print_help()
            return 0 if any(x in ("-h", "--help") for x in argv[1:]) else 2
        if argv[1] not in benches:
            p.error(f"unknown benchmark {argv[1]!r}; choose from {', '.join(benches)}")
        return int(methods.load(benches[argv[1]][0])(argv[2:]) or 0)
    a = p.parse_args(argv)
    try:
        if a.cmd == "calibrate":
            return _cmd_calibrate(a)
        if a.cmd == "kitti2bag":
            return _cmd_kitti2bag(a)
        if a.cmd == "lcct2bag":
            return _cmd_lcct2bag(a)
        return _cmd_simulate(a)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
