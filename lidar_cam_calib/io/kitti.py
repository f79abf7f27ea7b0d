"""Convert a KITTI raw drive folder into an MCAP bag with its ground-truth extrinsic.

``kitti_to_bag(kitti_dir, out_dir)`` reads

* ``image_02/data/*.png``            rectified left colour camera (cam2),
* ``velodyne_points/data/*.bin``     HDL-64E sweeps, float32 rows ``x y z reflectance``,
* ``calib_velo_to_cam.txt``          ``R``, ``T``: Velodyne -> unrectified cam0,
* ``calib_cam_to_cam.txt``           ``R_rect_00`` and ``P_rect_02``,

(the calib files are looked for in ``kitti_dir`` and its parent, as the KITTI raw layout keeps
them one level above the drive folder) and writes ``<out_dir>/<name>/`` (rosbag2 MCAP bag
directory, zstd chunks) with ``truth.yaml`` inside it:

* ``/lidar/points``        sensor_msgs/msg/PointCloud2, frame ``velodyne``, fields x y z intensity
                           (reflectance 0..1 as float32) time (float32 s relative to the stamp, from
                           each point's azimuth: :func:`kitti_point_time`),
* ``/camera/image_raw``    sensor_msgs/msg/Image bgr8, frame ``camera_optical_frame``,
* ``/camera/camera_info``  sensor_msgs/msg/CameraInfo: K = P_rect_02[:, :3], no distortion (the
                           images are rectified), R = I, P = P_rect_02.

Stamps: when the drive has KITTI's ``image_02/timestamps.txt`` and
``velodyne_points/timestamps.txt`` (one ``YYYY-MM-DD HH:MM:SS.fffffffff`` UTC line per frame, the
LiDAR's being the moment it faced forward), they are used; otherwise frame ``k`` (sorted by file
name, paired by the file stem) is stamped ``start_stamp_s + k / 10`` on both streams (KITTI's
nominal 10 Hz). ``truth.yaml`` says which (``stamps``).

Truth (``truth.yaml``): ``T_camera_lidar`` = Velodyne -> rectified cam2, as KITTI derives it:
``inv(K2) @ P_rect_02 @ R_rect_00 @ [R|T]`` with ``K2 = P_rect_02[:, :3]``; the translation
column of P_rect_02 (cam2's offset from rectified cam0) is carried into T.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml

from lidar_cam_calib.core.errors import InputError
from lidar_cam_calib.core.geometry import spin_time_s

TOPIC_POINTS = "/lidar/points"
TOPIC_IMAGE = "/camera/image_raw"
TOPIC_INFO = "/camera/camera_info"
LIDAR_FRAME = "velodyne"
CAMERA_FRAME = "camera_optical_frame"
KITTI_RATE_HZ = 10.0
# 2011-09-26 00:00 UTC, the recording day of the KITTI raw drives named 2011_09_26 (the exact time
# of day is not in the source; only differences between stamps matter).
DEFAULT_START_STAMP_S = 1316995200.0
SWEEP_PERIOD_S = 1.0 / KITTI_RATE_HZ


def kitti_point_time(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-point time (float32 s) relative to the sweep's stamp, from each point's azimuth.

    KITTI's files carry no per-point time, and their stamp is not the sweep's start: the HDL-64E
    triggers the cameras when it faces forward, which is the moment ``velodyne_points/timestamps.txt``
    records, and a sweep begins and ends facing backward. The head spins clockwise seen from above
    (the azimuth ``atan2(y, x)`` falls with time), so a point at azimuth ``a`` deg was measured
    ``((180 - a) mod 360) / 360 * 0.1 - 0.05`` s from the stamp: -0.05 s at the rear on the left,
    0 straight ahead, +0.05 s at the rear on the right. Without it a motion de-skew that takes the
    stamp for the sweep's start puts the sweep half a turn (at 1.3 m/s, 6.5 cm) from where the camera
    saw it."""
    return spin_time_s(np.asarray(x, float), np.asarray(y, float), SWEEP_PERIOD_S, spin=-1, start_azimuth_deg=180.0,
                       stamp_fraction=0.5).astype(np.float32)


def read_kitti_calib(path: Path) -> dict:
    """``key: v1 v2 ...`` lines -> {key: float array} (non-numeric values kept as strings)."""
    out: dict = {}
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read KITTI calibration file {path}: {exc}") from exc
    for line in text.splitlines():
        if ":" not in line:
            continue
        key, val = line.split(":", 1)
        try:
            out[key.strip()] = np.array([float(x) for x in val.split()])
        except ValueError:
            out[key.strip()] = val.strip()
    return out


