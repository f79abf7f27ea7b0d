"""Lossless, deterministic replay of a rosbag2 MCAP bag through a real node.

The node runs as its own process (exactly what ``ros2 run`` starts) with
``replay_ack:=true`` and reliable inputs, in a namespace of its own
(``/lcc_replay_<pid>_<n>``) with every bag topic remapped into it, so a
replay talks only to the node it started: two replays on one domain, or a
live node of the same name beside them, never see each other's messages.
The node announces its inputs (resolved topic and type) in its latched
``~/status``; this process checks them against the bag (a wrong type is
said at once), plays the bag's raw CDR messages in log-time order, one at a
time, and waits for the node's ``~/ack`` counter (published after the work
the message caused) before sending the next. Nothing is dropped and the node
sees the same sequence whatever the machine's speed.
"""
from __future__ import annotations

import dataclasses
import importlib
import itertools
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from typing import Callable

from .. import methods
from ..core.calibrator import collected_count
from ..core.result import CalibrationSet
from ..io.bag import BagError, bag_message_counts, bag_topics, read_bag
from .env import apply_loopback_env, loopback_env

_counter = itertools.count()


class ReplayError(RuntimeError):
    pass


@dataclasses.dataclass
class ReplayOutcome:
    result: CalibrationSet | None          # the calibration in effect at the end (= the file)
    status: dict
    messages_sent: int
    messages_in_bag_topics: dict
    bag_error: str = ""
    node_returncode: int | None = None
    node_log: str = ""
    wall_time_s: float = 0.0
    namespace: str = ""


def _msg_class(typename: str):
    pkg, kind, name = typename.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def default_domain_id() -> int:
    """ROS_DOMAIN_ID as every ROS tool reads it (0 when unset)."""
    v = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not v:
        return 0
    try:
        d = int(v)
    except ValueError:
        raise ReplayError(f"ROS_DOMAIN_ID={v!r} is not a number") from None
    if not 0 <= d <= 232:
        raise ReplayError(f"ROS_DOMAIN_ID={d} is outside 0..232")
    return d


def scan_topics(bag_path: str) -> tuple[dict, str]:
    """Topic -> type of a bag; for a bag without a summary (truncated), by
    reading what can be read. Returns (topics, the read error or '')."""
    try:
        return bag_topics(bag_path), ""
    except BagError as first:
        topics: dict = {}
        try:
            for rec in read_bag(bag_path):
                topics.setdefault(rec.topic, rec.typename)
        except BagError as e:
            if not topics:
                raise ReplayError(str(e) if "no messages" in str(e) else f"{first}") from e
            return topics, str(e)
        return topics, ""


