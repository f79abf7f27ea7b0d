"""Micro-benchmark of the message decoders (``lidar-cam-calib bench decode``).

Prints the median wall time of

* ``pointcloud2_to_arrays`` on a 130 000-point cloud laid out like a typical
  spinning LiDAR driver: x, y, z, intensity FLOAT32 at 0/4/8/12, ring UINT16
  at 16, time FLOAT32 at 20 (seconds), point_step 32 (8 bytes padding);
* ``depth_image_to_m`` on a 640x480 16UC1 (millimetre) depth image.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from .convert import depth_image_to_m, pointcloud2_to_arrays
from .msgtypes import RosbagsFactory


def make_bench_cloud(factory, n_points: int = 130_000, seed: int = 0):
    """PointCloud2 with the benchmark layout (see module docstring); ~2 % NaN points."""
    rng = np.random.default_rng(seed)
    dt = np.dtype({
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 20],
        "itemsize": 32,
    })
    rec = np.zeros(n_points, dtype=dt)
    rec["x"], rec["y"], rec["z"] = (rng.normal(size=(3, n_points)) * 10).astype(np.float32)
    rec["x"][rng.random(n_points) < 0.02] = np.nan
    rec["intensity"] = rng.random(n_points) * 255
    rec["ring"] = np.arange(n_points) % 128
    rec["time"] = np.linspace(0.0, 0.1, n_points)
    fields = [
        factory.make("sensor_msgs/msg/PointField", name=nm, offset=off, datatype=dtc, count=1)
        for nm, off, dtc in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4),
                             ("time", 20, 7))
    ]
    return factory.make(
        "sensor_msgs/msg/PointCloud2", header=factory.make_header(1.7e9, "lidar"), height=1, width=n_points,
        fields=fields, is_bigendian=False, point_step=32, row_step=32 * n_points,
        data=rec.view(np.uint8), is_dense=False,
    )


def make_bench_depth(factory, width: int = 640, height: int = 480, seed: int = 0):
    """640x480 16UC1 depth image in millimetres with ~5 % zero (invalid) pixels."""
    rng = np.random.default_rng(seed)
    mm = rng.integers(300, 8000, size=(height, width), dtype=np.uint16)
    mm[rng.random((height, width)) < 0.05] = 0
    return factory.make(
        "sensor_msgs/msg/Image", header=factory.make_header(1.7e9, "cam"), height=height, width=width,
        encoding="16UC1", is_bigendian=False, step=2 * width, data=mm.view(np.uint8).reshape(-1),
    )


def _minor_faults() -> int:
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)
    except Exception:  # noqa: BLE001 - non-POSIX: no fault counter
        return 0


def _median_ms(fn, runs: int) -> tuple[float, float]:
    """(median ms, minor page faults per call); result freeing is inside the timing."""
    fn()  # warm-up
    times = []
    f0 = _minor_faults()
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3), (_minor_faults() - f0) / max(runs, 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lidar-cam-calib bench decode", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50, help="timed repetitions (median reported)")
    ap.add_argument("--points", type=int, default=130_000, help="points in the benchmark cloud")
    args = ap.parse_args(argv)
    factory = RosbagsFactory()
    cloud = make_bench_cloud(factory, args.points)
    depth = make_bench_depth(factory)
    out = pointcloud2_to_arrays(cloud)
    t_cloud, pf_cloud = _median_ms(lambda: pointcloud2_to_arrays(cloud), args.runs)
    t_depth, pf_depth = _median_ms(lambda: depth_image_to_m(depth), args.runs)
    print(f"pointcloud2_to_arrays: {args.points} points (point_step 32, x y z intensity ring time), "
          f"{out['xyz'].shape[0]} valid: median {t_cloud:.2f} ms over {args.runs} runs "
          f"({pf_cloud:.0f} minor page faults/call)")
    print(f"depth_image_to_m: 640x480 16UC1: median {t_depth:.2f} ms over {args.runs} runs "
          f"({pf_depth:.0f} minor page faults/call)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
