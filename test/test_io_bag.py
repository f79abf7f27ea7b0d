"""Tests for lidar_cam_calib.io.bag (rosbag2 MCAP write/read without ROS)."""
from __future__ import annotations

import numpy as np
import pytest

from lidar_cam_calib.io.bag import BagError, BagWriter, bag_topics, read_bag
from lidar_cam_calib.io.convert import (
    array_to_image,
    arrays_to_pointcloud2,
    image_to_array,
    laserscan_to_points,
    make_laserscan,
    pointcloud2_to_arrays,
)
from lidar_cam_calib.io.msgtypes import RosbagsFactory

F = RosbagsFactory()
T0 = 1_700_000_000_000_000_000


def _write_bag(path, n=20, img_size=(48, 64)):
    """Writes n scans, n images and n small clouds; returns the list of written (topic, stamp_ns)."""
    written = []
    with BagWriter(path) as bw:
        for i in range(n):
            t = T0 + i * 100_000_000
            scan = make_laserscan(np.full(90, 1.0 + i), -1.0, 0.02, 0.1, 30.0, F, F.make_header(t * 1e-9, "laser"))
            bw.write("/scan", "sensor_msgs/msg/LaserScan", t, scan)
            img = array_to_image(np.full(img_size, i, np.uint8), "mono8", F, F.make_header(t * 1e-9, "cam"))
            bw.write("/cam/image_raw", "sensor_msgs/msg/Image", t + 1000, img)
            cloud = arrays_to_pointcloud2(np.full((5, 3), float(i)), F, F.make_header(t * 1e-9, "lidar"))
            bw.write("/points", "sensor_msgs/msg/PointCloud2", t + 2000, cloud)
            written += [("/scan", t), ("/cam/image_raw", t + 1000), ("/points", t + 2000)]
    return written


def test_write_read_directory_roundtrip(tmp_path):
    bag = tmp_path / "bag1"
    written = _write_bag(bag)
    assert (bag / "metadata.yaml").is_file() and len(list(bag.glob("*.mcap"))) == 1
    recs = list(read_bag(bag))
    assert [(r.topic, r.stamp_ns) for r in recs] == written
    assert bag_topics(bag) == {"/scan": "sensor_msgs/msg/LaserScan", "/cam/image_raw": "sensor_msgs/msg/Image",
                               "/points": "sensor_msgs/msg/PointCloud2"}
    scans = [r for r in recs if r.topic == "/scan"]
    msg = F.deserialize(scans[3].raw, scans[3].typename)
    pts = laserscan_to_points(msg)
    assert pts["valid"].all() and np.allclose(np.hypot(*pts["xy"].T), 4.0)
    img = F.deserialize(recs[1].raw, recs[1].typename)
    assert image_to_array(img).shape == (48, 64) and image_to_array(img)[0, 0] == 0
    cloud = F.deserialize(recs[-1].raw, recs[-1].typename)
    np.testing.assert_array_equal(pointcloud2_to_arrays(cloud)["xyz"], 19.0)
    assert F.deserialize(scans[0].raw, "sensor_msgs/msg/LaserScan").header.stamp.sec == T0 // 10**9


def test_read_single_mcap_file_and_topic_filter(tmp_path):
    bag = tmp_path / "bag2"
    written = _write_bag(bag, n=5)
    mcap_file = next(bag.glob("*.mcap"))
    lone = tmp_path / "lone.mcap"
    lone.write_bytes(mcap_file.read_bytes())  # no metadata.yaml next to it
    assert [(r.topic, r.stamp_ns) for r in read_bag(lone)] == written
    assert set(bag_topics(lone)) == {"/scan", "/cam/image_raw", "/points"}
    only = list(read_bag(lone, topics=["/points"]))
    assert len(only) == 5 and all(r.typename == "sensor_msgs/msg/PointCloud2" for r in only)


def test_log_time_order_when_written_out_of_order(tmp_path):
    bag = tmp_path / "bag3"
    with BagWriter(bag) as bw:
        for t in (30, 10, 20):
            bw.write("/scan", "sensor_msgs/msg/LaserScan", T0 + t,
                     make_laserscan([1.0], 0.0, 0.1, 0.1, 5.0, F, F.make_header(1.0, "l")))
    assert [r.stamp_ns - T0 for r in read_bag(bag)] == [10, 20, 30]


def test_raw_bytes_and_qos_written(tmp_path):
    bag = tmp_path / "bag4"
    scan = make_laserscan([1.0, 2.0], 0.0, 0.1, 0.1, 5.0, F, F.make_header(1.0, "l"))
    raw = F.serialize(scan, "sensor_msgs/msg/LaserScan")
    with BagWriter(bag) as bw:
        bw.write("/scan", "sensor_msgs/msg/LaserScan", T0, raw)
        bw.write("/tf_static", "tf2_msgs/msg/TFMessage", T0, F.make("tf2_msgs/msg/TFMessage"))
        with pytest.raises(BagError, match="registered as"):
            bw.write("/scan", "sensor_msgs/msg/Image", T0, F.make("sensor_msgs/msg/Image"))
    recs = list(read_bag(bag))
    assert recs[0].raw == raw
    meta = (bag / "metadata.yaml").read_text()
    assert "transient_local" in meta.lower() or "durability: 1" in meta


def test_writer_refuses_existing_path(tmp_path):
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path).open()


def test_missing_and_empty_bags(tmp_path):
    with pytest.raises(BagError, match="not found"):
        read_bag(tmp_path / "nope")  # fails at the call, not on iteration
    with pytest.raises(BagError, match="no bag files"):
        read_bag(tmp_path)
    (tmp_path / "zero.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="empty"):
        read_bag(tmp_path / "zero.mcap")
    with pytest.raises(BagError, match="empty"):
        bag_topics(tmp_path / "zero.mcap")
    empty = tmp_path / "nomsgs"
    with BagWriter(empty):
        pass
    with pytest.raises(BagError, match="no messages"):
        list(read_bag(empty))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(BagError):
        list(read_bag(junk))


def test_truncated_bag_yields_complete_prefix_then_bag_error(tmp_path):
    bag = tmp_path / "bag5"
    # ~4 MB of images so that the 1 MiB chunks before the cut are complete
    written = _write_bag(bag, n=60, img_size=(240, 320))
    data = next(bag.glob("*.mcap")).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got = []
    with pytest.raises(BagError, match="truncated"):
        for rec in read_bag(cut):
            got.append((rec.topic, rec.stamp_ns))
    assert 0 < len(got) < len(written)
    assert got == written[: len(got)]  # a clean prefix: no partial or reordered message
    with pytest.raises(BagError, match="truncated"):
        bag_topics(cut)


def test_read_sqlite3_bag_directory(tmp_path):
    from rosbags.rosbag2 import Writer

    bag = tmp_path / "sq"
    scan = make_laserscan([1.0, 2.0], 0.0, 0.1, 0.1, 5.0, F, F.make_header(1.0, "l"))
    with Writer(bag, version=9) as w:  # default storage: sqlite3
        conn = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=F.typestore)
        for i in range(3):
            w.write(conn, T0 + i, F.serialize(scan, "sensor_msgs/msg/LaserScan"))
    recs = list(read_bag(bag))
    assert [r.stamp_ns - T0 for r in recs] == [0, 1, 2] and recs[0].typename == "sensor_msgs/msg/LaserScan"
    assert bag_topics(bag) == {"/scan": "sensor_msgs/msg/LaserScan"}
