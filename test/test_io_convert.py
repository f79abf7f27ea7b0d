"""Tests for lidar_cam_calib.io.convert / msgtypes (ROS-free message conversions)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_cam_calib.io.convert import (
    IMAGE_ENCODINGS,
    array_to_image,
    arrays_to_pointcloud2,
    camera_info_to_model,
    camera_model_to_camera_info,
    depth_image_to_m,
    image_to_array,
    laserscan_to_points,
    make_laserscan,
    pointcloud2_to_arrays,
)
from lidar_cam_calib.io.msgtypes import RclpyFactory, RosbagsFactory, split_stamp

_ROSBAGS = RosbagsFactory()


def _rclpy_factory():
    pytest.importorskip("rclpy")
    pytest.importorskip("sensor_msgs.msg")
    return RclpyFactory()


@pytest.fixture(params=["rosbags", "rclpy"])
def factory(request):
    return _ROSBAGS if request.param == "rosbags" else _rclpy_factory()


def _roundtrip_cdr(factory, msg, typename):
    """Serialise and deserialise through the factory (checks CDR compatibility too)."""
    return factory.deserialize(factory.serialize(msg, typename), typename)


# ---------------------------------------------------------------------------
# helpers to build arbitrary PointCloud2 layouts
# ---------------------------------------------------------------------------
_PF_CODE = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def make_cloud(factory, fields, values, point_step, *, height=1, row_pad=0, bigendian=False, stamp_s=100.0,
               counts=None):
    """fields: list of (name, offset, datatype); values: name -> (N,) array (N = height*width)."""
    n = len(next(iter(values.values())))
    width = n // height
    end = ">" if bigendian else "<"
    counts = counts or {}
    dt = np.dtype({
        "names": [f[0] for f in fields],
        "formats": [(end + _PF_CODE[f[2]], (counts[f[0]],)) if counts.get(f[0], 1) > 1 else end + _PF_CODE[f[2]]
                    for f in fields],
        "offsets": [f[1] for f in fields],
        "itemsize": point_step,
    })
    rec = np.zeros(n, dtype=dt)
    for name, _, _ in fields:
        if counts.get(name, 1) > 1:
            rec[name][:, 0] = values[name]
            rec[name][:, 1:] = 77
        else:
            rec[name] = values[name]
    rows = rec.view(np.uint8).reshape(height, width * point_step)
    if row_pad:
        rows = np.hstack([rows, np.full((height, row_pad), 0xAB, dtype=np.uint8)])
    pfs = [factory.make("sensor_msgs/msg/PointField", name=nm, offset=off, datatype=dtc, count=counts.get(nm, 1))
           for nm, off, dtc in fields]
    return factory.make(
        "sensor_msgs/msg/PointCloud2", header=factory.make_header(stamp_s, "lidar"), height=height, width=width,
        fields=pfs, is_bigendian=bigendian, point_step=point_step, row_step=width * point_step + row_pad,
        data=np.ascontiguousarray(rows).reshape(-1), is_dense=False,
    )


def _rng():
    return np.random.default_rng(42)


# ---------------------------------------------------------------------------
# msgtypes
# ---------------------------------------------------------------------------
def test_split_stamp_carries_and_rounds():
    assert split_stamp(12.5) == (12, 500_000_000)
    assert split_stamp(0.9999999999) == (1, 0)
    assert split_stamp(-0.25) == (-1, 750_000_000)


def test_factories_produce_identical_cdr():
    rcl = _rclpy_factory()
    for f in (_ROSBAGS, rcl):
        assert f.make_header(1.5, "x").stamp.nanosec == 500_000_000
    kw = dict(height=2, width=3, encoding="mono8", step=3, data=np.arange(6, dtype=np.uint8))
    a = _ROSBAGS.make("sensor_msgs/msg/Image", header=_ROSBAGS.make_header(7.25, "cam"), **kw)
    b = rcl.make("sensor_msgs/msg/Image", header=rcl.make_header(7.25, "cam"), **kw)
    # CDR alignment padding bytes are unspecified, so compare the decoded content across implementations
    from_rcl = _ROSBAGS.deserialize(rcl.serialize(b, "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    from_rb = rcl.deserialize(_ROSBAGS.serialize(a, "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    for m in (from_rcl, from_rb):
        assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (7, 250_000_000, "cam")
        assert (m.height, m.width, m.encoding, m.step) == (2, 3, "mono8", 3)
        assert list(m.data) == list(range(6))


def test_rosbags_make_defaults_and_errors():
    ci = _ROSBAGS.make("sensor_msgs/msg/CameraInfo")
    assert ci.k.shape == (9,) and ci.d.size == 0 and ci.header.stamp.sec == 0 and ci.roi.width == 0
    with pytest.raises(ValueError, match="no field"):
        _ROSBAGS.make("sensor_msgs/msg/Image", nonsense=1)
    with pytest.raises(ValueError, match="unknown message type"):
        _ROSBAGS.make("sensor_msgs/msg/NoSuchThing")
    with pytest.raises(ValueError, match="exactly 9"):
        _ROSBAGS.make("sensor_msgs/msg/CameraInfo", k=[1, 2, 3])


# ---------------------------------------------------------------------------
# PointCloud2
# ---------------------------------------------------------------------------
def test_pointcloud_roundtrip_both_factories(factory):
    rng = _rng()
    n = 500
    xyz = rng.normal(size=(n, 3)) * 20
    inten = rng.random(n).astype(np.float32) * 100
    ring = (np.arange(n) % 32).astype(np.uint16)
    t = np.linspace(0, 0.1, n)
    msg = arrays_to_pointcloud2(xyz, factory, factory.make_header(5.0, "lidar"), intensity=inten, ring=ring, time_s=t)
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/PointCloud2")
    out = pointcloud2_to_arrays(msg)
    assert out["xyz"].dtype == np.float64 and out["xyz"].shape == (n, 3)
    np.testing.assert_allclose(out["xyz"], xyz.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_array_equal(out["intensity"], inten)
    np.testing.assert_array_equal(out["ring"], ring)
    np.testing.assert_allclose(out["time_s"], t, atol=1e-8)
    assert out["valid"].all() and np.array_equal(out["index"], np.arange(n))
    assert msg.is_dense and msg.point_step % 4 == 0


def test_pointcloud_xyz_only_and_empty(factory):
    msg = arrays_to_pointcloud2(np.zeros((0, 3)), factory, factory.make_header(1.0, "l"))
    out = pointcloud2_to_arrays(msg)
    assert out["xyz"].shape == (0, 3) and "intensity" not in out and "time_s" not in out


def test_pointcloud_padding_offsets_rowstep_organised(factory):
    rng = _rng()
    h, w = 4, 25
    n = h * w
    vals = {"ring": np.arange(n) % 16, "z": rng.normal(size=n), "x": rng.normal(size=n), "y": rng.normal(size=n),
            "intensity": rng.random(n) * 50}
    # shuffled offsets, gaps, 40-byte points with 16 bytes of padding, 12 bytes row padding
    fields = [("ring", 0, 4), ("z", 4, 7), ("x", 12, 8), ("y", 24, 7), ("intensity", 32, 7)]
    msg = make_cloud(factory, fields, vals, point_step=40, height=h, row_pad=12)
    out = pointcloud2_to_arrays(msg)
    assert tuple(out["shape"]) == (h, w)
    np.testing.assert_allclose(out["xyz"][:, 0], vals["x"], atol=0)  # float64 field: exact
    np.testing.assert_allclose(out["xyz"][:, 1], vals["y"].astype(np.float32))
    np.testing.assert_allclose(out["xyz"][:, 2], vals["z"].astype(np.float32))
    np.testing.assert_array_equal(out["ring"], vals["ring"])
    np.testing.assert_allclose(out["intensity"], vals["intensity"].astype(np.float32))


@pytest.mark.parametrize("datatype", [1, 2, 3, 4, 5, 6, 7, 8])
@pytest.mark.parametrize("bigendian", [False, True])
def test_pointcloud_all_datatypes_and_endianness(datatype, bigendian):
    n = 64
    rng = _rng()
    size = np.dtype(_PF_CODE[datatype]).itemsize
    inten = np.arange(n) % 100  # representable in every datatype
    xyz = rng.normal(size=(n, 3))
    fields = [("x", 0, 8), ("y", 8, 8), ("z", 16, 8), ("intensity", 24, datatype)]
    msg = make_cloud(_ROSBAGS, fields, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": inten},
                     point_step=24 + size + 3, bigendian=bigendian)
    out = pointcloud2_to_arrays(_roundtrip_cdr(_ROSBAGS, msg, "sensor_msgs/msg/PointCloud2"))
    np.testing.assert_array_equal(out["xyz"], xyz)
    np.testing.assert_array_equal(out["intensity"], inten.astype(np.float32))


def test_pointcloud_bigendian_float32_xyz_time_ring():
    n = 100
    rng = _rng()
    vals = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n),
            "ring": np.arange(n) % 64, "t": np.arange(n) * 1000}
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("t", 12, 6), ("ring", 16, 4)]
    out = pointcloud2_to_arrays(make_cloud(_ROSBAGS, fields, vals, point_step=20, bigendian=True))
    np.testing.assert_allclose(out["xyz"][:, 1], vals["y"].astype(np.float32))
    np.testing.assert_array_equal(out["ring"], vals["ring"])
    np.testing.assert_allclose(out["time_s"], np.arange(n) * 1e-6)  # uint32 ns -> s


def test_pointcloud_nan_points_dropped_or_kept(factory):
    rng = _rng()
    n = 200
    xyz = rng.normal(size=(n, 3))
    bad = np.zeros(n, bool)
    bad[[3, 50, 51, 199]] = True
    xyz[3, 0] = np.nan
    xyz[50, 2] = np.inf
    xyz[51] = np.nan
    xyz[199, 1] = -np.inf
    inten = np.arange(n, dtype=np.float32)
    msg = arrays_to_pointcloud2(xyz, factory, factory.make_header(1.0, "l"), intensity=inten)
    assert not msg.is_dense
    out = pointcloud2_to_arrays(msg)
    assert out["xyz"].shape == (n - 4, 3) and np.isfinite(out["xyz"]).all()
    np.testing.assert_array_equal(out["index"], np.flatnonzero(~bad))
    np.testing.assert_array_equal(out["intensity"], inten[~bad])  # fields stay aligned
    full = pointcloud2_to_arrays(msg, keep_nan=True)
    assert full["xyz"].shape == (n, 3)
    np.testing.assert_array_equal(full["valid"], ~bad)


def test_pointcloud_reflectivity_alias_and_priority():
    n = 10
    v = {"x": np.ones(n), "y": np.zeros(n), "z": np.zeros(n), "reflectivity": np.arange(n) * 3}
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("reflectivity", 12, 4)]
    out = pointcloud2_to_arrays(make_cloud(_ROSBAGS, fields, v, point_step=16))
    assert out["intensity"].dtype == np.float32
    np.testing.assert_array_equal(out["intensity"], np.arange(n) * 3)
    v["intensity"] = np.full(n, 9.0)
    fields.append(("intensity", 16, 7))
    out = pointcloud2_to_arrays(make_cloud(_ROSBAGS, fields, v, point_step=20))
    np.testing.assert_array_equal(out["intensity"], 9.0)


def test_pointcloud_missing_xyz_field_raises():
    v = {"x": np.ones(3), "y": np.ones(3), "intensity": np.ones(3)}
    msg = make_cloud(_ROSBAGS, [("x", 0, 7), ("y", 4, 7), ("intensity", 8, 7)], v, point_step=12)
    with pytest.raises(ValueError, match=r"no z field.*intensity"):
        pointcloud2_to_arrays(msg)


def test_pointcloud_short_buffer_raises():
    msg = arrays_to_pointcloud2(np.ones((10, 3)), _ROSBAGS, _ROSBAGS.make_header(1.0, "l"))
    msg.data = msg.data[:-5]
    with pytest.raises(ValueError, match="bytes"):
        pointcloud2_to_arrays(msg)


def test_pointcloud_count_gt1_uses_first_element():
    n = 5
    v = {"x": np.arange(n, dtype=float), "y": np.zeros(n), "z": np.zeros(n), "intensity": np.arange(n) + 0.5}
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)]
    msg = make_cloud(_ROSBAGS, fields, v, point_step=24, counts={"intensity": 3})
    out = pointcloud2_to_arrays(msg)
    np.testing.assert_array_equal(out["intensity"], v["intensity"].astype(np.float32))


@pytest.mark.parametrize("name,datatype,raw,expected_s", [
    ("t", 6, np.array([0, 50_000, 99_000_000]), np.array([0.0, 5e-5, 0.099])),           # Ouster uint32 ns
    ("time", 7, np.array([-0.05, 0.0, 0.049]), np.array([-0.05, 0.0, 0.049])),           # Velodyne float s
    ("offset_time", 6, np.array([0, 1000, 2000]), np.array([0.0, 1e-6, 2e-6])),          # Livox uint32 ns
    ("timestamp", 8, 1.7e9 + np.array([0.0, 0.01, 0.02]), np.array([0.0, 0.01, 0.02])),  # absolute epoch s
    ("time", 7, np.array([0.0, 2.5e6, 5e7]), np.array([0.0, 2.5e-3, 5e-2])),             # float ns (relative)
])
def test_pointcloud_time_units(name, datatype, raw, expected_s):
    n = raw.size
    v = {"x": np.ones(n), "y": np.ones(n), "z": np.ones(n), name: raw}
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), (name, 16, datatype)]
    msg = make_cloud(_ROSBAGS, fields, v, point_step=24, stamp_s=1.7e9)
    np.testing.assert_allclose(pointcloud2_to_arrays(msg)["time_s"], expected_s, atol=1e-6, rtol=1e-6)


def test_pointcloud_time_absolute_epoch_ns_float64():
    """Livox-style FLOAT64 absolute nanoseconds become seconds relative to header.stamp."""
    stamp_ns = 1_700_000_000_123_000_000
    raw = stamp_ns + np.array([0, 1_000_000, 90_000_000], dtype=np.int64)
    n = raw.size
    v = {"x": np.ones(n), "y": np.ones(n), "z": np.ones(n), "timestamp": raw.astype(np.float64)}
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("timestamp", 16, 8)]
    msg = make_cloud(_ROSBAGS, fields, v, point_step=24)
    msg.header = _ROSBAGS.make("std_msgs/msg/Header", stamp=_ROSBAGS.make_time_ns(stamp_ns), frame_id="l")
    # float64 holds epoch-ns to ~256 ns, hence the 1 us tolerance
    np.testing.assert_allclose(pointcloud2_to_arrays(msg)["time_s"], [0.0, 1e-3, 0.09], atol=1e-6)


# ---------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------
def _test_image(enc, h=7, w=5):
    rng = _rng()
    code, ch, _ = IMAGE_ENCODINGS[enc]
    shape = (h, w) if ch == 1 else (h, w, 3)
    if code == "f4":
        return rng.random(shape).astype(np.float32) * 10
    hi = 255 if code == "u1" else 65535
    return rng.integers(0, hi + 1, size=shape).astype(np.dtype(code))


@pytest.mark.parametrize("enc", list(IMAGE_ENCODINGS))
def test_image_roundtrip_all_encodings(enc, factory):
    arr = _test_image(enc)
    msg = array_to_image(arr, enc, factory, factory.make_header(3.0, "cam"))
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/Image")
    back = image_to_array(msg)
    assert back.dtype == arr.dtype and back.shape == arr.shape
    np.testing.assert_array_equal(back, arr)  # colour: BGR in, BGR out
    assert back.flags.owndata or back.base is None or back.base.flags.owndata


def test_image_rgb_channel_order_is_bgr_out():
    # one pure-red pixel in RGB byte order
    for enc, px in (("rgb8", [255, 0, 0]), ("rgba8", [255, 0, 0, 128]), ("bgr8", [0, 0, 255]),
                    ("bgra8", [0, 0, 255, 7])):
        msg = _ROSBAGS.make("sensor_msgs/msg/Image", height=1, width=1, encoding=enc, step=len(px),
                            data=np.array(px, np.uint8))
        np.testing.assert_array_equal(image_to_array(msg)[0, 0], [0, 0, 255], err_msg=enc)


@pytest.mark.parametrize("enc", ["mono8", "mono16", "rgb8", "32FC1"])
def test_image_row_padding(enc):
    arr = _test_image(enc, h=6, w=9)
    packed = array_to_image(arr, enc, _ROSBAGS, _ROSBAGS.make_header(1.0, "c"))
    rows = packed.data.reshape(packed.height, packed.step)
    padded = np.hstack([rows, np.full((rows.shape[0], 11), 0xEE, np.uint8)])
    msg = _ROSBAGS.make("sensor_msgs/msg/Image", height=packed.height, width=packed.width, encoding=enc,
                        step=packed.step + 11, data=padded.reshape(-1))
    np.testing.assert_array_equal(image_to_array(msg), arr)


def test_image_is_copy_not_view():
    arr = _test_image("mono8")
    ref = arr.copy()
    msg = array_to_image(arr, "mono8", _ROSBAGS, _ROSBAGS.make_header(1.0, "c"))
    arr[:] = 1  # the message owns its data ...
    np.testing.assert_array_equal(image_to_array(msg), ref)
    out = image_to_array(msg)
    msg.data[:] = 0  # ... and the decoded array does not alias the message
    np.testing.assert_array_equal(out, ref)


def test_image_bigendian_16bit():
    vals = np.array([[1, 256, 65535], [4660, 0, 43981]], dtype=np.uint16)
    msg = _ROSBAGS.make("sensor_msgs/msg/Image", height=2, width=3, encoding="16UC1", is_bigendian=1, step=6,
                        data=vals.astype(">u2").view(np.uint8).reshape(-1))
    out = image_to_array(msg)
    assert out.dtype == np.uint16 and out.dtype.isnative
    np.testing.assert_array_equal(out, vals)


def test_image_unknown_encoding_message():
    msg = _ROSBAGS.make("sensor_msgs/msg/Image", height=1, width=1, encoding="yuv422", step=2,
                        data=np.zeros(2, np.uint8))
    with pytest.raises(ValueError, match=r"'yuv422'.*mono8.*32FC1"):
        image_to_array(msg)
    with pytest.raises(ValueError, match="yuv422"):
        array_to_image(np.zeros((2, 2), np.uint8), "yuv422", _ROSBAGS, _ROSBAGS.make_header(0.0, ""))


def test_array_to_image_rejects_out_of_range():
    with pytest.raises(ValueError, match="range"):
        array_to_image(np.array([[300]]), "mono8", _ROSBAGS, _ROSBAGS.make_header(0.0, ""))
    with pytest.raises(ValueError, match="integer"):
        array_to_image(np.array([[1.5]]), "16UC1", _ROSBAGS, _ROSBAGS.make_header(0.0, ""))


def test_depth_16uc1_millimetres(factory):
    mm = np.array([[0, 1000, 1500], [65535, 1, 0]], dtype=np.uint16)
    msg = array_to_image(mm, "16UC1", factory, factory.make_header(1.0, "cam"))
    d = depth_image_to_m(msg)
    assert d.dtype == np.float32 and d.shape == (2, 3)
    assert np.isnan(d[0, 0]) and np.isnan(d[1, 2])
    np.testing.assert_allclose(d[0, 1:], [1.0, 1.5], rtol=1e-6)
    np.testing.assert_allclose(d[1, :2], [65.535, 0.001], rtol=1e-6)


def test_depth_32fc1_metres():
    m = np.array([[0.0, 2.5, np.nan], [np.inf, -1.0, 0.3]], dtype=np.float32)
    d = depth_image_to_m(array_to_image(m, "32FC1", _ROSBAGS, _ROSBAGS.make_header(1.0, "cam")))
    np.testing.assert_array_equal(np.isnan(d), [[True, False, True], [True, True, False]])
    np.testing.assert_allclose(d[0, 1], 2.5) and np.testing.assert_allclose(d[1, 2], 0.3, rtol=1e-6)


def test_depth_wrong_encoding():
    msg = array_to_image(np.zeros((2, 2, 3), np.uint8), "rgb8", _ROSBAGS, _ROSBAGS.make_header(1.0, "c"))
    with pytest.raises(ValueError, match=r"depth image must be 16UC1 \(mm\) or 32FC1 \(m\), got rgb8"):
        depth_image_to_m(msg)


# ---------------------------------------------------------------------------
# CameraInfo
# ---------------------------------------------------------------------------
_CASES = [
    ("plumb_bob", [-0.28, 0.07, 1e-3, -5e-4, 0.0]),
    ("rational_polynomial", [0.1, -0.05, 1e-4, 2e-4, 0.01, 0.12, -0.03, 0.005]),
    ("equidistant", [0.05, -0.01, 0.002, -0.0005]),
]


@pytest.mark.parametrize("dm,D", _CASES)
def test_camera_info_roundtrip(dm, D, factory):
    from lidar_cam_calib.core.camera import CameraModel

    K = np.array([[600.0, 0, 320.5], [0, 605.0, 241.0], [0, 0, 1]])
    model = CameraModel(640, 480, K, np.array(D), dm)
    msg = camera_model_to_camera_info(model, factory, factory.make_header(2.0, "cam_optical"))
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/CameraInfo")
    back = camera_info_to_model(msg)
    assert (back.width, back.height, back.distortion_model) == (640, 480, dm)
    np.testing.assert_array_equal(back.K, K)
    np.testing.assert_array_equal(back.D, D)
    pts = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(back.project(pts)[0], model.project(pts)[0], atol=1e-9)
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], K)


def test_camera_info_empty_model_pinhole_and_inferred():
    K = [500.0, 0, 100, 0, 500, 80, 0, 0, 1]
    msg = _ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=200, height=160, k=K, distortion_model="", d=[])
    m = camera_info_to_model(msg)
    assert m.distortion_model in ("", "none") and not m.is_distorted
    msg = _ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=200, height=160, k=K, distortion_model="",
                        d=[0.1, 0, 0, 0, 0])
    assert camera_info_to_model(msg).distortion_model == "plumb_bob"
    # a pinhole model written out is plumb_bob with zeros and projects identically
    out = camera_model_to_camera_info(m, _ROSBAGS, _ROSBAGS.make_header(0.0, "c"))
    assert out.distortion_model == "plumb_bob" and not np.any(out.d)
    # short plumb_bob D is zero-padded
    msg = _ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=200, height=160, k=K, distortion_model="plumb_bob",
                        d=[0.1, 0.2])
    np.testing.assert_array_equal(camera_info_to_model(msg).D, [0.1, 0.2, 0, 0, 0])


def test_camera_info_errors():
    msg = _ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=640, height=480, distortion_model="plumb_bob")
    with pytest.raises(ValueError, match="all zeros.*uncalibrated"):
        camera_info_to_model(msg)
    K = [500.0, 0, 100, 0, 500, 80, 0, 0, 1]
    with pytest.raises(ValueError, match="0x480"):
        camera_info_to_model(_ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=0, height=480, k=K))
    with pytest.raises(ValueError, match="unsupported distortion_model 'weird'"):
        camera_info_to_model(_ROSBAGS.make("sensor_msgs/msg/CameraInfo", width=640, height=480, k=K,
                                           distortion_model="weird"))


# ---------------------------------------------------------------------------
# LaserScan
# ---------------------------------------------------------------------------
def test_laserscan_validity_and_points(factory):
    ranges = np.array([1.0, np.inf, np.nan, 0.0, 0.05, 2.0, 40.0, -1.0, 3.0])
    amin, inc = -0.4, 0.1
    msg = make_laserscan(ranges, amin, inc, 0.1, 30.0, factory, factory.make_header(9.0, "laser"),
                         intensities=np.arange(9), scan_time=0.1, time_increment=1e-4)
    msg = _roundtrip_cdr(factory, msg, "sensor_msgs/msg/LaserScan")
    assert abs(msg.angle_max - (amin + 8 * inc)) < 1e-6
    out = laserscan_to_points(msg)
    expected_valid = np.array([1, 0, 0, 0, 0, 1, 0, 0, 1], bool)
    np.testing.assert_array_equal(out["valid"], expected_valid)
    np.testing.assert_array_equal(out["index"], [0, 5, 8])
    ang = np.float32(amin) + np.arange(9) * np.float32(inc)
    np.testing.assert_allclose(out["angles"], ang, atol=1e-6)
    r = np.array([1.0, 2.0, 3.0])
    a = ang[[0, 5, 8]]
    np.testing.assert_allclose(out["xy"], np.c_[r * np.cos(a), r * np.sin(a)], atol=1e-6)
    np.testing.assert_allclose(out["time_s"][8], 8e-4, rtol=1e-5)
    np.testing.assert_array_equal(out["intensities"], np.arange(9))


def test_laserscan_all_invalid():
    msg = make_laserscan(np.full(5, np.inf), 0.0, 0.01, 0.1, 10.0, _ROSBAGS, _ROSBAGS.make_header(1.0, "l"))
    out = laserscan_to_points(msg)
    assert out["xy"].shape == (0, 2) and out["index"].size == 0 and not out["valid"].any()
    assert "intensities" not in out
