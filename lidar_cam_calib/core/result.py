"""One result type for every method, with YAML round-trip and safe file output.

The transform is ``T_child_parent``: it maps a point from the *parent* frame
(the range sensor, e.g. ``laser``) into the *child* frame (the camera optical
frame): ``p_camera = T_camera_lidar @ p_lidar``. Published on tf as
``header.frame_id = parent`` and ``child_frame_id = child``, the
TransformStamped carries the pose of the child in the parent, i.e.
``inv(T_camera_lidar)``; see :meth:`CalibrationResult.tf_translation_rotation`.
"""
from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import time
from typing import Any

import numpy as np
import yaml

from .geometry import inv_T, make_T, quat_from_R, R_from_quat, rpy_from_R

SCHEMA_VERSION = 1


class ResultFileError(RuntimeError):
    """Raised when a result file cannot be written or read."""


@dataclasses.dataclass
class CalibrationResult:
    method: str
    parent_frame: str
    child_frame: str
    T_child_parent: np.ndarray
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.full((6, 6), np.nan))
    metrics: dict = dataclasses.field(default_factory=dict)
    observations_used: int = 0
    input_topics: dict = dataclasses.field(default_factory=dict)
    stamps: list = dataclasses.field(default_factory=list)  # seconds, one per observation
    solver: str = ""
    created_unix_s: float = dataclasses.field(default_factory=time.time)
    notes: list = dataclasses.field(default_factory=list)

    # -- derived quantities ------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.T_child_parent)[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return np.asarray(self.T_child_parent)[:3, 3]

    def sigma(self) -> tuple[float, float]:
        """(rotation 1-sigma in degrees, translation 1-sigma in mm): the largest
        standard deviation over the three axes, from the covariance diagonal."""
        c = np.asarray(self.covariance, dtype=float)
        if not np.all(np.isfinite(np.diag(c))):
            return (math.nan, math.nan)
        d = np.sqrt(np.clip(np.diag(c), 0.0, None))
        return (float(np.degrees(d[:3].max())), float(d[3:].max() * 1000.0))

    def tf_translation_rotation(self) -> tuple[np.ndarray, np.ndarray]:
        """Translation and quaternion (x, y, z, w) of the TransformStamped with
        ``frame_id = parent`` and ``child_frame_id = child``: the child's pose
        in the parent frame, ``T_parent_child = inv(T_child_parent)``."""
        T_pc = inv_T(self.T_child_parent)
        return T_pc[:3, 3].copy(), quat_from_R(T_pc[:3, :3])

    def quality_key(self) -> tuple[float, float]:
        """Smaller is better: (rotation sigma, translation sigma) with NaN last."""
        r, t = self.sigma()
        return (r if math.isfinite(r) else math.inf, t if math.isfinite(t) else math.inf)

    def is_better_than(self, other: "CalibrationResult | None") -> bool:
        """True when this result is no worse than ``other``: both its rotation
        and translation uncertainties within 1 % of the other's or smaller.
        Whether results for different frame pairs or methods may replace each
        other is the node's policy, not decided here."""
        if other is None:
            return True
        r, t = self.quality_key()
        ro, to = other.quality_key()
        return r <= ro * 1.01 and t <= to * 1.01

    # -- YAML --------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        T = np.asarray(self.T_child_parent, dtype=float)
        tf_t, tf_q = self.tf_translation_rotation()
        rs, ts = self.sigma()
        rpy = np.degrees(rpy_from_R(T[:3, :3]))
        return {
            "schema_version": SCHEMA_VERSION,
            "method": self.method,
            "solver": self.solver,
            "convention": (f"p_{self.child_frame} = T @ p_{self.parent_frame}; "
                           "tf: frame_id=parent_frame, child_frame_id=child_frame, "
                           "transform = inv(T)"),
            "parent_frame": self.parent_frame,
            "child_frame": self.child_frame,
            "T_child_parent": [[float(v) for v in row] for row in T],
            "translation_m": [float(v) for v in T[:3, 3]],
            "quaternion_xyzw": [float(v) for v in quat_from_R(T[:3, :3])],
            "rpy_deg": [float(v) for v in rpy],
            "tf_parent_to_child": {
                "translation_m": [float(v) for v in tf_t],
                "quaternion_xyzw": [float(v) for v in tf_q],
            },
            "covariance_rot_first": [[_f(v) for v in row] for row in np.asarray(self.covariance, dtype=float)],
            "sigma_rotation_deg": _f(rs),
            "sigma_translation_mm": _f(ts),
            "metrics": {k: to_plain(v) for k, v in self.metrics.items()},
            "observations_used": int(self.observations_used),
            "input_topics": dict(self.input_topics),
            "stamps_s": [float(s) for s in self.stamps],
            "created_unix_s": float(self.created_unix_s),
            "notes": list(self.notes),
        }

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=120)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CalibrationResult":
        if "T_child_parent" in d:
            T = np.array(d["T_child_parent"], dtype=float)
        else:
            T = make_T(R_from_quat(d["quaternion_xyzw"]), d["translation_m"])
        cov = d.get("covariance_rot_first")
        cov = np.array(cov, dtype=float) if cov is not None else np.full((6, 6), np.nan)
        return cls(
            method=d.get("method", ""), parent_frame=d.get("parent_frame", ""),
            child_frame=d.get("child_frame", ""), T_child_parent=T, covariance=cov,
            metrics=dict(d.get("metrics") or {}), observations_used=int(d.get("observations_used", 0)),
            input_topics=dict(d.get("input_topics") or {}), stamps=list(d.get("stamps_s") or []),
            solver=d.get("solver", ""), created_unix_s=float(d.get("created_unix_s", 0.0)),
            notes=list(d.get("notes") or []),
        )

    @classmethod
    def from_yaml(cls, text: str) -> "CalibrationResult":
        d = yaml.safe_load(text)
        if not isinstance(d, dict):
            raise ResultFileError("result YAML is not a mapping")
        return cls.from_dict(d)

    @classmethod
    def load(cls, path: str) -> "CalibrationResult":
        try:
            with open(path, "r", encoding="utf-8") as f:
                return cls.from_yaml(f.read())
        except (OSError, yaml.YAMLError, KeyError, ValueError, TypeError) as e:
            raise ResultFileError(f"cannot read calibration result {path!r}: {e}") from e


