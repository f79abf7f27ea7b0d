"""Write a simulated ``targetless`` drive (street, spinning LiDAR, camera) as an MCAP bag.

``write_street_bag(scenario, out_dir)`` creates ``<out_dir>/<scenario.name>/`` (rosbag2 MCAP
directory, zstd-compressed chunks) with the ground truth inside it as ``truth.yaml``.

Topics (log time == header stamp; LiDAR stamps on the LiDAR clock, camera stamps on the camera
clock, which runs ``time_offset_s`` ahead: no hardware trigger):

* ``/lidar/points``         sensor_msgs/msg/PointCloud2, frame ``lidar``, fields x y z intensity
                            [ring] [time] as the preset's driver publishes them (``time``: float32
                            seconds after the header stamp = sweep start); points are NOT
                            motion-compensated.
* ``/camera/image_raw``     sensor_msgs/msg/Image bgr8 (mono8 if ``camera.mono``), frame
                            ``camera_optical_frame``, stamped at the exposure (camera clock).
* ``/camera/camera_info``   sensor_msgs/msg/CameraInfo (same stamps), distortion as simulated.
* ``/camera/dynamic_mask``  (only with ``write_masks``) sensor_msgs/msg/Image mono8, same stamps
                            and frame, 255 on moving objects: what an upstream instance
                            segmentation node (Mask R-CNN in paper 001) would publish, as truth.

Frames are rendered one by one (nothing is held in memory) in stamp order.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml

from lidar_cam_calib.core.geometry import quat_from_R
from lidar_cam_calib.sim.street_world import (
    iter_drive,
    load_street_scenario,
    sample_street_family,
)

TOPIC_POINTS = "/lidar/points"
TOPIC_IMAGE = "/camera/image_raw"
TOPIC_INFO = "/camera/camera_info"
TOPIC_MASK = "/camera/dynamic_mask"


def _T_doc(T: np.ndarray) -> dict:
    T = np.asarray(T, dtype=float)
    return {"matrix": T.round(12).tolist(), "translation_m": T[:3, 3].round(12).tolist(),
            "quaternion_xyzw": quat_from_R(T[:3, :3]).round(12).tolist()}


def write_street_bag(scenario, out_dir, seed: int | None = None, overwrite: bool = False,
                     image_scale: float = 1.0, duration_s: float | None = None,
                     write_masks: bool = False) -> tuple[Path, Path]:
    """Simulate ``scenario`` (StreetScenario, dict, YAML path or None) into ``<out_dir>/<name>/``.

    ``seed`` overrides ``scenario.seed`` (layout, motion phases, noise). With ``overwrite`` an
    existing bag directory of that name is replaced, otherwise BagError is raised.
    Returns (bag_path, truth_yaml_path)."""
    import dataclasses

    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.bag import BagError
    from lidar_cam_calib.io.msgtypes import RosbagsFactory, stamp_to_ns
    from lidar_cam_calib.io.bag import BagWriter

    sc = load_street_scenario(scenario)
    if seed is not None:
        sc = dataclasses.replace(sc, seed=int(seed))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = out_dir / sc.name
    truth_path = bag_path / "truth.yaml"
    if bag_path.exists():
        if not overwrite:
            raise BagError(f"cannot write bag: {bag_path} already exists (use overwrite=True)")
        shutil.rmtree(bag_path)

    it = iter_drive(sc, np.random.default_rng(sc.seed), duration_s=duration_s, image_scale=image_scale)
    run = next(it)
    fr = run.frames
    fac = RosbagsFactory()
    counts: dict = {}
    sweep_stamps, image_stamps, exposures = [], [], []
    n_points = []
    enc = "mono8" if sc.camera.mono else "bgr8"
    writer = BagWriter(bag_path, compress=True).open()  # BagWriter refuses an existing path
    try:
        for stamp, kind, item in it:
            ns = stamp_to_ns(stamp)
            if kind == "sweep":
                c = item.cloud
                hdr = fac.make_header(stamp, fr["lidar_frame"])
                xyz = np.stack([c["x"], c["y"], c["z"]], axis=1)
                msg = convert.arrays_to_pointcloud2(xyz, fac, hdr, intensity=c.get("intensity"),
                                                    ring=c.get("ring"), time_s=c.get("time"))
                out = [(TOPIC_POINTS, "sensor_msgs/msg/PointCloud2", msg)]
                sweep_stamps.append(float(stamp))
                n_points.append(int(xyz.shape[0]))
            else:
                hdr = fac.make_header(stamp, fr["camera_frame"])
                out = [(TOPIC_IMAGE, "sensor_msgs/msg/Image", convert.array_to_image(item.image, enc, fac, hdr)),
                       (TOPIC_INFO, "sensor_msgs/msg/CameraInfo",
                        convert.camera_model_to_camera_info(run.camera, fac, hdr))]
                if write_masks:
                    mask = item.dynamic_mask.astype(np.uint8) * np.uint8(255)
                    out.append((TOPIC_MASK, "sensor_msgs/msg/Image", convert.array_to_image(mask, "mono8", fac, hdr)))
                image_stamps.append(float(stamp))
                exposures.append(float(item.exposure_s))
            for topic, typ, msg in out:
                writer.write(topic, typ, ns, msg)
                counts[topic] = counts.get(topic, 0) + 1
    finally:
        writer.close()

    traj = run.T_world_lidar
    cam = run.camera
    lid = run.lidar
    doc = {
        "scenario": sc.name,
        "seed": int(sc.seed),
        "bag": bag_path.name,
        "description": "T_a_b maps points from frame b into frame a (p_a = T_a_b @ p_b). "
                       "Camera stamps = LiDAR-clock exposure time + time_offset_s.",
        "parent_frame": fr["lidar_frame"],
        "child_frame": fr["camera_frame"],
        "T_camera_lidar": np.asarray(run.T_camera_lidar).round(12).tolist(),
        "translation_m": run.T_camera_lidar[:3, 3].round(12).tolist(),
        "quaternion_xyzw": quat_from_R(run.T_camera_lidar[:3, :3]).round(12).tolist(),
        "frames": fr,
        "time_offset_s": float(run.time_offset_s),
        "speed_set": run.speed_set,
        "mean_speed_kmh": float(run.mean_speed_kmh),
        "lidar_preset": lid.name,
        "lidar_model": getattr(lid, "model", lid.name),
        "lidar_fields": sorted(set(getattr(lid, "fields", ())) - {"x", "y", "z"}),
        "lidar_rate_hz": float(lid.rate_hz),
        "camera": {"width": cam.width, "height": cam.height, "K": cam.K.round(9).tolist(),
                   "D": cam.D.round(12).tolist(), "distortion_model": cam.distortion_model,
                   "rate_hz": float(sc.camera.rate_hz)},
        "T_car_lidar": _T_doc(run.T_car_lidar),
        "T_car_camera": _T_doc(run.T_car_camera),
        "topics": {"points": TOPIC_POINTS, "image": TOPIC_IMAGE, "camera_info": TOPIC_INFO,
                   **({"dynamic_mask": TOPIC_MASK} if write_masks else {})},
        "message_counts": counts,
        "points_per_sweep": {"min": min(n_points, default=0), "max": max(n_points, default=0)},
        "sweeps": [{"stamp_s": s, "T_world_lidar_at_stamp": np.asarray(traj(s)).round(9).tolist()}
                   for s in sweep_stamps],
        "images": [{"stamp_s": s, "exposure_s": e, "T_world_camera":
                    (np.asarray(traj(e)) @ np.linalg.inv(run.T_camera_lidar)).round(9).tolist()}
                   for s, e in zip(image_stamps, exposures)],
        "landmarks": [{k: v for k, v in lm.items() if k != "pids"} for lm in run.landmarks],
        "image_scale": float(image_scale),
        "scenario_params": run.scenario.to_dict(),
    }
    tmp = truth_path.with_suffix(".yaml.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    tmp.replace(truth_path)
    return bag_path, truth_path


def main(argv=None) -> int:
    """``python -m lidar_cam_calib.sim.street_bag [SCENARIO.yaml] OUT_DIR [--seed N]
    [--family slow|fast] [--image-scale S] [--duration S] [--masks] [--overwrite]``.

    ``--family`` draws a scenario family member from ``--seed`` (default 0) instead of a YAML."""
    import argparse
    import time

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("args", nargs="+", metavar="[SCENARIO] OUT_DIR")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--family", choices=("slow", "fast"), default=None)
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--masks", action="store_true", help="also write /camera/dynamic_mask (truth)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    if len(a.args) > 2:
        ap.error("expected [SCENARIO] OUT_DIR")
    scenario, out_dir = (a.args[0], a.args[1]) if len(a.args) == 2 else (None, a.args[0])
    if a.family is not None:
        if scenario is not None:
            ap.error("give either a SCENARIO file or --family, not both")
        scenario = sample_street_family(0 if a.seed is None else a.seed, a.family)
    t0 = time.perf_counter()
    bag, truth = write_street_bag(scenario, out_dir, seed=a.seed, overwrite=a.overwrite,
                                  image_scale=a.image_scale, duration_s=a.duration, write_masks=a.masks)
    size = sum(f.stat().st_size for f in Path(bag).rglob("*") if f.is_file())
    print(f"wrote {bag} ({size / 1e6:.1f} MB) and {truth} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
