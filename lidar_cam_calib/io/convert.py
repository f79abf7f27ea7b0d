"""ROS-free conversions between sensor messages and numpy arrays.

Every ``*_to_*`` reader is duck-typed: it only reads attributes, so rclpy
message objects and rosbags dataclasses (and simple namespaces in tests) all
work.  Writers (``arrays_to_pointcloud2`` ...) take a *factory* from
:mod:`lidar_cam_calib.io.msgtypes` that decides which message classes to
build.  Nothing here imports rclpy.

Frames/units: point coordinates are in the message's ``header.frame_id`` in
metres; times are seconds; angles radians.
"""
from __future__ import annotations

import array
import math
from typing import Any

import numpy as np

from ..core.errors import InputError

__all__ = [
    "POINTFIELD_DTYPES",
    "IMAGE_ENCODINGS",
    "pointcloud2_to_arrays",
    "arrays_to_pointcloud2",
    "image_to_array",
    "array_to_image",
    "depth_image_to_m",
    "camera_info_to_model",
    "camera_model_to_camera_info",
    "laserscan_to_points",
    "make_laserscan",
    "stamp_to_s",
    "validate_laserscan",
]

# sensor_msgs/PointField datatype constants -> (numpy kind code, size in bytes)
POINTFIELD_DTYPES = {
    1: ("i1", 1),  # INT8
    2: ("u1", 1),  # UINT8
    3: ("i2", 2),  # INT16
    4: ("u2", 2),  # UINT16
    5: ("i4", 4),  # INT32
    6: ("u4", 4),  # UINT32
    7: ("f4", 4),  # FLOAT32
    8: ("f8", 8),  # FLOAT64
}
_PF_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64"}

_INTENSITY_NAMES = ("intensity", "reflectivity")
_RING_NAMES = ("ring", "line")
_TIME_NAMES = ("t", "time", "offset_time", "timestamp")


