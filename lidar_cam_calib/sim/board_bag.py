"""Write a simulated ``board`` session (spinning LiDAR + 1-3 cameras, reflective-border
checkerboard carried between still poses) as an MCAP bag.

``write_board_bag(scenario, out_dir)`` creates ``<out_dir>/<scenario.name>/`` (a rosbag2 MCAP
bag directory, zstd-compressed chunks) and its ground truth beside the bag files as
``<out_dir>/<scenario.name>/truth.yaml`` (rosbag2 readers ignore files metadata.yaml does not
list).

Topics (log time == header stamp; every topic's stamps strictly increase):

* ``/lidar/points``           sensor_msgs/msg/PointCloud2, frame ``lidar``, one message per sweep
                              (stamp = sweep start; fields x, y, z[, intensity, ring, time] as the
                              preset's driver publishes them; ``time`` in s after the stamp)
* ``/<cam>/image_raw``        sensor_msgs/msg/Image (mono8 or bgr8), frame ``<cam>_optical_frame``
* ``/<cam>/camera_info``      sensor_msgs/msg/CameraInfo, same stamps

Timeline: the board stands still ``still_s`` at each pose and is carried ``carry_s`` to the
next; the LiDAR and every camera keep publishing all the time (frames taken while the board
moves are in the bag too: a method must refuse them). Each camera runs at its own rate and
phase, and stamps on its own clock (``time_offset_s`` is added to the true capture time).
The poses are those of ``BoardWorld(scenario, np.random.default_rng(seed))``.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml

from lidar_cam_calib.io.bag import BagWriter

from lidar_cam_calib.core.geometry import quat_from_R
from lidar_cam_calib.sim.board_world import BoardWorld, load_board_scenario

TOPIC_POINTS = "/lidar/points"
T_CLOUD = "sensor_msgs/msg/PointCloud2"
T_IMAGE = "sensor_msgs/msg/Image"
T_INFO = "sensor_msgs/msg/CameraInfo"


def _T_list(T: np.ndarray) -> list:
    return np.asarray(T, dtype=float).round(12).tolist()


def build_events(world: BoardWorld) -> list:
    """Every message slot of the bag in stamp order: (stamp_rel_s, kind, name, t_true_rel_s) with
    kind 'lidar' (name '') or 'camera' (the camera's name)."""
    k = max(int(world.scenario.lidar.record_every), 1)
    ev = [(float(t), "lidar", "", float(t)) for t in world.sweep_starts()[::k]]
    for name, cam in world.cameras.items():
        for tc in world.camera_captures(name):
            ev.append((float(tc) + cam.time_offset_s, "camera", name, float(tc)))
    ev.sort(key=lambda e: (e[0], e[1] != "lidar", e[2]))
    return ev


def write_board_bag(scenario, out_dir, seed: int | None = None, overwrite: bool = False,
                    full_size: bool = True) -> tuple[Path, Path]:
    """Simulate ``scenario`` (path, dict or BoardScenario) and write the bag + truth YAML.

    ``seed`` overrides ``scenario.seed`` (poses, timeline and noise). With ``overwrite`` an
    existing bag directory of the same name is replaced, otherwise BagError is raised.
    Returns (bag_path, truth_yaml_path)."""
    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.msgtypes import RosbagsFactory, stamp_to_ns

    sc = load_board_scenario(scenario)
    seed = sc.seed if seed is None else int(seed)
    rng = np.random.default_rng(seed)
    world = BoardWorld(sc, rng, full_size=full_size)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = out_dir / sc.name
    truth_path = bag_path / "truth.yaml"
    if overwrite and bag_path.is_dir() and (any(bag_path.glob("*.mcap")) or (bag_path / "metadata.yaml").exists()):
        shutil.rmtree(bag_path)
    fac = RosbagsFactory()
    preset = world.preset
    counts: dict = {}
    writer = BagWriter(bag_path, compress=bool(sc.timeline.compress)).open()  # refuses an existing path
    try:
        for stamp_rel, kind, name, t_true in build_events(world):
            stamp = world.start_s + stamp_rel
            ns = stamp_to_ns(stamp)
            if kind == "lidar":
                cloud, _info = world.lidar_sweep(t_true, rng)
                hdr = fac.make_header(stamp, "lidar")
                xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
                msg = convert.arrays_to_pointcloud2(xyz, fac, hdr, intensity=cloud.get("intensity"),
                                                    ring=cloud.get("ring"), time_s=cloud.get("time"))
                out = [(TOPIC_POINTS, T_CLOUD, msg)]
            else:
                cam = world.cameras[name]
                img = world.render(name, world.board_poses_exposed(name, t_true), rng)
                hdr = fac.make_header(stamp, cam.frame_id)
                out = [(cam.image_topic, T_IMAGE, convert.array_to_image(img, cam.encoding, fac, hdr)),
                       (cam.camera_info_topic, T_INFO, convert.camera_model_to_camera_info(cam.model, fac, hdr))]
            for topic, typ, msg in out:
                writer.write(topic, typ, ns, msg)
                counts[topic] = counts.get(topic, 0) + 1
    finally:
        writer.close()

    cams = {}
    for name, cam in world.cameras.items():
        m = cam.model
        cams[name] = {
            "T_camera_lidar": _T_list(cam.T_camera_lidar),
            "translation_m": cam.T_camera_lidar[:3, 3].round(12).tolist(),
            "quaternion_xyzw": quat_from_R(cam.T_camera_lidar[:3, :3]).round(12).tolist(),
            "frame_id": cam.frame_id,
            "image_topic": cam.image_topic,
            "camera_info_topic": cam.camera_info_topic,
            "encoding": cam.encoding,
            "rate_hz": float(cam.rate_hz),
            "phase_s": float(cam.phase_s),
            "time_offset_s": float(cam.time_offset_s),
            "width": int(m.width), "height": int(m.height),
            "K": np.asarray(m.K).round(9).tolist(), "D": np.asarray(m.D).round(12).tolist(),
            "distortion_model": m.distortion_model,
        }
    doc = {
        "scenario": sc.name,
        "seed": seed,
        "bag": bag_path.name,
        "description": ("T_camera_lidar maps LiDAR points into the camera optical frame "
                        "(p_camera = T @ p_lidar). Board frame: origin at the board centre, x along "
                        "the long side, y along the short side, z out of the patterned face; "
                        "square (0, 0) at -x,-y is black; inner corners row-major, x fastest."),
        "lidar_frame": "lidar",
        "lidar_topic": TOPIC_POINTS,
        "lidar": {"preset": preset.name, "model": preset.model, "fields": list(preset.fields),
                  "intensity_scale": preset.intensity_scale,
                  "intensity_threshold": float(preset.intensity_threshold),
                  "rate_hz": float(preset.rate_hz), "n_rings": preset.n_rings,
                  "ring_order": preset.ring_order,
                  "azimuth_range_deg": list(sc.lidar.azimuth_range_deg)},
        "preset": preset.name,
        "cameras": cams,
        "board": world.board.to_dict(),
        "noise": world.noise(),
        "start_s": float(world.start_s),
        "still_intervals": [
            {"index": i, "start_s": float(world.start_s + a), "end_s": float(world.start_s + b),
             "T_lidar_board": _T_list(world.poses[i])}
            for i, (a, b) in enumerate(world.still_intervals)],
        "message_counts": counts,
        "scenario_params": sc.to_dict(),
    }
    tmp = truth_path.with_suffix(".yaml.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    tmp.replace(truth_path)
    return bag_path, truth_path


def main(argv=None) -> int:
    """``python -m lidar_cam_calib.sim.board_bag SCENARIO.yaml OUT_DIR [--seed N] [--family N]
    [--poses N] [--lidar PRESET] [--overwrite]``. ``--family N`` draws the scenario from
    sample_board_family(N) instead of reading SCENARIO (pass ``-`` as SCENARIO)."""
    import argparse
    import time

    from lidar_cam_calib.sim.board_world import sample_board_family

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("scenario", help="scenario YAML, or '-' with --family")
    ap.add_argument("out_dir")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--family", type=int, default=None, help="draw the scenario from this family seed")
    ap.add_argument("--poses", type=int, default=None, help="with --family: number of board poses")
    ap.add_argument("--lidar", default=None, help="with --family: LiDAR preset key")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    if a.family is not None:
        sc = sample_board_family(a.family, poses=a.poses, lidar=a.lidar)
    elif a.scenario == "-":
        ap.error("SCENARIO '-' needs --family N")
    else:
        sc = a.scenario
    t0 = time.perf_counter()
    bag, truth = write_board_bag(sc, a.out_dir, seed=a.seed, overwrite=a.overwrite)
    size = sum(f.stat().st_size for f in Path(bag).rglob("*") if f.is_file())
    print(f"wrote {bag} ({size / 1e6:.1f} MB) and {truth} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
