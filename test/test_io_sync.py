"""Tests for lidar_cam_calib.io.sync (approximate-time matching)."""
from __future__ import annotations

import types

import numpy as np
import pytest

from lidar_cam_calib.io.convert import stamp_to_s as to_seconds
from lidar_cam_calib.io.sync import ApproxTimeSync


def _feed(sync, events):
    out = []
    for topic, stamp, item in events:
        out.extend(sync.push(topic, stamp, item))
    return out


def _interleave(streams):
    """streams: topic -> list of (arrival_time, stamp); returns events sorted by arrival."""
    ev = [(arr, topic, st) for topic, lst in streams.items() for arr, st in lst]
    ev.sort(key=lambda e: (e[0], e[1]))
    return [(topic, st, (topic, st)) for _, topic, st in ev]


def test_to_seconds_duck_typed():
    t = types.SimpleNamespace(sec=12, nanosec=500_000_000)
    assert to_seconds(t) == 12.5
    assert to_seconds(types.SimpleNamespace(stamp=t, frame_id="x")) == 12.5
    assert to_seconds(3.25) == 3.25


def test_two_streams_jitter_each_set_once():
    rng = np.random.default_rng(1)
    cam = [(0.1 * i, 0.1 * i + rng.uniform(-0.004, 0.004)) for i in range(50)]      # 10 Hz
    lidar = [(0.1 * i + 0.02, 0.1 * i + 0.01 + rng.uniform(-0.004, 0.004)) for i in range(50)]
    sync = ApproxTimeSync(["/cam", "/lidar"], slop_s=0.03)
    sets = _feed(sync, _interleave({"/cam": cam, "/lidar": lidar}))
    assert len(sets) == 50
    for i, (c, li) in enumerate(sets):
        assert c[0] == "/cam" and li[0] == "/lidar"  # ordered as topics
        assert c[1] == cam[i][1] and li[1] == lidar[i][1]
        assert abs(c[1] - li[1]) <= 0.03
    assert sync.emitted == 50 and sync.dropped_out_of_order == 0


def test_three_streams_different_rates():
    cam = [(t, t) for t in np.arange(0, 3, 1 / 15)]         # 15 Hz
    lidar = [(t, t + 0.003) for t in np.arange(0, 3, 0.1)]  # 10 Hz
    imu = [(t, t) for t in np.arange(0, 3, 0.01)]            # 100 Hz
    sync = ApproxTimeSync(["cam", "lidar", "imu"], slop_s=0.01)
    sets = _feed(sync, _interleave({"cam": cam, "lidar": lidar, "imu": imu}))
    stamps = np.array([[s[1] for s in st] for st in sets])
    assert len(sets) >= 9  # lidar/cam coincide every 0.2 s
    assert np.all(stamps.max(1) - stamps.min(1) <= 0.01 + 1e-12)
    for col in range(3):
        assert np.all(np.diff(stamps[:, col]) > 0)  # nothing reused, monotone


def test_unmatched_items_discarded_and_counted():
    sync = ApproxTimeSync(["a", "b"], slop_s=0.01)
    assert sync.push("a", 1.00, "a1") == []
    assert sync.push("b", 1.50, "b1") == []  # a1 can never match now
    assert sync.dropped_unmatched == 1 and sync.pending() == {"a": 0, "b": 1}
    assert sync.push("a", 1.505, "a2") == [("a2", "b1")]


def test_prefers_closer_queued_candidate():
    sync = ApproxTimeSync(["a", "b"], slop_s=0.05)
    sync.push("a", 1.00, "a1")
    sync.push("a", 1.03, "a2")
    assert sync.push("b", 1.031, "b1") == [("a2", "b1")]


def test_out_of_order_dropped_and_counted():
    sync = ApproxTimeSync(["a", "b"], slop_s=0.02)
    assert sync.push("a", 2.0, "a2") == []
    assert sync.push("b", 2.005, "b2") == [("a2", "b2")]
    assert sync.push("a", 1.9, "old") == []      # older than the last emitted set
    assert sync.push("b", 2.005, "dup") == []    # same stamp as the emitted one
    assert sync.dropped_out_of_order == 2
    assert sync.push("b", 2.10, "b3") == []
    assert sync.push("b", 2.10, "b3dup") == []   # duplicate of a queued stamp
    assert sync.dropped_out_of_order == 3
    # late but newer than what was emitted is accepted and sorted into the queue
    assert sync.push("b", 2.05, "b_late") == []
    assert sync.push("a", 2.052, "a3") == [("a3", "b_late")]


def test_bounded_queue_overflow():
    sync = ApproxTimeSync(["a", "b"], slop_s=0.001, queue_size=5)
    for i in range(12):
        sync.push("a", float(i), i)
    assert sync.pending()["a"] == 5 and sync.dropped_overflow == 7
    assert sync.push("a", 5.0, "x") == []  # below the overflow watermark
    assert sync.dropped_out_of_order == 1
    assert sync.push("b", 9.0, "b9") == [(9, "b9")]


def test_deterministic_replay():
    rng = np.random.default_rng(7)
    events = [(("a", "b", "c")[int(rng.integers(3))], float(rng.uniform(0, 5)), i) for i in range(600)]
    s1, s2 = ApproxTimeSync(["a", "b", "c"], 0.02), ApproxTimeSync(["a", "b", "c"], 0.02)
    out1, out2 = _feed(s1, events), _feed(s2, events)
    assert out1 == out2 and len(out1) > 0
    assert s1.dropped_out_of_order == s2.dropped_out_of_order > 0
    used = [x for st in out1 for x in st]
    assert len(used) == len(set(used))  # every item at most once


def test_single_topic_passthrough_and_errors():
    sync = ApproxTimeSync(["only"], slop_s=0.0)
    assert sync.push("only", 1.0, "x") == [("x",)]
    with pytest.raises(ValueError, match="unknown topic"):
        sync.push("other", 1.0, "y")
    with pytest.raises(ValueError, match="duplicate"):
        ApproxTimeSync(["a", "a"], 0.1)
    with pytest.raises(ValueError):
        ApproxTimeSync(["a"], -1.0)