def stamp_to_s(stamp: Any) -> float:
    """Seconds (float64) of a builtin_interfaces/Time (``sec``, ``nanosec``),
    duck-typed; a Header (with ``.stamp``) or a plain number of seconds too.
    The one stamp conversion of the package (nodes, sync, bags)."""
    if hasattr(stamp, "stamp") and not hasattr(stamp, "sec"):
        stamp = stamp.stamp
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return float(stamp.sec) + float(stamp.nanosec) * 1e-9
    return float(stamp)


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _as_bytes_buffer(data: Any) -> np.ndarray:
    """uint8 numpy view (no copy when possible) of a message ``data`` field."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            data = data.view(np.uint8) if data.flags.c_contiguous else np.ascontiguousarray(data).view(np.uint8)
        return data.reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)


# ---------------------------------------------------------------------------
# PointCloud2
# ---------------------------------------------------------------------------
def _field_map(msg: Any) -> dict[str, tuple[int, int, int]]:
    """name -> (offset, datatype, count); first occurrence wins."""
    out: dict[str, tuple[int, int, int]] = {}
    for f in msg.fields:
        name = str(f.name)
        if name not in out:
            out[name] = (int(f.offset), int(f.datatype), int(f.count))
    return out


def pointcloud2_to_arrays(msg: Any, keep_nan: bool = False) -> dict[str, np.ndarray]:
    """Decode a sensor_msgs/PointCloud2 into numpy arrays.

    Returns a dict with

    * ``'xyz'``: (N, 3) float64 metres in ``header.frame_id``.
    * ``'intensity'``: (N,) float32, from a field ``intensity`` or, failing
      that, ``reflectivity`` (only when present).
    * ``'ring'``: (N,) uint16 laser ring/channel, from ``ring`` or ``line``
      (only when present; values outside 0..65535 are clipped).
    * ``'time_s'``: (N,) float64 per-point time in seconds *relative to
      header.stamp*, from the first present of ``t``, ``time``,
      ``offset_time``, ``timestamp`` (only when present).  Units are detected:
      integer fields are nanoseconds; float fields are seconds if every
      |value| <= 1e3, nanoseconds if < 1e8 ... (see ``_decode_time``); values
      that look absolute (epoch seconds or epoch nanoseconds) are made
      relative by subtracting the header stamp.
    * ``'valid'``: (N,) bool, all of x, y, z finite.  With ``keep_nan=False``
      (default) invalid points are dropped, so it is all True; with
      ``keep_nan=True`` every point is kept (organised clouds keep their
      row-major order) and the mask tells which are usable.
    * ``'index'``: (N,) int64 row-major index of each returned point in the
      original ``height x width`` grid.
    * ``'shape'``: (2,) int64 ``(height, width)`` of the message.

    Any layout is supported: arbitrary field offsets, padding inside
    ``point_step``, padding at the end of each row (``row_step``), big-endian
    data, all PointField datatypes.  Fields with ``count > 1`` contribute their
    first element only.

    Raises ValueError when x, y or z is missing or the data buffer is too short.
    """
    fields = _field_map(msg)
    missing = [c for c in ("x", "y", "z") if c not in fields]
    if missing:
        raise InputError(
            f"PointCloud2 has no {'/'.join(missing)} field(s); fields present: {sorted(fields)}"
        )
    height = int(msg.height)
    width = int(msg.width)
    point_step = int(msg.point_step)
    row_step = int(msg.row_step) if int(msg.row_step) > 0 else width * point_step
    endian = ">" if bool(msg.is_bigendian) else "<"

    wanted: dict[str, str] = {"x": "x", "y": "y", "z": "z"}
    for key, names in (("intensity", _INTENSITY_NAMES), ("ring", _RING_NAMES), ("time", _TIME_NAMES)):
        for n in names:
            if n in fields:
                wanted[key] = n
                break

    names, formats, offsets = [], [], []
    for key, fname in wanted.items():
        off, dt, _count = fields[fname]
        if dt not in POINTFIELD_DTYPES:
            raise InputError(f"PointCloud2 field {fname!r} has unknown datatype {dt}")
        code, size = POINTFIELD_DTYPES[dt]
        if off < 0 or off + size > point_step:
            raise InputError(
                f"PointCloud2 field {fname!r} (offset {off}, {size} bytes) does not fit point_step {point_step}"
            )
        names.append(key)
        formats.append(endian + code if size > 1 else code)
        offsets.append(off)

    n_total = height * width
    out: dict[str, np.ndarray] = {"shape": np.array([height, width], dtype=np.int64)}
    if n_total == 0:
        out["xyz"] = np.zeros((0, 3))
        out["valid"] = np.zeros(0, dtype=bool)
        out["index"] = np.zeros(0, dtype=np.int64)
        if "intensity" in wanted:
            out["intensity"] = np.zeros(0, dtype=np.float32)
        if "ring" in wanted:
            out["ring"] = np.zeros(0, dtype=np.uint16)
        if "time" in wanted:
            out["time_s"] = np.zeros(0)
        return out

    if point_step <= 0 or row_step < width * point_step:
        raise InputError(f"PointCloud2 has inconsistent point_step {point_step} / row_step {row_step} "
                         f"for width {width}")
    buf = _as_bytes_buffer(msg.data)
    need = (height - 1) * row_step + width * point_step
    if buf.size < need:
        raise InputError(f"PointCloud2 data has {buf.size} bytes, layout needs {need}")

    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    if row_step == width * point_step:
        raw = buf[: n_total * point_step]
    else:  # drop the padding at the end of each row (one packed copy)
        rows = np.lib.stride_tricks.as_strided(buf, shape=(height, width * point_step), strides=(row_step, 1))
        raw = np.ascontiguousarray(rows).reshape(-1)
    pts = np.frombuffer(raw, dtype=dtype, count=n_total)

    # Validity from the source fields (no float64 temporaries).
    valid = np.isfinite(pts["x"]) & np.isfinite(pts["y"]) & np.isfinite(pts["z"])
    if keep_nan or valid.all():
        index = np.arange(n_total, dtype=np.int64)

        def pick(name: str) -> np.ndarray:
            return pts[name]
    else:
        # Boolean-mask each needed (strided) field view once: measured much
        # cheaper than decoding everything and gathering the outputs later.
        index = np.flatnonzero(valid)
        mask = valid
        valid = np.ones(index.size, dtype=bool)

        def pick(name: str) -> np.ndarray:
            return pts[name][mask]

    xyz = np.empty((index.size, 3), dtype=np.float64)
    xyz[:, 0] = pick("x")
    xyz[:, 1] = pick("y")
    xyz[:, 2] = pick("z")
    out["xyz"] = xyz
    if "intensity" in wanted:
        out["intensity"] = pick("intensity").astype(np.float32)
    if "ring" in wanted:
        ring = pick("ring")
        if ring.dtype.kind == "u" and ring.dtype.itemsize <= 2:
            out["ring"] = ring.astype(np.uint16)
        else:
            out["ring"] = np.clip(np.nan_to_num(ring.astype(np.float64)), 0, 65535).astype(np.uint16)
    if "time" in wanted:
        out["time_s"] = _decode_time(pick("time"), msg.header.stamp)
    out["index"] = index
    out["valid"] = valid
    return out


def _decode_time(t: np.ndarray, header_stamp: Any) -> np.ndarray:
    """Per-point time field -> float64 seconds relative to the header stamp.

    Rules (documented heuristics, decided on the largest finite |value|):

    * integer datatypes: nanoseconds; if the largest value exceeds 1e15 it is
      an absolute epoch time in ns and the header stamp is subtracted.
    * float datatypes: largest |v| <= 1e3 -> relative seconds;
      1e8 < |v| < 1e11 -> absolute epoch seconds (header subtracted);
      |v| >= 1e15 -> absolute epoch nanoseconds (header subtracted);
      otherwise (1e3 .. 1e8 or 1e11 .. 1e15) -> relative nanoseconds.
    """
    if t.size == 0:
        return np.zeros(0)
    if t.dtype.kind in "iu":
        tmax = max(abs(int(t.min())), abs(int(t.max())))
        if tmax > 10**15:
            rel = (t.astype(np.int64) - _stamp_ns(header_stamp)).astype(np.float64)
        else:
            rel = t.astype(np.float64)
        rel *= 1e-9
        return rel
    tf = t.astype(np.float64)
    lo, hi = float(tf.min()), float(tf.max())  # no |t| temporary (allocation churn is costly)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        finite = np.isfinite(tf)
        if not finite.any():
            return tf
        lo, hi = float(tf[finite].min()), float(tf[finite].max())
    amax = max(abs(lo), abs(hi))
    if amax <= 1e3:
        return tf
    if 1e8 < amax < 1e11:
        tf -= stamp_to_s(header_stamp)
        return tf
    if amax >= 1e15:
        tf -= float(_stamp_ns(header_stamp))
    tf *= 1e-9
    return tf


def _make_point_field(factory: Any, name: str, offset: int, datatype: int) -> Any:
    return factory.make("sensor_msgs/msg/PointField", name=name, offset=offset, datatype=datatype, count=1)


def arrays_to_pointcloud2(
    xyz: np.ndarray,
    factory: Any,
    header: Any,
    intensity: np.ndarray | None = None,
    ring: np.ndarray | None = None,
    time_s: np.ndarray | None = None,
) -> Any:
    """Build an unorganised (height 1) little-endian PointCloud2.

    Layout: x, y, z FLOAT32 at 0/4/8, then optional ``intensity`` FLOAT32,
    ``ring`` UINT16 (padded to 4 bytes), ``time`` FLOAT32 seconds relative to
    ``header.stamp``; ``point_step`` is a multiple of 4.  ``is_dense`` is True
    iff every coordinate is finite.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = xyz.shape[0]
    names, formats, offsets, pfs = ["x", "y", "z"], ["<f4"] * 3, [0, 4, 8], []
    for nm, off in zip(names, offsets):
        pfs.append(_make_point_field(factory, nm, off, 7))
    off = 12
    extras: dict[str, np.ndarray] = {}
    for name, values, fmt, datatype, cast in (("intensity", intensity, "<f4", 7, np.float32),
                                              ("ring", ring, "<u2", 4, np.uint16),
                                              ("time", time_s, "<f4", 7, np.float32)):
        if values is None:
            continue
        names.append(name)
        formats.append(fmt)
        offsets.append(off)
        pfs.append(_make_point_field(factory, name, off, datatype))
        off += 4
        extras[name] = np.asarray(values).reshape(-1).astype(cast)
    for k, v in extras.items():
        if v.shape[0] != n:
            raise InputError(f"{k} has {v.shape[0]} values for {n} points")
    point_step = off
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    rec = np.zeros(n, dtype=dtype)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for k, v in extras.items():
        rec[k] = v
    data = rec.view(np.uint8).reshape(-1)
    return factory.make(
        "sensor_msgs/msg/PointCloud2",
        header=header,
        height=1,
        width=n,
        fields=pfs,
        is_bigendian=False,
        point_step=point_step,
        row_step=point_step * n,
        data=data,
        is_dense=bool(np.isfinite(xyz).all()),
    )


