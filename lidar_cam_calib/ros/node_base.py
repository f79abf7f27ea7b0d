"""Node base class shared by every calibration node (the only rclpy layer).

A method node subclasses :class:`CalibNodeBase`, declares its own parameters
and subscriptions, converts messages to the method's ROS-free frame type and
calls :meth:`publish_result` / :meth:`publish_status` / :meth:`publish_overlay`.

Outputs (DESIGN.md):
  ~/transform    geometry_msgs/TransformStamped, transient-local (latched)
  /tf_static     via tf2_ros when importable, else tf2_msgs directly, else skipped
  ~/result_yaml  std_msgs/String, transient-local, and the same YAML on disk
                 (atomic write, previous file kept as .bak, never replaced by
                 a worse result)
  ~/status       std_msgs/String (JSON): progress and last rejection reason
  ~/overlay      sensor_msgs/Image (bgr8): range points drawn on the image
  ~/ack          std_msgs/UInt64, only when parameter replay_ack is true: the
                 number of input messages processed (lock-step replay)
Services: ~/recalibrate, ~/capture (std_srvs/Trigger).
"""
from __future__ import annotations

import json
import math
import os
import traceback
from typing import Any, Callable

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt64
from std_srvs.srv import Trigger

from ..core.result import CalibrationResult, ResultFileError, save_if_better
from ..io.convert import array_to_image
from ..io.msgtypes import RclpyFactory

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def input_qos(reliability: str, depth: int) -> QoSProfile:
    """Subscription QoS for sensor inputs: 'best_effort' (matches any driver,
    the usual sensor-data QoS) or 'reliable' (lossless replay)."""
    if reliability == "reliable":
        return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    q = QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                   reliability=qos_profile_sensor_data.reliability,
                   durability=DurabilityPolicy.VOLATILE)
    return q


def stamp_to_s(stamp) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