def replay(method: str, bag_path: str, params_file: str | None = None, output_path: str | None = None,
           overlay_path: str | None = None, extra_params: dict | None = None, domain_id: int | None = None,
           log: Callable[[str], None] = print, message_timeout_s: float = 300.0,
           startup_timeout_s: float = 30.0, progress: bool | None = None) -> ReplayOutcome:
    """Play ``bag_path`` through the ``method`` node; return the calibration
    in effect at the end and the node's last status."""
    try:
        spec = methods.get(method)
    except KeyError as e:
        raise ReplayError(str(e.args[0])) from None
    if not os.path.exists(bag_path):
        raise ReplayError(f"bag not found: {bag_path}")
    topics, read_error = scan_topics(bag_path)
    if not topics:
        raise ReplayError(f"bag {bag_path} contains no messages")
    if domain_id is None:
        domain_id = default_domain_id()
    if progress is None:
        progress = sys.stderr.isatty()
    ns = f"/lcc_replay_{os.getpid()}_{next(_counter)}"
    node_name = spec.executable
    base = f"{ns}/{node_name}"
    t_start = time.monotonic()

    params = {"replay_ack": True, "input_reliability": "reliable", "input_queue_depth": 1000}
    if output_path is not None:
        params["output_path"] = output_path
    if overlay_path is not None:
        params["overlay_path"] = overlay_path
    params.update(extra_params or {})
    cmd = [sys.executable, "-m", spec.node_module, "--ros-args", "--disable-external-lib-logs",
           "-r", f"__ns:={ns}"]
    for t in sorted(topics):
        cmd += ["-r", f"{t}:={ns}/in{t}"]
    cmd += ["-r", f"/tf_static:={ns}/tf_static"]
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
    rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    player = Node(f"lcc_player_{os.getpid()}_{next(_counter)}", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(player)
    from .node_base import LATCHED as latched
    state = {"ack": -1, "yaml": None, "status": {}}
    player.create_subscription(UInt64, f"{base}/ack", lambda m: state.__setitem__("ack", int(m.data)), latched)
    player.create_subscription(String, f"{base}/result_yaml", lambda m: state.__setitem__("yaml", m.data), latched)
    player.create_subscription(String, f"{base}/status",
                               lambda m: state.__setitem__("status", json.loads(m.data)), latched)

    def spin_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not pred():
            if proc.poll() is not None:
                raise ReplayError(_node_exit_text(proc.returncode, what, log_file.name))
            if time.monotonic() > deadline:
                raise ReplayError(f"timed out after {timeout_s:.0f} s waiting for {what}:\n" + _tail(log_file.name))
            executor.spin_once(timeout_sec=0.01)

    outcome = ReplayOutcome(None, {}, 0, {}, namespace=ns)
    try:
        spin_until(lambda: state["ack"] >= 0 and state["status"].get("inputs") is not None, startup_timeout_s,
                   f"{node_name} to start")
        pubs = _match_inputs(player, state["status"]["inputs"], topics, ns, node_name)
        qos = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        pubs = {t: player.create_publisher(_msg_class(ty), f"{ns}/in{t}", qos) for t, ty in pubs.items()}
        spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), startup_timeout_s,
                   "the node's subscriptions to match")
        log(f"replaying {bag_path}: topics {', '.join(sorted(pubs))} -> {base}")
        counts_in_bag = bag_message_counts(bag_path)
        total = sum(counts_in_bag.get(t, 0) for t in pubs) or None
        counts = {t: 0 for t in pubs}
        sent = 0
        last_report = 0.0
        try:
            for rec in read_bag(bag_path):
                pub = pubs.get(rec.topic)
                if pub is None:
                    continue
                pub.publish(bytes(rec.raw))
                sent += 1
                counts[rec.topic] += 1
                spin_until(lambda n=sent: state["ack"] >= n, message_timeout_s, f"ack of message {sent}")
                if progress and time.monotonic() - last_report > 0.25:
                    st = state["status"]
                    sys.stderr.write(f"\r  sent {sent}{'/' + str(total) if total else ''} messages; "
                                     f"observations {collected_count(st)}   ")
                    sys.stderr.flush()
                    last_report = time.monotonic()
        except BagError as e:
            outcome.bag_error = str(e)
        if progress:
            sys.stderr.write("\n")
        if read_error and not outcome.bag_error:
            outcome.bag_error = read_error
        if outcome.bag_error:
            log(f"bag error after {sent} messages: {outcome.bag_error}")
        # the final status (and latched result) of the last message's work
        spin_until(lambda n=sent: state["status"].get("inputs_processed", -1) >= n, 10.0, "the final status")
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        outcome.messages_sent = sent
        outcome.messages_in_bag_topics = counts
        outcome.status = state["status"]
        if state["yaml"]:
            outcome.result = CalibrationSet.from_yaml(state["yaml"])
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


def _match_inputs(player, inputs: list, topics: dict, ns: str, node_name: str) -> dict:
    """Bag topic -> type for every input of the node; a type mismatch or a
    required input with no topic in the bag is an error, said at once."""
    prefix = f"{ns}/in"
    wanted: dict = {}
    missing = []
    for inp in inputs:
        topic = inp.get("topic", "")
        bag_topic = topic[len(prefix):] if topic.startswith(prefix) else None
        if bag_topic is None or bag_topic not in topics:
            if inp.get("required", True):
                missing.append(f"{inp['name']} ({inp['type']} on {topic.replace(ns, '') or 'no topic'})")
            continue
        have = topics[bag_topic]
        if have.replace("/msg/", "/") != inp["type"].replace("/msg/", "/"):
            raise ReplayError(f"topic {bag_topic} in the bag holds {have}, but {node_name} reads {inp['type']} "
                              f"there (its {inp['name']} input): point the node's topic parameter at the right "
                              "topic with --params")
        wanted[bag_topic] = have
    if missing:
        raise ReplayError(f"the bag has no topic for {node_name}'s input(s) {', '.join(missing)}; the bag's topics: "
                          + ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items()))
                          + ". Set the node's *_topic parameters with --params")
    return wanted


def _node_exit_text(code: int, what: str, log_path: str) -> str:
    tail = _tail(log_path).strip()
    errors = [ln for ln in tail.splitlines() if ln.startswith("error:")]
    if errors:
        return errors[-1][len("error: "):]
    return f"node exited with code {code} while waiting for {what}:\n{tail}"


def _param_literal(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_param_literal(x) for x in v) + "]"
    if isinstance(v, str):
        return json.dumps(v) if (v == "" or any(c in v for c in " :,[]{}#'\"")) else v
    return str(v)


def _tail(path: str, n: int = 2000) -> str:
    try:
        with open(path, "r", encoding="utf-8", errors="replace") as f:
            return f.read()[-n:]
    except OSError:
        return ""