def _f(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def to_plain(v: Any) -> Any:
    """Plain YAML/JSON values: numpy scalars and arrays to Python, NaN/inf to None."""
    if isinstance(v, (np.floating, float)):
        return _f(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return [to_plain(x) for x in v.tolist()]
    if isinstance(v, (list, tuple)):
        return [to_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): to_plain(x) for k, x in v.items()}
    return v


_SPECIAL_ROOTS = ("/proc", "/sys", "/dev")


def _file_mode() -> int:
    """0666 under the process umask (0644 under umask 022), as any file."""
    try:
        with open("/proc/self/status", "r", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def check_output_path(path: str) -> str:
    """Absolute path for a result file, or :class:`ResultFileError` when it
    cannot be one: an existing directory, device or other non-regular file,
    anything under /proc, /sys or /dev, or a parent that is not a directory.
    Nothing is created or touched."""
    p = os.path.abspath(os.path.expanduser(path))
    real = os.path.realpath(p)
    if any(real == r or real.startswith(r + "/") for r in _SPECIAL_ROOTS):
        raise ResultFileError(f"{p} is under /{real.split('/')[1]}: not a place for a result file")
    if os.path.lexists(p) and not os.path.isfile(p):
        kind = "a directory" if os.path.isdir(p) else "not a regular file"
        raise ResultFileError(f"{p} is {kind}: give the path of a YAML file")
    parent = os.path.dirname(p)
    while parent and not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if parent and not os.path.isdir(parent):
        raise ResultFileError(f"{parent} is not a directory, so {p} cannot be created")
    return p


def write_atomic(path: str, text: str, keep_bak: bool = True) -> None:
    """Write ``text`` to ``path`` atomically: temp file in the same directory,
    fsync, rename, with the mode any new file gets under the umask. The
    previous file, if any, is kept as ``path + '.bak'``. Raises
    :class:`ResultFileError` with a clear message on failure; the old file is
    untouched in that case, and nothing is written where
    :func:`check_output_path` refuses."""
    path = check_output_path(path)
    d = os.path.dirname(path)
    try:
        os.makedirs(d, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".yaml", dir=d)
    except OSError as e:
        raise ResultFileError(f"cannot write result to {path!r}: {e.strerror or e}") from e
    try:
        os.fchmod(fd, _file_mode())
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if keep_bak and os.path.isfile(path):
            os.replace(path, path + ".bak")
        os.replace(tmp, path)
        try:
            dfd = os.open(d, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass
    except OSError as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise ResultFileError(f"cannot write result to {path!r}: {e.strerror or e}") from e


@dataclasses.dataclass
class CalibrationSet:
    """The results of one fit of one method: one :class:`CalibrationResult`
    per child frame (the board method's cameras), plus what relates them.

    A set with one result under the key ``""`` is a single calibration and
    its YAML is exactly :meth:`CalibrationResult.to_yaml`'s; otherwise the
    YAML holds ``cameras: {name: <single-result fields>}``, ``extras`` (e.g.
    ``camera_to_camera``) and ``refused: {name: reason}`` for cameras that
    were not calibrated."""
    method: str
    results: dict
    extras: dict = dataclasses.field(default_factory=dict)
    refused: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def single(cls, result: CalibrationResult) -> "CalibrationSet":
        return cls(result.method, {"": result})

    @property
    def is_single(self) -> bool:
        return list(self.results) == [""]

    def frame_pairs(self) -> dict:
        """name -> (parent_frame, child_frame)."""
        return {k: (r.parent_frame, r.child_frame) for k, r in self.results.items()}

    def to_dict(self) -> dict[str, Any]:
        if self.is_single and not self.extras and not self.refused:
            return self.results[""].to_dict()
        return {"schema_version": SCHEMA_VERSION, "method": self.method,
                "cameras": {k: r.to_dict() for k, r in self.results.items()},
                "extras": to_plain(self.extras), "refused": dict(self.refused)}

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=120)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CalibrationSet":
        if "cameras" in d:
            res = {str(k): CalibrationResult.from_dict(v) for k, v in (d.get("cameras") or {}).items()}
            return cls(d.get("method", ""), res, dict(d.get("extras") or {}), dict(d.get("refused") or {}))
        return cls.single(CalibrationResult.from_dict(d))

    @classmethod
    def from_yaml(cls, text: str) -> "CalibrationSet":
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ResultFileError(f"result YAML does not parse: {e}") from e
        if not isinstance(d, dict):
            raise ResultFileError("result YAML is not a mapping")
        try:
            return cls.from_dict(d)
        except (KeyError, ValueError, TypeError) as e:
            raise ResultFileError(f"result YAML is incomplete: {e}") from e

    @classmethod
    def load(cls, path: str) -> "CalibrationSet":
        try:
            with open(path, "r", encoding="utf-8") as f:
                text = f.read()
        except OSError as e:
            raise ResultFileError(f"cannot read calibration result {path!r}: {e.strerror or e}") from e
        try:
            return cls.from_yaml(text)
        except ResultFileError as e:
            raise ResultFileError(f"cannot read calibration result {path!r}: {e}") from e