def _find_calib(kitti_dir: Path, name: str) -> Path:
    for cand in (kitti_dir / name, kitti_dir.parent / name):
        if cand.is_file():
            return cand
    raise InputError(f"KITTI calibration file {name} not found in {kitti_dir} or {kitti_dir.parent}; "
                     "copy the drive's calib_*.txt files next to image_02/ and velodyne_points/")


def _need(calib: dict, key: str, n: int, path: Path) -> np.ndarray:
    v = calib.get(key)
    if not isinstance(v, np.ndarray) or v.size != n:
        got = "missing" if v is None else f"{getattr(v, 'size', '?')} values"
        raise InputError(f"{path}: key {key} must have {n} numbers ({got})")
    return v


def kitti_calibration(kitti_dir) -> tuple[np.ndarray, np.ndarray]:
    """(T_camera_lidar 4x4: Velodyne -> rectified cam2, P_rect_02 3x4) from the calib files."""
    kitti_dir = Path(kitti_dir)
    p_v2c = _find_calib(kitti_dir, "calib_velo_to_cam.txt")
    p_c2c = _find_calib(kitti_dir, "calib_cam_to_cam.txt")
    v2c, c2c = read_kitti_calib(p_v2c), read_kitti_calib(p_c2c)
    R = _need(v2c, "R", 9, p_v2c).reshape(3, 3)
    T = _need(v2c, "T", 3, p_v2c)
    R_rect = _need(c2c, "R_rect_00", 9, p_c2c).reshape(3, 3)
    P2 = _need(c2c, "P_rect_02", 12, p_c2c).reshape(3, 4)
    K2 = P2[:, :3]
    if not (K2[0, 0] > 0 and K2[1, 1] > 0):
        raise InputError(f"{p_c2c}: P_rect_02 has no focal length ({K2[0, 0]}, {K2[1, 1]})")
    Tr = np.eye(4)
    Tr[:3, :3], Tr[:3, 3] = R, T
    R4 = np.eye(4)
    R4[:3, :3] = R_rect
    T_cl = np.eye(4)
    T_cl[:3, :] = np.linalg.solve(K2, P2) @ R4 @ Tr
    return T_cl, P2


