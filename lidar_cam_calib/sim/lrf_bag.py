"""Write a simulated ``lrf`` session (2D laser + stereo depth camera on an AGV) as an MCAP bag.

``write_lrf_bag(scenario, out_dir)`` creates ``<out_dir>/<scenario.name>/`` (a rosbag2 MCAP bag
directory) with its ground truth inside it as ``<out_dir>/<scenario.name>/truth.yaml``
(rosbag2 readers ignore files that metadata.yaml does not list).

Topics (log time == header stamp, per-topic stamps strictly increasing):

* ``/scan``                             sensor_msgs/msg/LaserScan, frame ``laser``, ``scan_hz``
* ``/camera/depth/image_raw``           sensor_msgs/msg/Image 16UC1 (mm, 0 = invalid),
                                        frame ``camera_depth_optical_frame``, ``depth_hz``
* ``/camera/depth/camera_info``         sensor_msgs/msg/CameraInfo (same stamps)
* ``/camera/color/image_raw``           bgr8, same frame/stamps (if ``timeline.write_color``)
* ``/camera/color/camera_info``
* ``/camera_right/depth/image_raw``     16UC1, frame ``camera_right_depth_optical_frame``
* ``/camera_right/depth/camera_info``   (if the right camera is enabled and ``write_right``)

Timeline: at each observation pose the AGV stands still for ``static_s`` (every frame freshly
noised), then drives for ``drive_s`` to the next pose (smooth-step interpolation of the AGV pose
and, when re-placed, of the board pose) while the sensors keep publishing. Depth frames are
stamped ``depth_offset_s`` after a scan slot so the two streams are not trivially aligned.
The observation poses are the same as ``simulate(scenario, np.random.default_rng(seed))``.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from lidar_cam_calib.io.bag import BagWriter

from lidar_cam_calib.core.geometry import inv_T, make_T, quat_from_R, so3_exp, so3_log
from lidar_cam_calib.sim.lrf_world import LrfWorld
from lidar_cam_calib.sim.scenario import load_scenario

TOPIC_SCAN = "/scan"
TOPIC_DEPTH = "/camera/depth/image_raw"
TOPIC_DEPTH_INFO = "/camera/depth/camera_info"
TOPIC_COLOR = "/camera/color/image_raw"
TOPIC_COLOR_INFO = "/camera/color/camera_info"
TOPIC_RIGHT_DEPTH = "/camera_right/depth/image_raw"
TOPIC_RIGHT_INFO = "/camera_right/depth/camera_info"

T_SCAN = "sensor_msgs/msg/LaserScan"
T_IMAGE = "sensor_msgs/msg/Image"
T_INFO = "sensor_msgs/msg/CameraInfo"


def depth_to_16uc1(depth_m: np.ndarray) -> np.ndarray:
    """Metres (NaN/0/inf invalid) -> uint16 millimetres with 0 = invalid (values > 65.535 m -> 0)."""
    d = np.asarray(depth_m, dtype=np.float64)
    mm = np.where(np.isfinite(d) & (d > 0), np.round(d * 1000.0), 0.0)
    mm[mm > 65535] = 0
    return mm.astype(np.uint16)


def _interp_T(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose between T0 (s = 0) and T1 (s = 1): geodesic rotation, linear translation."""
    R = T0[:3, :3] @ so3_exp(s * so3_log(T0[:3, :3].T @ T1[:3, :3]))
    return make_T(R, (1 - s) * T0[:3, 3] + s * T1[:3, 3])


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def build_timeline(n_poses: int, tl) -> tuple[list, list, list]:
    """Frame times of the bag.

    Returns (scan_times, depth_times, static_intervals) where each time entry is
    (stamp_s, pose_index, s): pose ``pose_index`` blended towards the next by ``s`` in [0, 1]
    (s = 0 while standing still). ``static_intervals``: (index, start_s, end_s)."""
    cycle = tl.static_s + tl.drive_s
    duration = (n_poses - 1) * cycle + tl.static_s  # relative times avoid float loss at 1.7e9 s

    def where(rel: float):
        i = min(int(np.floor(rel / cycle + 1e-9)), n_poses - 1)
        tau = rel - i * cycle
        if tau <= tl.static_s + 1e-9 or i == n_poses - 1:
            return i, 0.0
        return i, _smoothstep((tau - tl.static_s) / tl.drive_s)

    def grid(rate_hz: float, offset_s: float) -> list:
        n = int(np.floor((duration - offset_s) * rate_hz + 1e-6)) + 1
        out = []
        for k in range(max(n, 0)):
            rel = offset_s + k / rate_hz
            out.append((tl.start_s + rel,) + where(rel))
        return out

    statics = [(i, tl.start_s + i * cycle, tl.start_s + i * cycle + tl.static_s) for i in range(n_poses)]
    return grid(tl.scan_hz, 0.0), grid(tl.depth_hz, tl.depth_offset_s), statics