# ---------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------
# encoding -> (numpy kind code, channels, channel order for colour)
IMAGE_ENCODINGS = {
    "mono8": ("u1", 1, None),
    "8UC1": ("u1", 1, None),
    "mono16": ("u2", 1, None),
    "16UC1": ("u2", 1, None),
    "32FC1": ("f4", 1, None),
    "bgr8": ("u1", 3, "bgr"),
    "8UC3": ("u1", 3, "bgr"),
    "rgb8": ("u1", 3, "rgb"),
    "bgra8": ("u1", 4, "bgra"),
    "rgba8": ("u1", 4, "rgba"),
}


def _unknown_encoding(enc: str) -> InputError:
    return InputError(f"unsupported image encoding {enc!r}; supported: {', '.join(IMAGE_ENCODINGS)}")


def image_to_array(msg: Any) -> np.ndarray:
    """Decode a sensor_msgs/Image into a new (non-view) numpy array.

    * mono8/8UC1 -> HxW uint8; mono16/16UC1 -> HxW uint16; 32FC1 -> HxW float32.
    * colour encodings (rgb8, bgr8, 8UC3, rgba8, bgra8) -> **HxWx3 uint8 in BGR
      order** (OpenCV convention); alpha is dropped.

    ``step`` row padding and ``is_bigendian`` are honoured.  Raises ValueError
    for an unknown encoding or a short data buffer.
    """
    enc = str(msg.encoding)
    if enc not in IMAGE_ENCODINGS:
        raise _unknown_encoding(enc)
    code, ch, order = IMAGE_ENCODINGS[enc]
    h, w = int(msg.height), int(msg.width)
    elem = np.dtype(code).itemsize
    row_bytes = w * ch * elem
    step = int(msg.step) if int(msg.step) > 0 else row_bytes
    if step < row_bytes:
        raise InputError(f"image step {step} is smaller than width*channels*bytes = {row_bytes}")
    buf = _as_bytes_buffer(msg.data)
    if h == 0 or w == 0:
        shape = (h, w) if ch == 1 else (h, w, 3)
        return np.zeros(shape, dtype=np.dtype(code))
    need = (h - 1) * step + row_bytes
    if buf.size < need:
        raise InputError(f"image data has {buf.size} bytes, {enc} {w}x{h} with step {step} needs {need}")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(h, row_bytes), strides=(step, 1), writeable=False)
    packed = np.array(rows, dtype=np.uint8, copy=True, order="C")  # drops row padding, owns its memory
    dt = np.dtype(code)
    if elem > 1:
        dt = dt.newbyteorder(">" if bool(msg.is_bigendian) else "<")
    arr = packed.view(dt).reshape((h, w) if ch == 1 else (h, w, ch))
    if elem > 1:
        arr = arr.astype(np.dtype(code).newbyteorder("="), copy=False)  # native byte order
    if ch == 1:
        return arr
    if order == "bgr":
        return arr
    if order == "rgb":
        return np.ascontiguousarray(arr[:, :, ::-1])
    if order == "bgra":
        return np.ascontiguousarray(arr[:, :, :3])
    return np.ascontiguousarray(arr[:, :, 2::-1])  # rgba -> bgr


