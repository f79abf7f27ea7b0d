"""Message construction for both rosbags dataclasses and rclpy message classes.

The conversion helpers in :mod:`lidar_cam_calib.io.convert` never construct a
message class directly; they ask a *factory* to do it.  Two factories exist:

* :class:`RosbagsFactory` builds ``rosbags`` dataclasses from the ROS 2 Jazzy
  type store (no ROS installation needed) and can (de)serialise CDR bytes.
* :class:`RclpyFactory` builds the generated rclpy message classes
  (``sensor_msgs.msg.Image`` ...), importing the Python module lazily from the
  type name.  It does *not* initialise rclpy.

Both share the same API::

    msg = factory.make('sensor_msgs/msg/Image', header=factory.make_header(12.5, 'cam'),
                       height=480, width=640, encoding='mono8', step=640, data=np_uint8_array)

Fields that are omitted get their ROS default (0, '', empty sequence, zeroed
fixed arrays, default nested messages).  A nested field may be given as a dict
of its own fields.  Numeric sequences/arrays may be given as numpy arrays,
lists or bytes; the factory converts them to what the message class expects
(numpy arrays for rosbags, ``array.array``/numpy for rclpy).

Type names use the ROS 2 form ``pkg/msg/Name``.
"""
from __future__ import annotations

import array
import importlib
import math
from typing import Any

import numpy as np

__all__ = ["RosbagsFactory", "RclpyFactory", "split_stamp", "stamp_to_ns"]

# ROS base type -> numpy dtype for numeric sequences/arrays (as rosbags stores them).
_NUMPY_BASE = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "octet": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}

# array.array typecode -> numpy dtype (used to coerce values for rclpy fields).
_ARRAY_TYPECODE_DTYPE = {
    "b": np.int8, "B": np.uint8, "h": np.int16, "H": np.uint16,
    "i": np.int32, "I": np.uint32, "l": np.int64, "L": np.uint64,
    "q": np.int64, "Q": np.uint64, "f": np.float32, "d": np.float64,
}


