"""`lidar-cam-calib` command line: calibrate (bag replay through the real node),
simulate (write a synthetic bag + truth), bench (accuracy / speed figures)."""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import yaml

from .core.geometry import inv_T, pose_errors, rpy_from_R


def load_truth(path: str) -> np.ndarray:
    """4x4 T_child_parent from a truth YAML (``T_camera_laser`` / ``T_child_parent``)."""
    with open(path, "r", encoding="utf-8") as f:
        d = yaml.safe_load(f)
    for key in ("T_camera_laser", "T_child_parent", "T_camera_lidar"):
        if isinstance(d, dict) and key in d:
            return np.array(d[key], dtype=float).reshape(4, 4)
    raise SystemExit(f"error: {path} has no T_camera_laser / T_child_parent matrix")


def _cmd_calibrate(a: argparse.Namespace) -> int:
    from .ros.replay import ReplayError, replay

    out = a.output or os.path.join("out", f"{a.method}_result.yaml")
    try:
        oc = replay(a.method, a.bag, params_file=a.params, output_path=out, overlay_path=a.overlay,
                    extra_params={"solver": a.solver} if a.solver else None, domain_id=a.domain_id)
    except ReplayError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    st = oc.status
    print(f"replayed {oc.messages_sent} messages in {oc.wall_time_s:.1f} s "
          f"({', '.join(f'{k}: {v}' for k, v in sorted(oc.messages_in_bag_topics.items()))})")
    if oc.result is None:
        print(f"error: no calibration: {st.get('observations', 0)} observation(s) accepted; "
              f"last reason: {st.get('last_reason') or 'none given'}", file=sys.stderr)
        if oc.bag_error:
            print(f"error: {oc.bag_error}", file=sys.stderr)
        return 3
    r = oc.result
    rs, ts = r.sigma()
    t = r.t
    rpy = np.degrees(rpy_from_R(r.R))
    print(f"T_{r.child_frame}_{r.parent_frame} (p_{r.child_frame} = T @ p_{r.parent_frame}), solver {r.solver}:")
    print("  " + np.array2string(r.T_child_parent, precision=5, suppress_small=True).replace("\n", "\n  "))
    print(f"  translation [m] {t[0]:+.4f} {t[1]:+.4f} {t[2]:+.4f}   rpy [deg] {rpy[0]:+.3f} {rpy[1]:+.3f} {rpy[2]:+.3f}")
    print(f"  1-sigma: {rs:.3f} deg, {ts:.2f} mm   observations: {r.observations_used}")
    m = r.metrics
    if "point_to_line_mm" in m:
        print(f"  eq. 12 point-to-line error {m['point_to_line_mm']:.2f} mm; laser points to camera planes RMS "
              f"{m.get('plane_rms_mm', float('nan')):.2f} mm")
    if "observability" in m:
        print(f"  observability: {m['observability']}"
              + (f" (weakest: {m['weakest_direction']})" if m.get("weakest_direction") else ""))
    if st.get("advice"):
        print(f"  advice: {st['advice']}")
    file_note = st.get("result_file", "")
    if file_note.startswith("result NOT saved"):
        print(f"error: {file_note}", file=sys.stderr)
    else:
        print(f"  result file: {file_note or out}" + (f"; overlay: {a.overlay}" if a.overlay else ""))
    if a.truth:
        T_true = load_truth(a.truth)
        er, et = pose_errors(r.T_child_parent, T_true)
        print(f"error vs truth: rotation {er:.3f} deg, translation {et:.2f} mm")
        tp = inv_T(T_true)[:3, 3]
        print(f"  truth tf {r.parent_frame}->{r.child_frame} translation [m] {tp[0]:+.4f} {tp[1]:+.4f} {tp[2]:+.4f}")
    if oc.bag_error:
        print(f"error: {oc.bag_error}", file=sys.stderr)
        return 4
    return 5 if file_note.startswith("result NOT saved") else 0


def _cmd_simulate(a: argparse.Namespace) -> int:
    from .sim.lrf_bag import write_lrf_bag
    from .sim.scenario import load_scenario

    sc = load_scenario(a.scenario) if a.scenario else load_scenario(_default_scenario_path(a.method))
    bag, truth = write_lrf_bag(sc, a.out, seed=a.seed, overwrite=a.overwrite)
    print(f"wrote {bag}\ntruth {truth}")
    return 0


def _default_scenario_path(method: str) -> str:
    here = os.path.dirname(os.path.abspath(__file__))
    for base in (os.path.join(here, "..", "config", "scenarios"),):
        p = os.path.join(base, f"{method}_default.yaml")
        if os.path.isfile(p):
            return p
    try:
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        return os.path.join(get_package_share_directory("lidar_cam_calib"), "config", "scenarios",
                            f"{method}_default.yaml")
    except Exception as e:  # noqa: BLE001
        raise SystemExit(f"error: no default scenario for {method}: {e}")


def _cmd_bench(a: argparse.Namespace, rest: list[str]) -> int:
    if a.what == "lrf":
        from .bench.lrf import main as bench_main

        return int(bench_main(rest) or 0)
    if a.what == "decode":
        from .io.bench_decode import main as bench_main

        return int(bench_main(rest) or 0)
    raise SystemExit(f"error: unknown benchmark {a.what!r}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lidar-cam-calib", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    c = sub.add_parser("calibrate", help="replay a bag through the method's node and print the extrinsic")
    c.add_argument("method", choices=["lrf"])
    c.add_argument("bag", help="rosbag2 MCAP bag directory or single .mcap file")
    c.add_argument("--params", help="node parameter file (config/<node>.yaml)")
    c.add_argument("--output", help="result YAML path (default out/<method>_result.yaml)")
    c.add_argument("--overlay", help="write the overlay PNG here")
    c.add_argument("--truth", help="ground-truth YAML: print the error against it")
    c.add_argument("--solver", choices=["ours", "paper"], help="solver for the published result (default ours)")
    c.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for the replay (default: from the pid)")

    s = sub.add_parser("simulate", help="write a synthetic bag and its ground truth")
    s.add_argument("method", choices=["lrf"])
    s.add_argument("--scenario", help="scenario YAML (default config/scenarios/<method>_default.yaml)")
    s.add_argument("--out", required=True, help="output folder: the bag is written to OUT/<scenario name>/")
    s.add_argument("--seed", type=int)
    s.add_argument("--overwrite", action="store_true", help="replace an existing bag of the same name")

    b = sub.add_parser("bench", help="benchmarks: lrf (paper vs ours), decode (message conversion)")
    b.add_argument("what", choices=["lrf", "decode"])

    a, rest = p.parse_known_args(argv)
    if a.cmd == "bench":
        return _cmd_bench(a, rest)
    if rest:
        p.error(f"unrecognized arguments: {' '.join(rest)}")
    if a.cmd == "calibrate":
        return _cmd_calibrate(a)
    return _cmd_simulate(a)


if __name__ == "__main__":
    sys.exit(main())