class CalibNodeBase(Node):
    """Parameters, outputs, services and error containment for calibration nodes."""

    method_name = "base"

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._factory = RclpyFactory()
        self._input_count = 0
        self.last_result: CalibrationResult | None = None
        self.last_reason = ""
        self.last_file_note = ""
        # Once this run has written the file, later fits of the same collection
        # (more observations) replace it; the better-or-not guard protects a
        # calibration from an earlier run or another collection.
        self._wrote_this_collection = False

        self.declare_str("output_path", "~/.ros/lidar_cam_calib/" + self.method_name + ".yaml",
                         "Where the result YAML is written (atomic; previous kept as .bak). Empty: no file.")
        self.declare_str("overlay_path", "",
                         "If set, each overlay image is also written there as PNG.")
        self.declare_bool("force_overwrite", False,
                          "Write the result file even when the file on disk holds a better (lower sigma) calibration.")
        self.declare_bool("publish_tf_static", True,
                          "Also publish the extrinsic on /tf_static (tf2_ros or tf2_msgs needed).")
        self.declare_str("input_reliability", "best_effort",
                         "QoS reliability of sensor subscriptions: best_effort (any driver) or reliable (lossless replay).")
        self.declare_int("input_queue_depth", 10, "Queue depth of sensor subscriptions.", 1, 10000)
        self.declare_bool("replay_ack", False,
                          "Publish ~/ack (processed input count) after each input message; used by lock-step replay.")
        self.declare_str("parent_frame", "", "Override the range sensor frame id (default: from the messages).")
        self.declare_str("child_frame", "", "Override the camera optical frame id (default: from the messages).")

        if self.get_parameter("input_reliability").value not in ("best_effort", "reliable"):
            raise ValueError("input_reliability must be 'best_effort' or 'reliable'")

        self.pub_transform = self.create_publisher(TransformStamped, "~/transform", LATCHED)
        self.pub_yaml = self.create_publisher(String, "~/result_yaml", LATCHED)
        self.pub_status = self.create_publisher(String, "~/status", 10)
        self.pub_overlay = self.create_publisher(Image, "~/overlay", 1)
        self.pub_ack = self.create_publisher(UInt64, "~/ack", LATCHED) \
            if self.get_parameter("replay_ack").value else None
        self.srv_recal = self.create_service(Trigger, "~/recalibrate", self._srv_recalibrate)
        self.srv_capture = self.create_service(Trigger, "~/capture", self._srv_capture)
        self._tf_publisher = self._make_tf_static_publisher()
        self._load_existing_result()

    def announce_ready(self) -> None:
        """Call at the end of a subclass __init__, once every subscription
        exists: the latched ~/ack = 0 tells a replayer the node is up."""
        if self.pub_ack is not None:
            self.pub_ack.publish(UInt64(data=0))
        self.publish_status()

    # -- parameters --------------------------------------------------------
    def _declare(self, name: str, default: Any, descriptor: ParameterDescriptor) -> Any:
        return self.declare_parameter(name, default, descriptor).value

    def declare_str(self, name: str, default: str, description: str) -> str:
        return self._declare(name, default, ParameterDescriptor(description=description))

    def declare_bool(self, name: str, default: bool, description: str) -> bool:
        return self._declare(name, default, ParameterDescriptor(description=description))

    def declare_int(self, name: str, default: int, description: str, lo: int, hi: int) -> int:
        d = ParameterDescriptor(description=description,
                                integer_range=[IntegerRange(from_value=lo, to_value=hi, step=1)])
        return self._declare(name, default, d)

    def declare_float(self, name: str, default: float, description: str, lo: float, hi: float) -> float:
        d = ParameterDescriptor(description=description,
                                floating_point_range=[FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)])
        return self._declare(name, float(default), d)

    def param(self, name: str) -> Any:
        return self.get_parameter(name).value

    def sensor_qos(self) -> QoSProfile:
        return input_qos(self.param("input_reliability"), int(self.param("input_queue_depth")))

    # -- error containment -------------------------------------------------
    def guarded(self, what: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """Wrap a subscription callback: exceptions become a status reason and
        a log line, the node stays up; the ack counter always advances."""
        def cb(msg: Any) -> None:
            try:
                fn(msg)
            except Exception as e:  # noqa: BLE001 - the node must stay up on bad input
                self.reject(f"{what}: {e}")
                self.get_logger().debug(traceback.format_exc())
            finally:
                self._input_count += 1
                if self.pub_ack is not None:
                    self.pub_ack.publish(UInt64(data=self._input_count))
        return cb

    def reject(self, reason: str) -> None:
        self.last_reason = reason
        self.get_logger().warning(reason, throttle_duration_sec=1.0)
        self.publish_status()

    # -- outputs -----------------------------------------------------------
    def status_dict(self) -> dict:
        """Override to add method progress; keep it JSON-serialisable."""
        return {"node": self.get_name(), "method": self.method_name, "last_reason": self.last_reason,
                "result_file": self.last_file_note}

    def publish_status(self, extra: dict | None = None) -> dict:
        d = self.status_dict()
        if extra:
            d.update(extra)
        self.pub_status.publish(String(data=json.dumps(_jsonable(d), sort_keys=True)))
        return d

    def publish_result(self, result: CalibrationResult, stamp=None) -> str:
        """Publish a calibration on ~/transform, /tf_static, ~/result_yaml and
        write the file if it is not worse than what is on disk. Returns a
        human-readable note about the file."""
        self.last_result = result
        parent = self.param("parent_frame") or result.parent_frame
        child = self.param("child_frame") or result.child_frame
        result.parent_frame, result.child_frame = parent, child
        ts = self.transform_msg(result, stamp)
        self.pub_transform.publish(ts)
        if self._tf_publisher is not None:
            try:
                self._tf_publisher(ts)
            except Exception as e:  # noqa: BLE001
                self.get_logger().warning(f"/tf_static publish failed: {e}")
        yaml_text = result.to_yaml()
        self.pub_yaml.publish(String(data=yaml_text))
        self.last_file_note = self._write_file(result)
        return self.last_file_note

    def transform_msg(self, result: CalibrationResult, stamp=None) -> TransformStamped:
        t, q = result.tf_translation_rotation()
        ts = TransformStamped()
        ts.header.stamp = stamp if stamp is not None else self.get_clock().now().to_msg()
        ts.header.frame_id = result.parent_frame
        ts.child_frame_id = result.child_frame
        ts.transform.translation.x, ts.transform.translation.y, ts.transform.translation.z = (float(v) for v in t)
        (ts.transform.rotation.x, ts.transform.rotation.y,
         ts.transform.rotation.z, ts.transform.rotation.w) = (float(v) for v in q)
        return ts

    def _write_file(self, result: CalibrationResult) -> str:
        path = self.param("output_path")
        if not path:
            return "no output_path set: result not written to disk"
        path = os.path.expanduser(path)
        try:
            written, note = save_if_better(result, path, force=bool(self.param("force_overwrite"))
                                           or self._wrote_this_collection)
        except ResultFileError as e:
            note = f"result NOT saved: {e}"
            self.get_logger().error(note)
            self.last_reason = note
            return note
        if written:
            self._wrote_this_collection = True
            self.get_logger().info(note)
        else:
            self.get_logger().warning(note)
        return note

    def publish_overlay(self, bgr: np.ndarray, stamp=None, frame_id: str = "") -> None:
        header = self._factory.make_header(0.0, frame_id)
        if stamp is not None:
            header.stamp = stamp
        self.pub_overlay.publish(array_to_image(bgr, "bgr8", self._factory, header))
        path = self.param("overlay_path")
        if path:
            try:
                import cv2

                path = os.path.expanduser(path)
                os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
                if not cv2.imwrite(path, bgr):
                    raise OSError("cv2.imwrite returned False")
            except Exception as e:  # noqa: BLE001
                self.get_logger().warning(f"cannot write overlay {path!r}: {e}")

    def _load_existing_result(self) -> None:
        """Publish the calibration already on disk (latched) so consumers have
        the last good extrinsic from the first second on."""
        path = os.path.expanduser(self.param("output_path") or "")
        if not path or not os.path.exists(path):
            return
        try:
            res = CalibrationResult.load(path)
        except ResultFileError as e:
            self.get_logger().warning(f"ignoring unreadable previous result: {e}")
            return
        ts = self.transform_msg(res)
        self.pub_transform.publish(ts)
        self.pub_yaml.publish(String(data=res.to_yaml()))
        if self._tf_publisher is not None:
            self._tf_publisher(ts)
        self.get_logger().info(f"published previous calibration from {path}")

    # -- tf ----------------------------------------------------------------
    def _make_tf_static_publisher(self) -> Callable[[TransformStamped], None] | None:
        if not self.param("publish_tf_static"):
            return None
        try:
            from tf2_ros.static_transform_broadcaster import StaticTransformBroadcaster  # type: ignore

            b = StaticTransformBroadcaster(self)
            return b.sendTransform
        except ImportError:
            pass
        try:
            from tf2_msgs.msg import TFMessage  # type: ignore
        except ImportError:
            self.get_logger().info("tf2_ros/tf2_msgs not importable: /tf_static output skipped "
                                   "(the extrinsic is still on ~/transform and ~/result_yaml)")
            return None
        qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = self.create_publisher(TFMessage, "/tf_static", qos)
        sent: dict[str, TransformStamped] = {}

        def send(ts: TransformStamped) -> None:
            # Like tf2_ros: /tf_static is latched per child frame; resend all.
            sent[ts.child_frame_id] = ts
            pub.publish(TFMessage(transforms=list(sent.values())))
        return send

    # -- services ------------------------------------------------------------
    def _srv_recalibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._wrote_this_collection = False
        try:
            response.success, response.message = self.on_recalibrate()
        except Exception as e:  # noqa: BLE001
            response.success, response.message = False, f"recalibrate failed: {e}"
        self.publish_status()
        return response

    def _srv_capture(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.success, response.message = self.on_capture()
        except Exception as e:  # noqa: BLE001
            response.success, response.message = False, f"capture failed: {e}"
            self.last_reason = response.message
        self.publish_status()
        return response

    def on_recalibrate(self) -> tuple[bool, str]:
        raise NotImplementedError

    def on_capture(self) -> tuple[bool, str]:
        return False, f"{self.method_name} does not take observations on demand"


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def _raise_keyboard_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def run_node(node_cls: type, args: list[str] | None = None) -> int:
    """Entry point helper: init, spin until Ctrl-C / SIGTERM, shut down cleanly."""
    import signal

    rclpy.init(args=args)
    node = None
    try:
        node = node_cls()
        signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


__all__ = ["CalibNodeBase", "LATCHED", "input_qos", "run_node", "stamp_to_s"]