def split_stamp(stamp_s: float) -> tuple[int, int]:
    """Split a time in seconds into ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``.

    Rounds to the nearest nanosecond (float64 resolution near 1.7e9 s is about
    0.24 us, so sub-microsecond digits are not meaningful anyway).
    """
    stamp_s = float(stamp_s)
    if not math.isfinite(stamp_s):
        raise ValueError(f"stamp must be finite, got {stamp_s}")
    sec = math.floor(stamp_s)
    nsec = int(round((stamp_s - sec) * 1e9))
    if nsec >= 1_000_000_000:
        sec += 1
        nsec -= 1_000_000_000
    return int(sec), nsec


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces Time (duck-typed) or of a float in seconds."""
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    sec, nsec = split_stamp(float(stamp))
    return sec * 1_000_000_000 + nsec


def _split_typename(typename: str) -> tuple[str, str, str]:
    parts = typename.split("/")
    if len(parts) == 2:  # 'sensor_msgs/Image' -> assume msg
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"type name must look like 'pkg/msg/Name', got {typename!r}")
    return parts[0], parts[1], parts[2]


def _normalise_typename(typename: str) -> str:
    return "/".join(_split_typename(typename))


class _FactoryBase:
    """Shared helpers (headers, times) built on top of ``make``."""

    def make(self, typename: str, **fields: Any) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def make_time(self, stamp_s: float) -> Any:
        """builtin_interfaces/msg/Time for a time in seconds."""
        sec, nsec = split_stamp(stamp_s)
        return self.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec)

    def make_time_ns(self, stamp_ns: int) -> Any:
        """builtin_interfaces/msg/Time for an integer time in nanoseconds."""
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec)

    def make_header(self, stamp_s: float, frame_id: str = "") -> Any:
        """std_msgs/msg/Header with ``stamp`` = ``stamp_s`` seconds and ``frame_id``."""
        return self.make("std_msgs/msg/Header", stamp=self.make_time(stamp_s), frame_id=str(frame_id))


class RosbagsFactory(_FactoryBase):
    """Builds rosbags dataclasses from ``get_typestore(Stores.ROS2_JAZZY)``.

    Parameters
    ----------
    typestore:
        Optional rosbags ``Typestore``; default: the ROS 2 Jazzy store.
    """

    def __init__(self, typestore: Any = None):
        if typestore is None:
            from rosbags.typesys import Stores, get_typestore

            typestore = get_typestore(Stores.ROS2_JAZZY)
        self.typestore = typestore

    # -- construction -------------------------------------------------------
    def _cls(self, typename: str):
        try:
            return self.typestore.types[typename]
        except KeyError:
            raise ValueError(f"unknown message type {typename!r} in the rosbags type store") from None

    def _default(self, desc: Any) -> Any:
        from rosbags.interfaces import Nodetype

        kind, arg = desc
        if kind == Nodetype.BASE:
            base = arg[0]
            if base in ("string", "wstring"):
                return ""
            if base == "bool":
                return False
            if base in ("float32", "float64"):
                return 0.0
            return 0
        if kind == Nodetype.NAME:
            return self.make(arg)
        sub, length = arg
        if sub[0] == Nodetype.BASE and sub[1][0] in _NUMPY_BASE:
            n = length if kind == Nodetype.ARRAY else 0
            return np.zeros(n, dtype=_NUMPY_BASE[sub[1][0]])
        if kind == Nodetype.ARRAY:
            return [self._default(sub) for _ in range(length)]
        return []

    def _coerce(self, desc: Any, value: Any, typename: str, name: str) -> Any:
        from rosbags.interfaces import Nodetype

        kind, arg = desc
        if kind == Nodetype.NAME:
            if isinstance(value, dict):
                return self.make(arg, **value)
            return value
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            sub, length = arg
            if sub[0] == Nodetype.BASE and sub[1][0] in _NUMPY_BASE:
                dtype = _NUMPY_BASE[sub[1][0]]
                if isinstance(value, (bytes, bytearray, memoryview)):
                    out = np.frombuffer(value, dtype=np.uint8).astype(dtype, copy=True)
                elif isinstance(value, array.array):
                    out = np.asarray(value).astype(dtype, copy=True)
                else:
                    out = np.asarray(value)
                    if out.dtype != dtype:
                        out = out.astype(dtype)
                    out = np.ascontiguousarray(out).reshape(-1)
                if kind == Nodetype.ARRAY and out.size != length:
                    raise ValueError(f"{typename}.{name} needs exactly {length} values, got {out.size}")
                return out
            if sub[0] == Nodetype.NAME:
                return [self.make(sub[1], **v) if isinstance(v, dict) else v for v in value]
            return list(value)
        return value

    def make(self, typename: str, **fields: Any) -> Any:
        """Instantiate ``typename`` with ``fields``; omitted fields get ROS defaults."""
        typename = _normalise_typename(typename)
        cls = self._cls(typename)
        _, defs = self.typestore.fielddefs[typename]
        known = {n for n, _ in defs}
        unknown = set(fields) - known
        if unknown:
            raise ValueError(f"{typename} has no field(s) {sorted(unknown)}; fields are {[n for n, _ in defs]}")
        kwargs = {}
        for name, desc in defs:
            if name in fields:
                kwargs[name] = self._coerce(desc, fields[name], typename, name)
            else:
                kwargs[name] = self._default(desc)
        return cls(**kwargs)

    # -- CDR ------------------------------------------------------------------
    def serialize(self, msg: Any, typename: str | None = None) -> bytes:
        """CDR (little-endian) bytes of ``msg``; ``typename`` defaults to ``msg.__msgtype__``."""
        typename = _normalise_typename(typename or msg.__msgtype__)
        return bytes(self.typestore.serialize_cdr(msg, typename))

    def deserialize(self, raw: bytes | memoryview, typename: str) -> Any:
        """Dataclass from CDR bytes."""
        return self.typestore.deserialize_cdr(raw, _normalise_typename(typename))


class RclpyFactory(_FactoryBase):
    """Builds rclpy message objects (``sensor_msgs.msg.Image`` ...).

    The message module is imported lazily from the type name; rclpy itself is
    never initialised.  ``serialize``/``deserialize`` use ``rclpy.serialization``
    (imported lazily too).
    """

    def __init__(self):
        self._classes: dict[str, Any] = {}

    def _cls(self, typename: str):
        typename = _normalise_typename(typename)
        cls = self._classes.get(typename)
        if cls is None:
            pkg, sub, name = _split_typename(typename)
            try:
                module = importlib.import_module(f"{pkg}.{sub}")
                cls = getattr(module, name)
            except (ImportError, AttributeError) as exc:
                raise ValueError(f"cannot import message class for {typename!r}: {exc}") from exc
            self._classes[typename] = cls
        return cls

    def _coerce(self, msg: Any, name: str, value: Any) -> Any:
        current = getattr(msg, name)
        if isinstance(value, dict):
            for k, v in value.items():
                setattr(current, k, self._coerce(current, k, v))
            return current
        if isinstance(current, array.array):
            tc = current.typecode
            if isinstance(value, array.array) and value.typecode == tc:
                return value
            dtype = _ARRAY_TYPECODE_DTYPE[tc]
            if isinstance(value, (bytes, bytearray, memoryview)) and tc == "B":
                return array.array("B", bytes(value))
            arr = np.ascontiguousarray(np.asarray(value).reshape(-1), dtype=dtype)
            out = array.array(tc)
            out.frombytes(arr.tobytes())
            return out
        if isinstance(current, np.ndarray):
            return np.asarray(value, dtype=current.dtype).reshape(current.shape)
        if isinstance(current, (bytes, bytearray)) and isinstance(value, np.ndarray):
            return value.tobytes()
        if isinstance(current, bool):
            return bool(value)
        if isinstance(current, int) and not isinstance(current, bool) and isinstance(value, (np.integer, bool)):
            return int(value)
        if isinstance(current, float) and isinstance(value, (np.floating, np.integer, int)):
            return float(value)
        return value

    def make(self, typename: str, **fields: Any) -> Any:
        """Instantiate ``typename`` and set ``fields`` as attributes (dicts fill nested messages)."""
        msg = self._cls(typename)()
        for name, value in fields.items():
            if not hasattr(msg, name):
                raise ValueError(f"{typename} has no field {name!r}")
            setattr(msg, name, self._coerce(msg, name, value))
        return msg

    def serialize(self, msg: Any, typename: str | None = None) -> bytes:
        """CDR bytes via ``rclpy.serialization.serialize_message`` (typename unused)."""
        from rclpy.serialization import serialize_message

        return serialize_message(msg)

    def deserialize(self, raw: bytes | memoryview, typename: str) -> Any:
        """Message object from CDR bytes via ``rclpy.serialization.deserialize_message``."""
        from rclpy.serialization import deserialize_message

        return deserialize_message(bytes(raw), self._cls(typename))
