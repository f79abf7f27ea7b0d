"""Node base class shared by every calibration node (the only rclpy layer).

The base owns the whole collect / fit / adopt / publish cycle; a method node
only declares its inputs (:meth:`CalibNodeBase.add_input`), turns messages
into its frame type and hands frames to :meth:`CalibNodeBase.submit_frame`.

Threads: input callbacks (one mutually exclusive group, in arrival order),
services and the 1 Hz status timer run on a multi-threaded executor; feature
extraction, fitting, file writing and overlays run on one worker thread, so
no input callback ever waits for a fit. In lock-step replay
(``replay_ack:=true``) the ack of a message is published only after the work
it caused is done, which keeps replay deterministic.

Outputs (the same calibration everywhere: the one in effect):
  ~/transform    geometry_msgs/TransformStamped per child frame, transient-local
  /tf_static     tf2_msgs/TFMessage, transient-local, one transform per child
                 frame, replaced on every adopted result (when tf2_msgs exists)
  ~/result_yaml  std_msgs/String, transient-local; the same YAML as the file
  ~/status       std_msgs/String (JSON), transient-local, on events and at 1 Hz
  ~/overlay      sensor_msgs/Image (bgr8), one per camera (``~/overlay/<name>``
                 for multi-camera methods)
  ~/ack          std_msgs/UInt64 (only with replay_ack): inputs processed
Services: ~/recalibrate, ~/capture (std_srvs/Trigger).
"""
from __future__ import annotations

import collections
import dataclasses
import json
import math
import os
import queue
import re
import threading
import time
import traceback
import zlib
from typing import Any, Callable

import numpy as np
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt64
from std_srvs.srv import Trigger

from ..core.calibrator import allowed_text, check_value, collected_count, validate_config
from ..core.errors import CalibError, ConfigError, InputError
from ..core.result import (CalibrationResult, CalibrationSet, ResultFileError, check_output_path, to_plain,
                           write_atomic)
from ..io.convert import array_to_image, stamp_to_s
from ..io.msgtypes import RclpyFactory

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def input_qos(reliability: str, depth: int) -> QoSProfile:
    """Subscription QoS for sensor inputs: 'best_effort' (matches any driver,
    the usual sensor-data QoS) or 'reliable' (lossless replay)."""
    rel = ReliabilityPolicy.RELIABLE if reliability == "reliable" else qos_profile_sensor_data.reliability
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=rel,
                      durability=DurabilityPolicy.VOLATILE)


@dataclasses.dataclass
class _Param:
    name: str
    default: Any
    meta: dict
    kind: str           # 'base' | 'config' | 'input' | 'node'


@dataclasses.dataclass
class _Input:
    name: str
    msg_type: Any
    param: str
    required: bool
    callback: Callable[[Any], None]
    subscription: Any = None


def _meta(help: str, range: tuple | None = None, choices: tuple | None = None, length: Any = None,
          exclusive_min: bool = False, read_only: bool = False) -> dict:
    return {"help": help, "range": range, "choices": choices, "length": length,
            "exclusive_min": exclusive_min, "param": True, "read_only": read_only}


# Parameters every node has. Files, topics and frames are read-only after
# start-up: anyone on the domain can set parameters.
BASE_PARAMS: tuple = (
    ("output_path", "", _meta("Where the result YAML is written (atomic, previous kept as .bak, mode as any "
                              "file under the umask). Empty: no file. Default ~/.ros/lidar_cam_calib/<method>.yaml.",
                              read_only=True)),
    ("overlay_path", "", _meta("If set, every overlay image is also written there as PNG (multi-camera: "
                               "<stem>_<camera>.png).", read_only=True)),
    ("force_overwrite", False, _meta("Replace the result file even when it holds a better calibration, another "
                                     "method's or another frame pair's.", read_only=True)),
    ("publish_tf_static", True, _meta("Also publish the calibration in effect on /tf_static.", read_only=True)),
    ("input_reliability", "best_effort", _meta("QoS reliability of the sensor subscriptions: best_effort "
                                               "(matches any driver) or reliable (lossless replay).",
                                               choices=("best_effort", "reliable"), read_only=True)),
    ("input_queue_depth", 10, _meta("Queue depth of the sensor subscriptions.", range=(1, 10000), read_only=True)),
    ("replay_ack", False, _meta("Publish ~/ack (inputs processed) after the work each input caused; used by "
                                "lock-step replay.", read_only=True)),
    ("parent_frame", "", _meta("Override the range sensor frame id (default: from the messages).", read_only=True)),
    ("child_frame", "", _meta("Override the camera optical frame id (default: from the messages; single-camera "
                              "methods only).", read_only=True)),
    ("time_jump_s", 1.0, _meta("A stamp this much older than the newest one of its input means time went back "
                               "(bag loop, simulated time restart): the collection starts again.",
                               range=(0.0, 1e6), exclusive_min=True)),
    ("status_period_s", 1.0, _meta("~/status is republished this often (and on every event).",
                                   range=(0.05, 3600.0), read_only=True)),
)