def depth_image_to_m(msg: Any) -> np.ndarray:
    """Depth image -> HxW float32 metres (optical frame z); invalid -> NaN.

    16UC1/mono16 are millimetres, 32FC1 metres.  0, negative, NaN and inf
    depths become NaN.  Other encodings raise ValueError.
    """
    enc = str(msg.encoding)
    if enc in ("16UC1", "mono16"):
        raw = image_to_array(msg)
        depth = raw.astype(np.float32) * np.float32(1e-3)
        depth[raw == 0] = np.nan
        return depth
    if enc == "32FC1":
        depth = image_to_array(msg).astype(np.float32, copy=False)
        bad = ~np.isfinite(depth) | (depth <= 0)
        depth[bad] = np.nan
        return depth
    raise InputError(f"depth image must be 16UC1 (mm) or 32FC1 (m), got {enc}")


def array_to_image(arr: np.ndarray, encoding: str, factory: Any, header: Any) -> Any:
    """Build a little-endian sensor_msgs/Image from an array (inverse of image_to_array).

    Colour input is expected as **BGR** (HxWx3) or BGRA (HxWx4) and is
    reordered for the target encoding (rgb8, bgr8, 8UC3, rgba8, bgra8; alpha
    255 is added when missing).  Mono encodings take HxW arrays (mono8/8UC1
    uint8, mono16/16UC1 uint16, 32FC1 float32); integer targets reject
    non-integer or out-of-range values.  ``step`` is packed (no padding).
    """
    if encoding not in IMAGE_ENCODINGS:
        raise _unknown_encoding(encoding)
    code, ch, order = IMAGE_ENCODINGS[encoding]
    a = np.asarray(arr)
    target = np.dtype(code)
    if ch == 1:
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[:, :, 0]
        if a.ndim != 2:
            raise InputError(f"{encoding} needs an HxW array, got shape {a.shape}")
    else:
        if a.ndim != 3 or a.shape[2] not in (3, 4):
            raise InputError(f"{encoding} needs an HxWx3 (BGR) or HxWx4 (BGRA) array, got shape {a.shape}")
    if a.dtype != target:
        if target.kind in "iu":
            if a.dtype.kind not in "iub":
                raise InputError(f"{encoding} needs integer data, got {a.dtype}")
            info = np.iinfo(target)
            if a.size and (a.min() < info.min or a.max() > info.max):
                raise InputError(f"values out of range for {encoding} ({target})")
        a = a.astype(target)
    if ch > 1:
        bgr = a[:, :, :3]
        alpha = a[:, :, 3] if a.shape[2] == 4 else np.full(a.shape[:2], 255, dtype=np.uint8)
        if order == "bgr":
            a = bgr
        elif order == "rgb":
            a = bgr[:, :, ::-1]
        elif order == "bgra":
            a = np.dstack([bgr, alpha])
        else:
            a = np.dstack([bgr[:, :, ::-1], alpha])
    a = np.array(a, dtype=target.newbyteorder("<"), order="C", copy=True)  # message owns its pixels
    h, w = a.shape[:2]
    return factory.make(
        "sensor_msgs/msg/Image",
        header=header,
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=False,
        step=w * ch * target.itemsize,
        data=a.view(np.uint8).reshape(-1),
    )


