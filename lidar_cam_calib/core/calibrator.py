"""The shape every method's calibrator has, and described config fields (ROS-free).

A method provides a config dataclass whose fields are declared with
:func:`cfg_field` (help text, allowed range or choices, list length), and a
calibrator that satisfies :class:`Calibrator`. The node base turns the config
fields into ROS parameters (description, range, validation at start-up and
on ``ros2 param set``), owns the collect / fit / adopt / publish cycle, and
calls only the methods below.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol, runtime_checkable

from .errors import ConfigError


@dataclasses.dataclass
class Verdict:
    """Answer of :meth:`Calibrator.add`: accepted or not, and why."""
    accepted: bool
    reason: str


@runtime_checkable
class Calibrator(Protocol):
    """Collects frames of one method and solves the extrinsic(s)."""

    cfg: Any

    def add(self, frame: Any) -> Verdict:
        """Take one synchronised frame (the method's own frame type)."""

    def ready(self) -> bool:
        """True when enough frames are in for :meth:`fit`."""

    def fit(self) -> Any:
        """A :class:`~lidar_cam_calib.core.result.CalibrationResult` or
        :class:`~lidar_cam_calib.core.result.CalibrationSet`; raises a
        :class:`~lidar_cam_calib.core.errors.CalibError` with the reason."""

    def status(self) -> dict:
        """JSON-able progress: frames collected / needed, advice, last reason."""

    def reset(self) -> None:
        """Drop every collected frame."""


COUNT_KEYS = ("observations", "placements", "frames_collected", "frames")


def collected_count(status: dict) -> int:
    """How many frames a calibrator's ``status()`` says it holds (methods name
    them observations, placements or frames)."""
    for k in COUNT_KEYS:
        if isinstance(status.get(k), int):
            return int(status[k])
    return 0


def cfg_field(default: Any, help: str, *, range: tuple | None = None, choices: tuple | None = None,
              length: int | tuple | None = None, exclusive_min: bool = False, param: bool = True,
              read_only: bool = False) -> Any:
    """A dataclass field with what a user needs to set it.

    ``range``: (lo, hi) inclusive (``exclusive_min``: lo itself not allowed);
    for lists, every element. ``choices``: allowed values. ``length``: the
    list length, or (min, max). ``param=False``: not exposed as a parameter.
    ``read_only``: cannot change after start-up (files, topics, frames)."""
    meta = {"help": help, "range": range, "choices": choices, "length": length,
            "exclusive_min": exclusive_min, "param": param, "read_only": read_only}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def allowed_text(meta: dict) -> str:
    """Human text for what a field allows, e.g. '0 < x <= 10' or 'one of a, b'."""
    parts = []
    if meta.get("choices"):
        parts.append("one of " + ", ".join(str(c) for c in meta["choices"]))
    ln = meta.get("length")
    if ln is not None:
        parts.append(f"a list of {ln} numbers" if isinstance(ln, int)
                     else f"a list of {ln[0]} to {ln[1]} numbers")
    rg = meta.get("range")
    if rg is not None:
        lo, hi = rg
        op = "<" if meta.get("exclusive_min") else "<="
        parts.append(f"{lo} {op} value <= {hi}" + (" (each element)" if ln is not None else ""))
    return "; ".join(parts) or "any value of the default's type"


def check_value(name: str, value: Any, meta: dict, default: Any = None) -> Any:
    """Validate one value against a field's metadata; return it normalised
    (ints widened to float where the default is a float, lists to tuples where
    the default is a tuple). Raises :class:`ConfigError` naming the parameter,
    the value and what is allowed."""
    def bad() -> ConfigError:
        return ConfigError(f"parameter {name}={value!r} is not allowed: {allowed_text(meta)}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
    elif isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(default, (tuple, list)) or meta.get("length") is not None:
        if not isinstance(value, (list, tuple)):
            raise bad()
        ln = meta.get("length")
        if isinstance(ln, int) and len(value) != ln:
            raise bad()
        if isinstance(ln, tuple) and not (ln[0] <= len(value) <= ln[1]):
            raise bad()
        elems = list(value)
        value = tuple(elems) if isinstance(default, tuple) else list(elems)
    else:
        elems = [value]
    if meta.get("choices") and value not in meta["choices"]:
        raise bad()
    rg = meta.get("range")
    if rg is not None:
        lo, hi = rg
        for e in elems:
            if isinstance(e, bool) or not isinstance(e, (int, float)) or not math.isfinite(float(e)):
                raise bad()
            if e > hi or e < lo or (meta.get("exclusive_min") and e == lo):
                raise bad()
    return value


def validate_config(cfg: Any) -> None:
    """Check every described field of a config dataclass (recursively for
    nested dataclasses); raise :class:`ConfigError` on the first bad one."""
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            validate_config(v)
        elif "help" in f.metadata:
            default = f.default if f.default is not dataclasses.MISSING else v
            check_value(f.name, v, f.metadata, default)


__all__ = ["Calibrator", "Verdict", "allowed_text", "cfg_field", "check_value", "collected_count", "validate_config"]