def _descriptor(p: _Param) -> ParameterDescriptor:
    d = ParameterDescriptor(description=f"{p.meta['help']} Allowed: {allowed_text(p.meta)}.",
                            read_only=bool(p.meta.get("read_only")))
    v = p.default
    rg = p.meta.get("range")
    if isinstance(v, float) or (isinstance(v, (list, tuple)) and v and isinstance(v[0], float)):
        # ints given for floats (-p x:=1) are accepted and widened; our own
        # check says what is wrong, so the rclpy type check is relaxed.
        d.dynamic_typing = True
        if rg is not None and isinstance(v, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(rg[0]), to_value=float(rg[1]), step=0.0)]
    elif isinstance(v, int) and not isinstance(v, bool) and rg is not None:
        d.integer_range = [IntegerRange(from_value=int(rg[0]), to_value=int(rg[1]), step=1)]
    return d


def _ros_value(v: Any) -> Any:
    if isinstance(v, tuple):
        return list(v)
    return v


class CalibNodeBase(Node):
    """Parameters, inputs, the worker, adoption of results, outputs, services."""

    method_name = "base"
    config_cls: Any = None       # the method's config dataclass (cfg_field fields)

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._factory = RclpyFactory()
        self._params: dict[str, _Param] = {}
        self._declaring = ""
        self._inputs: list[_Input] = []
        self._lock = threading.RLock()
        self._input_group = MutuallyExclusiveCallbackGroup()
        self._service_group = MutuallyExclusiveCallbackGroup()
        self._timer_group = MutuallyExclusiveCallbackGroup()
        self._input_count = 0
        self._log_times: dict[str, float] = {}
        self.last_reason = ""
        self.last_file_note = ""
        self.candidate: dict | None = None          # last fit that was not adopted
        self.last_fit_failure = ""                  # why the last fit was refused (kept while collecting on)
        self.in_effect: CalibrationSet | None = None
        self.in_effect_source = ""                  # 'file' (earlier run) | 'this collection' | ...
        self._in_effect_ours = False                # adopted in the current collection
        self._generation = 0                        # bumped by recalibrate / time jump
        self._last_stamp: dict[str, tuple[float, int]] = {}
        self.refused_after_s = -math.inf            # newest stamp of a refused input
        self.last_accepted_s = -math.inf            # stamp of the last accepted observation
        self._calib_status: dict = {}
        self._busy = ""
        self.max_input_delay_ms = 0.0
        self.dropped_busy = 0                       # live frames dropped while the worker was busy
        self._delays: collections.deque = collections.deque(maxlen=2000)

        for name, default, meta in BASE_PARAMS:
            self._declare(_Param(name, default, meta, "base"))
        if self.config_cls is not None:
            self._declare_config(self.config_cls(), ())
        self.declare_node_params()
        self.cfg = self._build_config()
        self.output_path = self._resolve_output_path()

        self.pub_transform = self.create_publisher(TransformStamped, "~/transform", LATCHED)
        self.pub_yaml = self.create_publisher(String, "~/result_yaml", LATCHED)
        self.pub_status = self.create_publisher(String, "~/status", LATCHED)
        self._overlay_pubs: dict[str, Any] = {}
        self.pub_ack = self.create_publisher(UInt64, "~/ack", LATCHED) if self.param("replay_ack") else None
        self.create_service(Trigger, "~/recalibrate", self._srv_recalibrate, callback_group=self._service_group)
        self.create_service(Trigger, "~/capture", self._srv_capture, callback_group=self._service_group)
        self._tf_pub, self._tf_sent = self._make_tf_static_publisher(), {}
        self.calib = self.make_calibrator(self.cfg)
        self._jobs: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work_loop, name=f"{node_name}_worker", daemon=True)
        self._worker.start()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._load_existing_result()
        self.create_timer(float(self.param("status_period_s")), self.publish_status,
                          callback_group=self._timer_group)

    def announce_ready(self) -> None:
        """Call at the end of a node's __init__, once every input exists: the
        latched ~/ack = 0 and ~/status (with the inputs) tell a replayer the
        node is up and what it reads."""
        self._warn_unknown_overrides()
        if self.pub_ack is not None:
            self.pub_ack.publish(UInt64(data=0))
        self.publish_status()

    # ------------------------------------------------------------------ hooks
    def declare_node_params(self) -> None:
        """Override: declare the node's own parameters (inputs, triggers)."""

    def make_calibrator(self, cfg: Any) -> Any:
        """Override: the method's calibrator for this config."""
        raise NotImplementedError

    def on_config_changed(self, cfg: Any) -> None:
        """A config parameter changed at run time (already validated)."""
        self.calib.cfg = cfg

    def on_reset(self) -> None:
        """Override: drop the node's own input state (pairs, detectors)."""

    def on_capture(self) -> tuple[bool, str]:
        return False, f"{self.method_name} does not take observations on demand"

    def after_fit(self) -> None:
        """Worker, after every fit attempt (adopted or not)."""

    def render_overlays(self, frame: Any, cal: CalibrationSet) -> dict:
        """Override: {camera name or '': bgr image} drawn with the result."""
        return {}

    def method_status(self) -> dict:
        """Override: node-level progress fields (not the calibrator's)."""
        return {}

    # ------------------------------------------------------------------ parameters
    def _declare(self, p: _Param) -> Any:
        if p.name in self._params:
            raise ConfigError(f"parameter {p.name} declared twice")
        self._params[p.name] = p
        self._declaring = p.name  # its value is checked below, not by the on-set callback
        try:
            value = self.declare_parameter(p.name, _ros_value(p.default), _descriptor(p)).value
        except rclpy.exceptions.ParameterException as e:  # wrong type / out of range override
            given = (getattr(self, "_parameter_overrides", {}) or {}).get(p.name)
            if given is not None:
                check_value(p.name, given.value, p.meta, p.default)  # says it our way when it can
            raise ConfigError(f"parameter {p.name}: {_first_line(e)}; allowed: {allowed_text(p.meta)}") from None
        finally:
            self._declaring = ""
        return check_value(p.name, value, p.meta, p.default)

    def _declare_config(self, cfg: Any, path: tuple) -> None:
        for f in dataclasses.fields(cfg):
            v = getattr(cfg, f.name)
            if dataclasses.is_dataclass(v):
                self._declare_config(v, path + (f.name,))
                continue
            if not f.metadata.get("param", True) or v is None:
                continue  # None cannot be a ROS parameter value
            meta = dict(f.metadata) if "help" in f.metadata else _meta(f"{f.name} (undocumented)")
            name = "_".join(path + (f.name,))
            self._declare(_Param(name, v, meta, "config"))

    def declare_param(self, name: str, default: Any, help: str, **kw: Any) -> Any:
        """Declare a node parameter described like a config field."""
        return self._declare(_Param(name, default, _meta(help, **kw), "node"))

    def add_input(self, name: str, msg_type: Any, param: str, default_topic: str, help: str,
                  callback: Callable[[Any], None], required: bool = True) -> None:
        """Declare a read-only topic parameter and subscribe to it. The
        callback runs in the input group; exceptions become reasons."""
        if param in self._params:   # the method's config names its own topics
            topic = self.param(param)
        else:
            topic = self._declare(_Param(param, default_topic, _meta(help, read_only=True), "input"))
        inp = _Input(name, msg_type, param, required, callback)
        if topic:
            qos = input_qos(self.param("input_reliability"), int(self.param("input_queue_depth")))
            inp.subscription = self.create_subscription(msg_type, topic, self._guarded(inp), qos,
                                                        callback_group=self._input_group)
        elif required:
            raise ConfigError(f"parameter {param} is empty: {name} input needs a topic")
        self._inputs.append(inp)

    def param(self, name: str) -> Any:
        p = self._params.get(name)
        v = self.get_parameter(name).value
        return check_value(name, v, p.meta, p.default) if p is not None else v

    def _build_config(self, overrides: dict | None = None) -> Any:
        if self.config_cls is None:
            return None
        overrides = overrides or {}

        def build(cls: Any, path: tuple) -> Any:
            kw = {}
            proto = cls()
            for f in dataclasses.fields(proto):
                v = getattr(proto, f.name)
                if dataclasses.is_dataclass(v):
                    kw[f.name] = build(type(v), path + (f.name,))
                    continue
                name = "_".join(path + (f.name,))
                if name in self._params:
                    kw[f.name] = overrides[name] if name in overrides else self.param(name)
            return cls(**kw)
        try:
            cfg = build(self.config_cls, ())
            validate_config(cfg)
        except (TypeError, ValueError) as e:
            raise ConfigError(str(e)) from None
        return cfg

    def _warn_unknown_overrides(self) -> None:
        known = set(self._params) | {"use_sim_time", "start_type_description_service"}
        for name in sorted(getattr(self, "_parameter_overrides", {}) or {}):
            if name not in known:
                close = [k for k in self._params if _similar(k, name)]
                self.get_logger().warning(f"unknown parameter {name!r} ignored"
                                          + (f" (did you mean {close[0]}?)" if close else ""))

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        changes = {}
        for prm in params:
            p = self._params.get(prm.name)
            if p is None or prm.name == self._declaring:
                continue
            if p.meta.get("read_only"):
                return SetParametersResult(successful=False,
                                           reason=f"{prm.name} is read-only after start-up (files, topics, "
                                                  "frames): restart the node to change it")
            if prm.type_ == ParameterType.PARAMETER_NOT_SET:
                return SetParametersResult(successful=False, reason=f"{prm.name} cannot be unset")
            try:
                changes[prm.name] = check_value(prm.name, prm.value, p.meta, p.default)
            except ConfigError as e:
                return SetParametersResult(successful=False, reason=str(e))
        cfg_changes = {k: v for k, v in changes.items() if self._params[k].kind == "config"}
        if cfg_changes:
            try:
                cfg = self._build_config(cfg_changes)
            except ConfigError as e:
                return SetParametersResult(successful=False, reason=str(e))
            self.submit(lambda: self._apply_config(cfg), wait=False)
        return SetParametersResult(successful=True)

    def _apply_config(self, cfg: Any) -> tuple[bool, str]:
        self.cfg = cfg
        self.on_config_changed(cfg)
        return True, "configuration updated"

    # ------------------------------------------------------------------ inputs
    def _guarded(self, inp: _Input) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            try:
                self._note_delay(msg)
                inp.callback(msg)
            except CalibError as e:
                self.refuse_input(inp.name, msg, str(e))
            except Exception as e:  # noqa: BLE001 - a bug must not take the node down
                self.refuse_input(inp.name, msg, f"{type(e).__name__}: {e}")
                self.get_logger().error(f"{inp.name} callback failed:\n{traceback.format_exc()}")
            finally:
                self._input_count += 1
                if self.pub_ack is not None:
                    self.wait_idle()
                    self.pub_ack.publish(UInt64(data=self._input_count))
        return cb

    def _note_delay(self, msg: Any) -> None:
        """Live only: how late an input callback starts after the message's
        stamp (the sensor's clock = ours on one machine); shown in status."""
        if self.pub_ack is not None:
            return
        try:
            d = 1000.0 * (time.time() - stamp_to_s(msg.header.stamp))
        except AttributeError:
            return
        if 0.0 <= d < 10_000.0:
            self.max_input_delay_ms = max(self.max_input_delay_ms, d)
            self._delays.append(d)

    def check_stamp(self, stream: str, t: float, content: Any) -> None:
        """Refuse a stamp that goes back (out of order) or repeats with other
        content; a jump back of more than ``time_jump_s`` starts a new
        collection (bag loop, simulated time restart)."""
        digest = _digest(content)
        last = self._last_stamp.get(stream)
        if last is not None:
            lt, ld = last
            if t < lt - float(self.param("time_jump_s")):
                self.new_collection(f"time went back on {stream} from {lt:.3f} s to {t:.3f} s (bag loop or "
                                    "simulated time restart): starting a new collection")
            elif t < lt:
                raise InputError(f"{stream} stamp {t:.3f} s is older than the previous {lt:.3f} s: out of order, "
                                 "dropped")
            elif t == lt:
                what = "the same content again" if digest == ld else "different content"
                raise InputError(f"two {stream} messages with the same stamp {t:.3f} s and {what}: the second is "
                                 "dropped (check the driver's clock)")
        self._last_stamp[stream] = (t, digest)

    def refuse_input(self, stream: str, msg: Any, reason: str) -> None:
        try:
            t = stamp_to_s(msg.header.stamp)
            with self._lock:
                self.refused_after_s = max(self.refused_after_s, t)
        except AttributeError:
            pass
        self.reject(reason)

    def reject(self, reason: str) -> None:
        self.last_reason = reason
        self.log_throttled(reason)
        self.publish_status()

    def log_throttled(self, reason: str, level: str = "warning") -> None:
        """At most one log line per second per kind of reason (numbers ignored)."""
        key = re.sub(r"[-+]?\d[\d.e+-]*", "#", reason)
        now = time.monotonic()
        if now - self._log_times.get(key, -math.inf) >= 1.0:
            self._log_times[key] = now
            # one call site per severity: rclpy refuses a call site whose severity changes
            if level == "info":
                self.get_logger().info(reason)
            elif level == "error":
                self.get_logger().error(reason)
            else:
                self.get_logger().warning(reason)

    def fresh_enough(self, *stamps: float) -> str:
        """'' when every stamp is newer than the last accepted observation and
        than any refused input; else why not."""
        with self._lock:
            t = min(stamps)
            if t <= self.last_accepted_s:
                return (f"no input newer than the last accepted observation ({self.last_accepted_s:.3f} s) "
                        "yet: move to the next pose and wait for new data")
            if t <= self.refused_after_s:
                return (f"the newest input ({self.refused_after_s:.3f} s) was refused "
                        f"({self.last_reason or 'see log'}); "
                        "waiting for valid data newer than it")
        return ""

    # ------------------------------------------------------------------ worker
    def submit(self, job: Callable[[], tuple[bool, str]], wait: bool = True, timeout_s: float = 600.0
               ) -> tuple[bool, str]:
        """Run ``job`` on the worker thread (in submission order). With
        ``wait``, block until it is done and return its answer."""
        done = threading.Event()
        box: list = [(False, "not run")]
        self._jobs.put((job, done, box))
        if not wait:
            return True, "queued"
        if not done.wait(timeout_s):
            return False, f"still running after {timeout_s:.0f} s"
        return box[0]

    def wait_idle(self) -> None:
        """Block until every job submitted so far is done (lock-step replay)."""
        self.submit(lambda: (True, ""), wait=True)

    def _work_loop(self) -> None:
        while not self._stop.is_set():
            try:
                job, done, box = self._jobs.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                box[0] = job()
            except CalibError as e:
                box[0] = (False, str(e))
                self._safe_reject(str(e))
            except Exception as e:  # noqa: BLE001 - the node stays up; the bug is logged
                box[0] = (False, f"{type(e).__name__}: {e}")
                self._safe_reject(box[0][1], traceback.format_exc())
            finally:
                self._busy = ""
                if not self._stop.is_set():
                    # the status that says what the job did goes out before its answer
                    try:
                        self._calib_status = to_plain(self.calib.status())
                    except Exception as e:  # noqa: BLE001 - status must not raise
                        self._calib_status = {"status_error": str(e)}
                    self.publish_status()
                done.set()

    def _safe_reject(self, reason: str, trace: str = "") -> None:
        """The worker never dies of its own error handling."""
        try:
            if trace:
                self.get_logger().error(f"worker job failed:\n{trace}")
            self.reject(reason)
        except Exception:  # noqa: BLE001 - last resort: keep the worker alive
            self.last_reason = reason

    def submit_frame(self, frame: Any, stamp_s: float, auto: bool, wait: bool, max_queued: int = 0
                     ) -> tuple[bool, str]:
        """Hand one frame to the calibrator (on the worker); fit, adopt and
        publish when it is ready. Live, with ``max_queued`` > 0, a frame that
        finds that many jobs waiting (a long fit) is dropped and counted
        instead of piling up; lock-step replay never drops."""
        if max_queued and self.pub_ack is None and self._jobs.qsize() >= max_queued:
            self.dropped_busy += 1
            return False, f"dropped: the worker is {self._busy or 'busy'}"
        gen = self._generation
        return self.submit(lambda: self._process_frame(frame, stamp_s, auto, gen), wait=wait)

    def _process_frame(self, frame: Any, stamp_s: float, auto: bool, gen: int, **add_kw: Any) -> tuple[bool, str]:
        """Worker: ``calib.add(frame, **add_kw)``, then fit and adopt when ready."""
        return self.process(lambda: self.calib.add(frame, **add_kw), frame, stamp_s, auto, gen)

    def process(self, add: Callable[[], Any], frame: Any, stamp_s: float, auto: bool, gen: int
                ) -> tuple[bool, str]:
        """Worker: ``add()`` gives the calibrator's Verdict on new data (one
        frame, or a whole stop); when accepted and ready, fit and adopt.
        ``frame`` is what the overlays are drawn on."""
        if gen != self._generation:
            return False, "frame from before ~/recalibrate (or a time jump): dropped"
        self._busy = "adding a frame"
        verdict = add()
        if not verdict.accepted:
            self.reject(verdict.reason)
            return False, verdict.reason
        with self._lock:
            self.last_accepted_s = max(self.last_accepted_s, stamp_s)
        self.last_reason = ""
        note = verdict.reason + (" (automatic)" if auto else "")
        if self.calib.ready():
            note += "; " + self._fit_and_adopt(frame, gen)
            self.after_fit()
        self.log_throttled(note, "info")
        return True, note

    def _fit_and_adopt(self, frame: Any, gen: int) -> str:
        self._busy = "fitting"
        t0 = time.monotonic()
        try:
            fitted = self.calib.fit()
        except CalibError as e:
            self.last_reason = self.last_fit_failure = f"fit failed: {e}"
            return self.last_reason
        self.last_fit_failure = ""
        cal = fitted if isinstance(fitted, CalibrationSet) else CalibrationSet.single(fitted)
        if gen != self._generation:
            return "fit finished after ~/recalibrate: discarded"
        self._stamp_frames(cal)
        fit_s = time.monotonic() - t0
        adopted, why = self.adopt(cal)
        if not adopted:
            self.candidate = {"reason": why, "sigma": _sigmas(cal), "observations": _obs(cal),
                              "fit_s": fit_s}
            self.log_throttled(f"calibration not adopted: {why}")
            return f"not adopted: {why}"
        self.candidate = None
        try:
            for name, img in self.render_overlays(frame, cal).items():
                self.publish_overlay(name, img)
        except Exception as e:  # noqa: BLE001 - an overlay never costs a result
            self.get_logger().warning(f"overlay failed: {e}")
        return f"published: {_sigma_text(cal)}; {self.last_file_note}"

    def _stamp_frames(self, cal: CalibrationSet) -> None:
        parent = self.param("parent_frame")
        child = self.param("child_frame")
        topics = {i.name: self.resolved_topic(i) for i in self._inputs}
        for r in cal.results.values():
            if parent:
                r.parent_frame = parent
            if child and cal.is_single:
                r.child_frame = child
            r.input_topics = topics

    def resolved_topic(self, inp: _Input) -> str:
        return inp.subscription.topic_name if inp.subscription is not None else ""

    # ------------------------------------------------------------------ adoption
    def adopt(self, cal: CalibrationSet) -> tuple[bool, str]:
        """Make ``cal`` the calibration in effect (file, topics, /tf_static)
        unless what is in effect must be kept. Returns (adopted, why not)."""
        force = bool(self.param("force_overwrite"))
        old = self.in_effect
        if old is not None and not force:
            if old.method != cal.method:
                return False, (f"{self._where()} holds a {old.method!r} calibration, this is {cal.method!r}: "
                               "kept; use another output_path or force_overwrite:=true")
            covers = set(old.frame_pairs().items()) <= set(cal.frame_pairs().items())  # may add cameras
            if not covers and not self._in_effect_ours:
                return False, (f"{self._where()} holds the calibration of {_pairs_text(old)}, this one is for "
                               f"{_pairs_text(cal)}: kept; use another output_path or force_overwrite:=true")
            if not self._in_effect_ours and not _no_worse(cal, old):
                return False, (f"{self._where()} holds a better calibration ({_sigma_text(old)} vs new "
                               f"{_sigma_text(cal)}): kept; force_overwrite:=true replaces it")
        if self.output_path:
            try:
                write_atomic(self.output_path, cal.to_yaml(), keep_bak=True)
                self.last_file_note = f"wrote {self.output_path}"
            except ResultFileError as e:
                self.last_file_note = f"result NOT saved: {e}"
                self.get_logger().error(self.last_file_note)
                if os.path.isfile(self.output_path):
                    return False, f"{e} (the file keeps the previous calibration, which stays in effect)"
        else:
            self.last_file_note = "no output_path set: result not written to disk"
        self.in_effect, self.in_effect_source, self._in_effect_ours = cal, "this collection", True
        self._publish_in_effect(cal)
        return True, ""

    def _where(self) -> str:
        if self.output_path and self.in_effect_source == "file":
            return self.output_path
        return "the calibration in effect"

    def _publish_in_effect(self, cal: CalibrationSet) -> None:
        for r in cal.results.values():
            ts = self.transform_msg(r)
            self.pub_transform.publish(ts)
            if self._tf_pub is not None:
                self._tf_sent[ts.child_frame_id] = ts
        if self._tf_pub is not None:
            from tf2_msgs.msg import TFMessage  # type: ignore

            self._tf_pub.publish(TFMessage(transforms=list(self._tf_sent.values())))
        self.pub_yaml.publish(String(data=cal.to_yaml()))

    def transform_msg(self, result: CalibrationResult) -> TransformStamped:
        t, q = result.tf_translation_rotation()
        ts = TransformStamped()
        ts.header.stamp = self.get_clock().now().to_msg()
        ts.header.frame_id = result.parent_frame
        ts.child_frame_id = result.child_frame
        ts.transform.translation.x, ts.transform.translation.y, ts.transform.translation.z = (float(v) for v in t)
        (ts.transform.rotation.x, ts.transform.rotation.y,
         ts.transform.rotation.z, ts.transform.rotation.w) = (float(v) for v in q)
        return ts

    def _resolve_output_path(self) -> str:
        path = self.param("output_path")
        if not path:
            path = f"~/.ros/lidar_cam_calib/{self.method_name}.yaml"
        try:
            return check_output_path(path)
        except ResultFileError as e:
            raise ConfigError(f"parameter output_path={path!r}: {e}") from None

    def _load_existing_result(self) -> None:
        """The calibration on disk is in effect from the first second on."""
        path = self.output_path
        if not path or not os.path.exists(path):
            return
        try:
            cal = CalibrationSet.load(path)
        except ResultFileError as e:
            self.get_logger().warning(f"ignoring unreadable previous result (it will be kept as .bak): {e}")
            return
        self.in_effect, self.in_effect_source, self._in_effect_ours = cal, "file", False
        if cal.method != self.method_name:
            self.get_logger().warning(f"{path} holds a {cal.method!r} calibration, not {self.method_name!r}: not "
                                      "published and not replaced (use another output_path or force_overwrite)")
            return
        self._publish_in_effect(cal)
        self.last_file_note = f"in effect: {path} from an earlier run ({_sigma_text(cal)})"
        self.get_logger().info(f"published the calibration from {path}")

    # ------------------------------------------------------------------ outputs
    def publish_status(self, extra: dict | None = None) -> dict:
        d = {"node": self.get_fully_qualified_name(), "method": self.method_name}
        d.update(self._calib_status)
        d.update(self.method_status())
        d["last_reason"] = self.last_reason or self._calib_status.get("last_reason", "")
        d["result_file"] = self.last_file_note
        d["busy"] = self._busy
        d["inputs_processed"] = self._input_count
        if self.dropped_busy:
            d["frames_dropped_while_busy"] = self.dropped_busy
        d["inputs"] = [{"name": i.name, "topic": self.resolved_topic(i), "required": i.required,
                        "type": _type_name(i.msg_type)} for i in self._inputs]
        if self.pub_ack is None:
            d["max_input_delay_ms"] = round(self.max_input_delay_ms, 2)
            if self._delays:
                q = np.percentile(np.fromiter(self._delays, float), [50, 99])
                d["input_delay_ms_p50_p99"] = [round(float(q[0]), 2), round(float(q[1]), 2)]
        eff = self.in_effect
        d["in_effect"] = None if eff is None else {
            "source": self.in_effect_source, "sigma": _sigmas(eff), "frames": _pairs_text(eff)}
        if self._in_effect_ours and eff is not None:
            d["sigma_deg_mm"] = _sigmas(eff).get("", None) if eff.is_single else _sigmas(eff)
        d["candidate"] = self.candidate
        if self.last_fit_failure:
            d["last_fit_failure"] = self.last_fit_failure
        if extra:
            d.update(extra)
        try:
            self.pub_status.publish(String(data=json.dumps(to_plain(d), sort_keys=True)))
        except Exception:  # noqa: BLE001 - after shutdown the publisher is gone
            pass
        return d

    def publish_overlay(self, name: str, bgr: np.ndarray) -> None:
        topic = "~/overlay" if not name else f"~/overlay/{name}"
        pub = self._overlay_pubs.get(topic)
        if pub is None:
            pub = self._overlay_pubs[topic] = self.create_publisher(Image, topic, 1)
        header = self._factory.make_header(0.0, name)
        header.stamp = self.get_clock().now().to_msg()
        pub.publish(array_to_image(bgr, "bgr8", self._factory, header))
        path = self.param("overlay_path")
        if path:
            import cv2

            path = os.path.expanduser(path)
            if name:
                stem, ext = os.path.splitext(path)
                path = f"{stem}_{name}{ext or '.png'}"
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            if not cv2.imwrite(path, bgr):
                self.get_logger().warning(f"cannot write overlay {path!r}")

    def _make_tf_static_publisher(self) -> Any:
        """Our own latched TFMessage with one transform per child frame, replaced
        on every adopted result (tf2_ros's StaticTransformBroadcaster in Jazzy
        never replaces a child it has sent)."""
        if not self.param("publish_tf_static"):
            return None
        try:
            from tf2_msgs.msg import TFMessage  # type: ignore
        except ImportError:
            self.get_logger().info("tf2_msgs not importable: /tf_static output skipped (the calibration is still "
                                   "on ~/transform and ~/result_yaml)")
            return None
        return self.create_publisher(TFMessage, "/tf_static", LATCHED)

    # ------------------------------------------------------------------ services
    def new_collection(self, why: str) -> int:
        """Drop everything collected (calibrator, node input state, stamps)."""
        with self._lock:
            self._generation += 1
            n = collected_count(self._calib_status)
            self._last_stamp.clear()
            self.refused_after_s = -math.inf
            self.last_accepted_s = -math.inf
            self.candidate = None
            self.last_reason = ""
            self.last_fit_failure = ""
            if self._in_effect_ours:
                self.in_effect_source, self._in_effect_ours = "earlier collection", False
            self.last_file_note = ""
            self.on_reset()
        self.submit(self._reset_job, wait=False)
        self.get_logger().info(why)
        return n

    def _reset_job(self) -> tuple[bool, str]:
        self.calib.reset()
        return True, "reset"

    def _srv_recalibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        busy = self._busy
        n = self.new_collection("~/recalibrate: starting a new collection")
        self.wait_idle()
        response.success = True
        response.message = (f"dropped {n} observations; collecting again"
                            + (f" (a {busy} in progress was discarded)" if busy == "fitting" else ""))
        return response

    def _srv_capture(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.success, response.message = self.on_capture()
        except CalibError as e:
            response.success, response.message = False, str(e)
        except Exception as e:  # noqa: BLE001
            response.success, response.message = False, f"capture failed: {type(e).__name__}: {e}"
            self.get_logger().error(traceback.format_exc())
        if not response.success:
            self.reject(response.message)
        return response

    # ------------------------------------------------------------------ shutdown
    def shutdown_worker(self, timeout_s: float = 0.5) -> bool:
        self._stop.set()
        self._worker.join(timeout_s)
        return not self._worker.is_alive()


# ---------------------------------------------------------------------- helpers
def _first_line(e: BaseException) -> str:
    return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__


def _similar(a: str, b: str) -> bool:
    import difflib

    return difflib.SequenceMatcher(None, a, b).ratio() > 0.8


def _digest(content: Any) -> int:
    if content is None:
        return 0
    if isinstance(content, np.ndarray):
        return zlib.crc32(np.ascontiguousarray(content).view(np.uint8).ravel())
    try:
        return zlib.crc32(memoryview(content).cast("B"))
    except TypeError:
        return zlib.crc32(np.asarray(content).tobytes())


def _type_name(cls: Any) -> str:
    mod = cls.__module__.split(".")
    return f"{mod[0]}/msg/{cls.__name__}"


def _sigmas(cal: CalibrationSet) -> dict:
    return {k: [round(v, 4) for v in r.sigma()] for k, r in cal.results.items()}


def _obs(cal: CalibrationSet) -> dict:
    return {k: r.observations_used for k, r in cal.results.items()}


def _sigma_text(cal: CalibrationSet) -> str:
    return ", ".join((f"{k}: " if k else "") + f"sigma {r.sigma()[0]:.3f} deg / {r.sigma()[1]:.2f} mm"
                     for k, r in cal.results.items())


def _pairs_text(cal: CalibrationSet) -> str:
    return ", ".join(f"{p}->{c}" for p, c in cal.frame_pairs().values())


def _no_worse(new: CalibrationSet, old: CalibrationSet) -> bool:
    """Every calibration of ``old`` is in ``new`` with sigma no larger (1 %)."""
    for k, o in old.results.items():
        n = new.results.get(k)
        if n is None or not n.is_better_than(o):
            return False
    return True


def run_node(node_cls: type, args: list[str] | None = None) -> int:
    """Entry point: init, spin until SIGINT/SIGTERM (within a second, whether
    idle, collecting or fitting), shut down. A bad parameter ends start-up
    with one line naming it (exit 2), never a traceback."""
    import sys

    sys.setswitchinterval(0.0005)  # input callbacks get the GIL back quickly while the worker computes
    rclpy.init(args=args)  # installs rclpy's SIGINT and SIGTERM handlers: both wake the executor
    node = None
    code = 0
    try:
        try:
            node = node_cls()
        except ConfigError as e:
            print(f"error: {e}", file=sys.stderr, flush=True)
            return 2
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        try:
            while rclpy.ok():
                try:
                    executor.spin()
                except (KeyboardInterrupt, ExternalShutdownException):
                    break
                except Exception:  # noqa: BLE001 - a callback's bug never ends the node
                    node.get_logger().error(f"callback failed:\n{traceback.format_exc()}")
        finally:
            executor.shutdown(timeout_sec=0.5)
    except KeyboardInterrupt:
        pass
    finally:
        clean = True
        if node is not None:
            clean = node.shutdown_worker(0.5)
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001
                pass
        rclpy.try_shutdown()
        import threading

        busy = [t for t in threading.enumerate()
                if t is not threading.main_thread() and not t.daemon and t.is_alive()]
        if node is not None and (not clean or busy):
            # a fit is still running in the worker, or an executor thread is still in a callback
            # (the interpreter would join it at exit, seen to take 10 s on a loaded machine): do
            # not wait for them; every file the node writes is written synchronously already
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    return code


__all__ = ["CalibNodeBase", "LATCHED", "input_qos", "run_node"]