# ---------------------------------------------------------------------------
# CameraInfo
# ---------------------------------------------------------------------------
_DIST_LEN = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
_DIST_ALIASES = {"fisheye": "equidistant", "none": "", "pinhole": ""}


def _ci_field(msg: Any, lower: str) -> Any:
    if hasattr(msg, lower):
        return getattr(msg, lower)
    return getattr(msg, lower.upper())  # ROS 1 style K/D/R/P


def camera_info_to_model(msg: Any):
    """sensor_msgs/CameraInfo -> :class:`lidar_cam_calib.core.camera.CameraModel`.

    Uses ``k`` and ``d`` (the raw, unrectified camera); ``r``/``p`` are
    ignored, so feed the *raw* image topic.  distortion_model handling:

    * ``plumb_bob`` (5 coeffs), ``rational_polynomial`` (8), ``equidistant``
      (4; alias ``fisheye``): D is zero-padded or truncated to that length.
    * ``''``/``none``: pinhole if D is empty or all zero; otherwise the model
      is inferred from len(D) (4 -> equidistant, 5 -> plumb_bob, 8 or more ->
      rational_polynomial).
    * anything else -> ValueError.

    Raises ValueError for an all-zero K (uncalibrated camera) or zero size.
    """
    from lidar_cam_calib.core.camera import CameraModel

    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise InputError(f"CameraInfo has image size {width}x{height}; width and height must be > 0")
    K = np.asarray(_ci_field(msg, "k"), dtype=np.float64).reshape(-1)
    if K.size != 9:
        raise InputError(f"CameraInfo K must have 9 values, got {K.size}")
    K = K.reshape(3, 3)
    if not np.any(K):
        raise InputError(
            "CameraInfo K is all zeros: the camera is uncalibrated; calibrate its intrinsics first "
            "(e.g. camera_calibration) or provide a calibrated camera_info"
        )
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"CameraInfo K has invalid focal lengths: fx={K[0, 0]}, fy={K[1, 1]}")
    D = np.asarray(_ci_field(msg, "d"), dtype=np.float64).reshape(-1)
    model = str(msg.distortion_model).strip().lower()
    model = _DIST_ALIASES.get(model, model)
    if model == "":
        if D.size == 0 or not np.any(D):
            return CameraModel(width, height, K, np.zeros(0), "")
        if D.size == 4:
            model = "equidistant"
        elif D.size == 5:
            model = "plumb_bob"
        elif D.size >= 8:
            model = "rational_polynomial"
        else:
            raise InputError(f"CameraInfo has empty distortion_model and {D.size} coefficients; cannot infer model")
    if model not in _DIST_LEN:
        raise InputError(
            f"unsupported distortion_model {msg.distortion_model!r}; supported: plumb_bob, rational_polynomial, "
            "equidistant, '' (none)"
        )
    n = _DIST_LEN[model]
    Dn = np.zeros(n)
    Dn[: min(n, D.size)] = D[:n]
    return CameraModel(width, height, K, Dn, model)