def _T_yaml(T: np.ndarray) -> dict:
    return {"matrix": np.asarray(T, dtype=float).round(12).tolist(),
            "translation_m": np.asarray(T[:3, 3], dtype=float).round(12).tolist(),
            "quaternion_xyzw": quat_from_R(T[:3, :3]).round(12).tolist()}


def write_lrf_bag(scenario, out_dir, seed: Optional[int] = None, overwrite: bool = False
                  ) -> tuple[Path, Path]:
    """Simulate ``scenario`` and write ``<out_dir>/<name>/`` (MCAP bag) + ``<name>/truth.yaml``.

    ``seed`` overrides ``scenario.seed`` (poses and noise). With ``overwrite`` an existing bag
    directory / truth file of the same name is replaced, otherwise BagError is raised.
    Returns (bag_path, truth_yaml_path)."""
    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.msgtypes import RosbagsFactory, stamp_to_ns

    sc = load_scenario(scenario)
    seed = sc.seed if seed is None else int(seed)
    world = LrfWorld(sc)
    rng = np.random.default_rng(seed)
    poses = world.sample_poses(rng)
    tl = sc.timeline
    scan_times, depth_times, statics = build_timeline(len(poses), tl)

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = out_dir / sc.name
    truth_path = bag_path / "truth.yaml"
    if overwrite:
        if bag_path.is_dir() and (any(bag_path.glob("*.mcap")) or (bag_path / "metadata.yaml").exists()):
            shutil.rmtree(bag_path)

    fac = RosbagsFactory()
    fr = world.truth().frames
    write_color = bool(tl.write_color)
    write_right = bool(tl.write_right) and world.has_right
    cam, cam_r = world.depth_cam.camera, (world.depth_cam_right.camera if world.has_right else None)

    def pose_at(i: int, s: float):
        if s <= 0.0:
            return poses[i]
        (A0, B0), (A1, B1) = poses[i], poses[i + 1]
        return _interp_T(A0, A1, s), _interp_T(B0, B1, s)

    # Merge both streams in time order (a scan and a depth frame never share a stamp when
    # depth_offset_s is not a multiple of the scan period; ties are written scan first).
    events = [(t, 0, i, s) for (t, i, s) in scan_times] + [(t, 1, i, s) for (t, i, s) in depth_times]
    events.sort(key=lambda e: (e[0], e[1]))
    counts: dict = {}
    writer = BagWriter(bag_path, compress=bool(tl.compress)).open()  # refuses an existing path
    try:
        for t, kind, i, s in events:
            T_wa, T_wb = pose_at(i, s)
            ns = stamp_to_ns(t)
            if kind == 0:
                obs = world.observe(t, T_wa, T_wb, rng, depth=False)
                hdr = fac.make_header(t, fr["laser"])
                msg = convert.make_laserscan(obs.scan_ranges_m, obs.scan_angle_min_rad,
                                             obs.scan_angle_increment_rad, obs.scan_range_min_m,
                                             obs.scan_range_max_m, fac, hdr,
                                             scan_time=1.0 / tl.scan_hz)
                out = [(TOPIC_SCAN, T_SCAN, msg)]
            else:
                obs = world.observe(t, T_wa, T_wb, rng, color=write_color, right=write_right)
                hdr = fac.make_header(t, fr["camera"])
                out = [(TOPIC_DEPTH, T_IMAGE, convert.array_to_image(depth_to_16uc1(obs.depth_m), "16UC1", fac, hdr)),
                       (TOPIC_DEPTH_INFO, T_INFO, convert.camera_model_to_camera_info(cam, fac, hdr))]
                if write_color and obs.color_bgr is not None:
                    out += [(TOPIC_COLOR, T_IMAGE, convert.array_to_image(obs.color_bgr, "bgr8", fac, hdr)),
                            (TOPIC_COLOR_INFO, T_INFO, convert.camera_model_to_camera_info(cam, fac, hdr))]
                if write_right and obs.depth_right_m is not None:
                    hdr_r = fac.make_header(t, fr["camera_right"])
                    out += [(TOPIC_RIGHT_DEPTH, T_IMAGE,
                             convert.array_to_image(depth_to_16uc1(obs.depth_right_m), "16UC1", fac, hdr_r)),
                            (TOPIC_RIGHT_INFO, T_INFO, convert.camera_model_to_camera_info(cam_r, fac, hdr_r))]
            for topic, typ, msg in out:
                writer.write(topic, typ, ns, msg)
                counts[topic] = counts.get(topic, 0) + 1
    finally:
        writer.close()

    truth = world.truth()
    topics = {"scan": TOPIC_SCAN, "depth": TOPIC_DEPTH, "depth_camera_info": TOPIC_DEPTH_INFO}
    if write_color:
        topics.update(color=TOPIC_COLOR, color_camera_info=TOPIC_COLOR_INFO)
    if write_right:
        topics.update(right_depth=TOPIC_RIGHT_DEPTH, right_depth_camera_info=TOPIC_RIGHT_INFO)
    doc = {
        "scenario": sc.name,
        "seed": seed,
        "bag": bag_path.name,
        "description": "T_a_b maps points from frame b into frame a (p_a = T_a_b @ p_b).",
        "parent_frame": fr["laser"],
        "child_frame": fr["camera"],
        "T_camera_laser": np.asarray(truth.T_camera_laser).round(12).tolist(),
        "translation_m": truth.T_camera_laser[:3, 3].round(12).tolist(),
        "quaternion_xyzw": quat_from_R(truth.T_camera_laser[:3, :3]).round(12).tolist(),
        "right_camera": ({"T_camera_right_laser": _T_yaml(truth.T_camera_right_laser),
                          "T_right_left": _T_yaml(truth.T_right_left),
                          "baseline_m": float(sc.camera.baseline_m)} if world.has_right else None),
        "T_agv_laser": _T_yaml(truth.T_agv_laser),
        "T_agv_camera": _T_yaml(truth.T_agv_camera),
        "frames": fr,
        "topics": topics,
        "message_counts": counts,
        "board": {"frame": "origin bottom-centre of base PBDQ, x right, y up, z out of the front",
                  **truth.params["board"]},
        "static_intervals": [
            {"index": i, "start_s": float(a), "end_s": float(b),
             "T_world_agv": np.asarray(poses[i][0]).round(12).tolist(),
             "T_world_board": np.asarray(poses[i][1]).round(12).tolist(),
             "T_camera_board": (inv_T(poses[i][0] @ truth.T_agv_camera) @ poses[i][1]).round(12).tolist()}
            for (i, a, b) in statics],
        "scenario_params": sc.to_dict(),
    }
    tmp = truth_path.with_suffix(".yaml.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    tmp.replace(truth_path)
    return bag_path, truth_path


def main(argv=None) -> int:
    """``python -m lidar_cam_calib.sim.lrf_bag SCENARIO.yaml OUT_DIR [--seed N] [--overwrite]``."""
    import argparse
    import time

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("scenario")
    ap.add_argument("out_dir")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    bag, truth = write_lrf_bag(a.scenario, a.out_dir, seed=a.seed, overwrite=a.overwrite)
    size = sum(f.stat().st_size for f in Path(bag).rglob("*") if f.is_file())
    print(f"wrote {bag} ({size / 1e6:.1f} MB) and {truth} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
