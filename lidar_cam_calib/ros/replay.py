"""Lossless, deterministic replay of a rosbag2 MCAP bag through a real node.

The node runs as its own process (exactly what ``ros2 run`` starts) with
``replay_ack:=true`` and reliable inputs; this process plays the bag's raw CDR
messages over DDS on loopback in log-time order, one at a time, and waits for
the node's ``~/ack`` counter before sending the next. Nothing is dropped and
the node sees the same sequence whatever the machine's speed.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from typing import Callable

from .env import apply_loopback_env, loopback_env
from ..core.result import CalibrationResult
from ..io.bag import BagError, bag_topics, read_bag

NODE_MODULES = {"lrf": ("lidar_cam_calib.ros.lrf_node", "lrf_calib_node")}


class ReplayError(RuntimeError):
    pass


@dataclasses.dataclass
class ReplayOutcome:
    result: CalibrationResult | None
    status: dict
    messages_sent: int
    messages_in_bag_topics: dict
    bag_error: str = ""
    node_returncode: int | None = None
    node_log: str = ""
    wall_time_s: float = 0.0


def _msg_class(typename: str):
    pkg, kind, name = typename.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def replay(method: str, bag_path: str, params_file: str | None = None, output_path: str | None = None,
           overlay_path: str | None = None, extra_params: dict | None = None, domain_id: int | None = None,
           log: Callable[[str], None] = print, message_timeout_s: float = 60.0,
           startup_timeout_s: float = 30.0) -> ReplayOutcome:
    """Play ``bag_path`` through the ``method`` node; return its final result."""
    if method not in NODE_MODULES:
        raise ReplayError(f"unknown method {method!r}; available: {', '.join(NODE_MODULES)}")
    if not os.path.exists(bag_path):
        raise ReplayError(f"bag not found: {bag_path}")
    try:
        topics = bag_topics(bag_path)
    except BagError as e:
        raise ReplayError(str(e)) from e
    if domain_id is None:
        domain_id = 100 + os.getpid() % 100
    module, node_name = NODE_MODULES[method]
    t_start = time.monotonic()

    params = {"replay_ack": True, "input_reliability": "reliable", "input_queue_depth": 1000}
    if output_path is not None:
        params["output_path"] = output_path
    if overlay_path is not None:
        params["overlay_path"] = overlay_path
    params.update(extra_params or {})
    cmd = [sys.executable, "-m", module, "--ros-args", "--disable-external-lib-logs"]
    if params_file:
        if not os.path.isfile(params_file):
            raise ReplayError(f"params file not found: {params_file}")
        cmd += ["--params-file", params_file]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={_param_literal(v)}"]

    apply_loopback_env(domain_id)
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String, UInt64

    log_file = tempfile.NamedTemporaryFile(prefix=f"{node_name}_", suffix=".log", delete=False)
    proc = subprocess.Popen(cmd, env=loopback_env(domain_id), stdout=log_file, stderr=subprocess.STDOUT)
    context = rclpy.Context()
    rclpy.init(context=context)
    player = Node("lidar_cam_calib_player", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(player)
    latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    state = {"ack": -1, "yaml": None, "status": {}}
    player.create_subscription(UInt64, f"/{node_name}/ack", lambda m: state.__setitem__("ack", int(m.data)), latched)
    player.create_subscription(String, f"/{node_name}/result_yaml",
                               lambda m: state.__setitem__("yaml", m.data), latched)
    player.create_subscription(String, f"/{node_name}/status",
                               lambda m: state.__setitem__("status", json.loads(m.data)), 50)

    def spin_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not pred():
            if proc.poll() is not None:
                raise ReplayError(f"node exited with code {proc.returncode} while waiting for {what}:\n"
                                  + _tail(log_file.name))
            if time.monotonic() > deadline:
                raise ReplayError(f"timed out after {timeout_s:.0f} s waiting for {what}:\n" + _tail(log_file.name))
            executor.spin_once(timeout_sec=0.01)

    outcome = ReplayOutcome(None, {}, 0, {})
    try:
        spin_until(lambda: state["ack"] >= 0, startup_timeout_s, f"{node_name} to start")
        # Which bag topics does the node subscribe to? Ask the graph until the
        # answer has been stable for half a second (discovery is incremental).
        wanted: dict[str, str] = {}
        stable_since = time.monotonic()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            now = {t: ty for t, ty in topics.items()
                   if any(i.node_name == node_name for i in player.get_subscriptions_info_by_topic(t))}
            if now != wanted:
                wanted, stable_since = now, time.monotonic()
            elif wanted and time.monotonic() - stable_since > 0.5:
                break
        if not wanted:
            raise ReplayError(f"{node_name} subscribes to none of the bag's topics {sorted(topics)}; "
                              "set its *_topic parameters with --params")
        qos = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        pubs = {t: player.create_publisher(_msg_class(ty), t, qos) for t, ty in wanted.items()}
        spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), startup_timeout_s,
                   "the node's subscriptions to match")
        log(f"replaying {bag_path}: topics {', '.join(sorted(wanted))} -> {node_name}")
        counts = {t: 0 for t in wanted}
        sent = 0
        last_report = time.monotonic()
        try:
            for rec in read_bag(bag_path):
                pub = pubs.get(rec.topic)
                if pub is None:
                    continue
                pub.publish(bytes(rec.raw))
                sent += 1
                counts[rec.topic] += 1
                spin_until(lambda: state["ack"] >= sent, message_timeout_s, f"ack of message {sent}")
                if time.monotonic() - last_report > 2.0:
                    st = state["status"]
                    log(f"  {sent} messages; observations {st.get('observations', '?')}; "
                        f"{st.get('last_reason', '')}")
                    last_report = time.monotonic()
        except BagError as e:
            outcome.bag_error = str(e)
            log(f"bag error after {sent} messages: {e}")
        # Let the latched result/status arrive.
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        outcome.messages_sent = sent
        outcome.messages_in_bag_topics = counts
        outcome.status = state["status"]
        if state["yaml"]:
            outcome.result = CalibrationResult.from_yaml(state["yaml"])
    finally:
        executor.shutdown()
        player.destroy_node()
        rclpy.shutdown(context=context)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log_file.close()
        outcome.node_returncode = proc.returncode
        outcome.node_log = _tail(log_file.name, 4000)
        try:
            os.unlink(log_file.name)
        except OSError:
            pass
        outcome.wall_time_s = time.monotonic() - t_start
    return outcome


def _param_literal(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v) if (v == "" or any(c in v for c in " :,[]{}#")) else v
    return str(v)


def _tail(path: str, n: int = 2000) -> str:
    try:
        with open(path, "r", encoding="utf-8", errors="replace") as f:
            return f.read()[-n:]
    except OSError:
        return ""