def camera_model_to_camera_info(model: Any, factory: Any, header: Any) -> Any:
    """CameraModel -> sensor_msgs/CameraInfo (R = I, P = [K | 0]).

    A pinhole model ('' / 'none') is written as ``plumb_bob`` with five zero
    coefficients, which is what ROS tools expect for an undistorted camera.
    """
    K = np.asarray(model.K, dtype=np.float64).reshape(3, 3)
    D = np.asarray(model.D, dtype=np.float64).reshape(-1) if model.D is not None else np.zeros(0)
    dm = str(model.distortion_model or "")
    if dm in ("", "none"):
        dm, D = "plumb_bob", np.zeros(5)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return factory.make(
        "sensor_msgs/msg/CameraInfo",
        header=header,
        width=int(model.width),
        height=int(model.height),
        distortion_model=dm,
        d=D,
        k=K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
    )


# ---------------------------------------------------------------------------
# LaserScan
# ---------------------------------------------------------------------------
def laserscan_to_points(msg: Any) -> dict[str, np.ndarray]:
    """sensor_msgs/LaserScan -> beam arrays and valid 2-D points (laser frame).

    Returns ``'angles'`` (N,) rad = angle_min + i*angle_increment,
    ``'ranges'`` (N,) m (float64), ``'valid'`` (N,) bool (finite, > 0 and
    within [range_min, range_max]), ``'xy'`` (K, 2) m of the valid beams
    (x forward, y left), ``'index'`` (K,) their beam indices, ``'time_s'``
    (N,) beam time relative to header.stamp (i*time_increment) and, when the
    message has one intensity per beam, ``'intensities'`` (N,) float32.
    """
    ranges = np.asarray(msg.ranges, dtype=np.float64).reshape(-1)
    n = ranges.size
    i = np.arange(n)
    angles = float(msg.angle_min) + i * float(msg.angle_increment)
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges > 0) & (ranges >= rmin) & (ranges <= rmax)
    index = np.flatnonzero(valid)
    r = ranges[index]
    a = angles[index]
    out = {
        "angles": angles,
        "ranges": ranges,
        "valid": valid,
        "xy": np.stack([r * np.cos(a), r * np.sin(a)], axis=1).reshape(-1, 2),
        "index": index,
        "time_s": i * float(msg.time_increment),
    }
    inten = np.asarray(getattr(msg, "intensities", []), dtype=np.float32).reshape(-1)
    if inten.size == n and n > 0:
        out["intensities"] = inten
    return out