def read_kitti_timestamps(path: Path) -> np.ndarray:
    """KITTI ``timestamps.txt`` (``2011-09-26 13:02:25.964389445`` per line, UTC) -> epoch seconds."""
    import datetime as _dt

    out = []
    for i, line in enumerate(Path(path).read_text(encoding="utf-8", errors="replace").splitlines()):
        line = line.strip()
        if not line:
            continue
        try:
            day, clock = line.split()
            hms, _, frac = clock.partition(".")
            base = _dt.datetime.strptime(f"{day} {hms}", "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc)
            out.append(base.timestamp() + (float("0." + frac) if frac else 0.0))
        except ValueError as exc:
            raise InputError(f"{path}:{i + 1}: cannot parse timestamp {line!r} "
                             "(expected 'YYYY-MM-DD HH:MM:SS.fffffffff')") from exc
    return np.array(out, dtype=float)


def _frames(kitti_dir: Path) -> list[tuple[str, Path, Path]]:
    img_dir = kitti_dir / "image_02" / "data"
    pc_dir = kitti_dir / "velodyne_points" / "data"
    for d in (img_dir, pc_dir):
        if not d.is_dir():
            raise InputError(f"{kitti_dir} is not a KITTI raw drive folder: {d} is missing "
                             "(expected image_02/data/*.png and velodyne_points/data/*.bin)")
    imgs = {p.stem: p for p in img_dir.glob("*.png")}
    bins = {p.stem: p for p in pc_dir.glob("*.bin")}
    stems = sorted(set(imgs) & set(bins))
    if not stems:
        raise InputError(f"no frame of {kitti_dir} has both image_02/data/<n>.png and "
                         f"velodyne_points/data/<n>.bin ({len(imgs)} images, {len(bins)} scans found)")
    return [(s, imgs[s], bins[s]) for s in stems]


def kitti_drive(kitti_dir) -> tuple:
    """ROS-free access to a drive: ``(camera, T_camera_lidar, frames)`` with ``frames`` a list of
    ``(stamp_s, load)`` where ``load()`` returns ``(cloud, image)``: the sweep as a dict of arrays
    (x, y, z, intensity, time: :func:`kitti_point_time`) and the BGR image. Stamps are the frame index /
    10 Hz (the files carry none)."""
    from lidar_cam_calib.core.camera import CameraModel
    kitti_dir = Path(kitti_dir)
    if not kitti_dir.is_dir():
        raise InputError(f"KITTI folder not found: {kitti_dir}")
    T_cl, P2 = kitti_calibration(kitti_dir)
    frames = _frames(kitti_dir)

    def loader(img_p: Path, bin_p: Path):
        def load():
            import cv2
            raw = np.fromfile(bin_p, dtype=np.float32)
            if raw.size % 4:
                raise InputError(f"{bin_p}: {raw.size} floats is not a multiple of 4 (x y z reflectance)")
            pts = raw.reshape(-1, 4)
            img = cv2.imread(str(img_p), cv2.IMREAD_COLOR)
            if img is None:
                raise InputError(f"cannot decode image {img_p}")
            return {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": pts[:, 3],
                    "time": kitti_point_time(pts[:, 0], pts[:, 1])}, img
        return load
    out = [(k / KITTI_RATE_HZ, loader(img_p, bin_p)) for k, (_, img_p, bin_p) in enumerate(frames)]
    _, img0 = out[0][1]()
    cam = CameraModel(int(img0.shape[1]), int(img0.shape[0]), P2[:, :3].copy(), np.zeros(5), "plumb_bob")
    return cam, T_cl, out


def kitti_to_bag(kitti_dir, out_dir, overwrite: bool = False, max_frames: int | None = None,
                 start_stamp_s: float = DEFAULT_START_STAMP_S, name: str | None = None
                 ) -> tuple[Path, Path]:
    """Write the KITTI drive in ``kitti_dir`` as ``<out_dir>/<name>/`` (MCAP) + ``truth.yaml``.

    ``name`` defaults to the drive folder's name; ``max_frames`` keeps the first frames only.
    Frames present in only one of the two streams are skipped. Returns (bag_path, truth_path).
    Raises InputError for a folder that is not a KITTI drive (what is missing is named) and
    BagError when the bag exists and ``overwrite`` is false."""
    import cv2

    from lidar_cam_calib.io import convert
    from lidar_cam_calib.io.bag import BagError
    from lidar_cam_calib.io.msgtypes import RosbagsFactory, stamp_to_ns
    from lidar_cam_calib.io.bag import BagWriter

    kitti_dir = Path(kitti_dir)
    if not kitti_dir.is_dir():
        raise InputError(f"KITTI folder not found: {kitti_dir}")
    T_cl, P2 = kitti_calibration(kitti_dir)
    frames = _frames(kitti_dir)
    stamps_img = stamps_pc = None
    ts_img = kitti_dir / "image_02" / "timestamps.txt"
    ts_pc = kitti_dir / "velodyne_points" / "timestamps.txt"
    if ts_img.is_file() and ts_pc.is_file():
        t_img, t_pc = read_kitti_timestamps(ts_img), read_kitti_timestamps(ts_pc)
        idx = [int(stem) for stem, _, _ in frames] if all(s.isdigit() for s, _, _ in frames) else []
        if idx and max(idx) < min(t_img.size, t_pc.size):
            stamps_img, stamps_pc = t_img[idx], t_pc[idx]
    if max_frames is not None:
        if int(max_frames) < 1:
            raise InputError(f"max_frames must be >= 1, got {max_frames}")
        frames = frames[: int(max_frames)]

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bag_path = out_dir / (name or kitti_dir.name)
    if bag_path.exists():
        if not overwrite:
            raise BagError(f"cannot write bag: {bag_path} already exists (use overwrite=True)")
        shutil.rmtree(bag_path)
    truth_path = bag_path / "truth.yaml"

    fac = RosbagsFactory()
    counts: dict = {}
    size = None
    writer = BagWriter(bag_path, compress=True).open()  # BagWriter refuses an existing path
    try:
        events = []
        for k in range(len(frames)):
            if stamps_img is not None:
                events += [(float(stamps_pc[k]), 0, k), (float(stamps_img[k]), 1, k)]
            else:
                t = float(start_stamp_s) + k / KITTI_RATE_HZ
                events += [(t, 0, k), (t, 1, k)]
        events.sort()
        clouds: dict = {}
        for t, kind, k in events:
            stem, img_p, bin_p = frames[k]
            ns = stamp_to_ns(t)
            if kind == 0:
                raw = np.fromfile(bin_p, dtype=np.float32)
                if raw.size % 4:
                    raise InputError(f"{bin_p}: {raw.size} floats is not a multiple of 4 (x y z reflectance)")
                pts = raw.reshape(-1, 4)
                clouds[k] = int(pts.shape[0])
                hdr_l = fac.make_header(t, LIDAR_FRAME)
                out = [(TOPIC_POINTS, "sensor_msgs/msg/PointCloud2",
                        convert.arrays_to_pointcloud2(pts[:, :3], fac, hdr_l, intensity=pts[:, 3],
                                                      time_s=kitti_point_time(pts[:, 0], pts[:, 1])))]
            else:
                img = cv2.imread(str(img_p), cv2.IMREAD_COLOR)
                if img is None:
                    raise InputError(f"cannot decode image {img_p}")
                if size is None:
                    size = (img.shape[1], img.shape[0])
                elif size != (img.shape[1], img.shape[0]):
                    raise InputError(f"{img_p} is {img.shape[1]}x{img.shape[0]}, earlier images were "
                                     f"{size[0]}x{size[1]}")
                hdr_c = fac.make_header(t, CAMERA_FRAME)
                K = P2[:, :3]
                info = fac.make("sensor_msgs/msg/CameraInfo", header=hdr_c, width=int(img.shape[1]),
                                height=int(img.shape[0]), distortion_model="plumb_bob", d=np.zeros(5),
                                k=K.reshape(-1), r=np.eye(3).reshape(-1), p=P2.reshape(-1))
                out = [(TOPIC_IMAGE, "sensor_msgs/msg/Image", convert.array_to_image(img, "bgr8", fac, hdr_c)),
                       (TOPIC_INFO, "sensor_msgs/msg/CameraInfo", info)]
            for topic, typ, msg in out:
                writer.write(topic, typ, ns, msg)
                counts[topic] = counts.get(topic, 0) + 1
    finally:
        writer.close()

    doc = {
        "source": str(kitti_dir.resolve()),
        "bag": bag_path.name,
        "description": "T_a_b maps points from frame b into frame a (p_a = T_a_b @ p_b). "
                       "T_camera_lidar = inv(K2) @ P_rect_02 @ R_rect_00 @ [R|T] (Velodyne -> "
                       "rectified cam2), K2 = P_rect_02[:, :3].",
        "parent_frame": LIDAR_FRAME,
        "child_frame": CAMERA_FRAME,
        "T_camera_lidar": T_cl.round(12).tolist(),
        "translation_m": T_cl[:3, 3].round(12).tolist(),
        "P_rect_02": P2.round(12).tolist(),
        "frames": {"lidar_frame": LIDAR_FRAME, "camera_frame": CAMERA_FRAME},
        "topics": {"points": TOPIC_POINTS, "image": TOPIC_IMAGE, "camera_info": TOPIC_INFO},
        "message_counts": counts,
        "rate_hz": KITTI_RATE_HZ,
        "stamps": "timestamps.txt" if stamps_img is not None else "frame index / 10 Hz",
        "start_stamp_s": float(stamps_pc[0]) if stamps_img is not None else float(start_stamp_s),
        "frame_files": [s for s, _, _ in frames],
        "points_per_sweep": {"min": min(clouds.values(), default=0), "max": max(clouds.values(), default=0)},
        "time_offset_s": 0.0,
        "notes": "KITTI triggers the cameras when the LiDAR faces forward (time offset 0 by design); "
                 "sweeps are not motion-compensated; the files carry no per-point time, so the bag's "
                 "'time' field is each point's azimuth turned into time about the forward-facing stamp "
                 "(clockwise spin, 0.1 s per turn)",
    }
    tmp = truth_path.with_suffix(".yaml.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None)
    tmp.replace(truth_path)
    return bag_path, truth_path


def main(argv=None) -> int:
    """``python -m lidar_cam_calib.io.kitti KITTI_DIR OUT_DIR [--max-frames N] [--overwrite]``."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("kitti_dir")
    ap.add_argument("out_dir")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    bag, truth = kitti_to_bag(a.kitti_dir, a.out_dir, overwrite=a.overwrite, max_frames=a.max_frames)
    print(f"wrote {bag} and {truth}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