def validate_laserscan(msg: Any) -> np.ndarray:
    """The ranges of a LaserScan as float32, or :class:`InputError` when the
    message contradicts itself: no ranges, a zero or non-finite increment, or
    a ranges length that disagrees with angle_min/angle_max/angle_increment
    (one beam either way is tolerated: drivers differ on the last beam)."""
    r = np.asarray(msg.ranges, dtype=np.float32).reshape(-1)
    a0, a1, inc = float(msg.angle_min), float(msg.angle_max), float(msg.angle_increment)
    if r.size == 0:
        raise InputError("LaserScan has no ranges")
    if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(inc)) or inc == 0.0:
        raise InputError(f"LaserScan angles are not usable: angle_min {a0}, angle_max {a1}, "
                         f"angle_increment {inc}")
    expected = int(round((a1 - a0) / inc)) + 1
    if abs(r.size - expected) > 1:
        raise InputError(f"LaserScan has {r.size} ranges but angle_min {a0:.6f}, angle_max {a1:.6f} and "
                         f"angle_increment {inc:.6g} rad give {expected} beams: the message is inconsistent, dropped")
    return r


def make_laserscan(
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    factory: Any,
    header: Any,
    intensities: np.ndarray | None = None,
    scan_time: float = 0.0,
    time_increment: float = 0.0,
) -> Any:
    """Build a sensor_msgs/LaserScan; ``angle_max = angle_min + (N-1)*angle_increment``."""
    r = np.asarray(ranges, dtype=np.float32).reshape(-1)
    fields = dict(
        header=header,
        angle_min=float(angle_min),
        angle_max=float(angle_min + max(r.size - 1, 0) * angle_increment),
        angle_increment=float(angle_increment),
        time_increment=float(time_increment),
        scan_time=float(scan_time),
        range_min=float(range_min),
        range_max=float(range_max),
        ranges=r,
    )
    if intensities is not None:
        inten = np.asarray(intensities, dtype=np.float32).reshape(-1)
        if inten.size != r.size:
            raise InputError(f"intensities has {inten.size} values for {r.size} ranges")
        fields["intensities"] = inten
    return factory.make("sensor_msgs/msg/LaserScan", **fields)
