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
        """True when this result should replace ``other`` on disk.

        A result replaces another only when both its rotation and translation
        uncertainties are no worse (within 1 %), or when the other is for a
        different frame pair / method (then it is not comparable and the
        caller decides)."""
        if other is None:
            return True
        if (other.parent_frame, other.child_frame) != (self.parent_frame, self.child_frame):
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
            "metrics": {k: _plain(v) for k, v in self.metrics.items()},
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


def _plain(v: Any) -> Any:
    if isinstance(v, (np.floating, float)):
        return _f(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.ndarray):
        return [_plain(x) for x in v.tolist()]
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    return v


def write_atomic(path: str, text: str, keep_bak: bool = True) -> None:
    """Write ``text`` to ``path`` atomically: temp file in the same directory,
    fsync, rename. The previous file, if any, is kept as ``path + '.bak'``.
    Raises :class:`ResultFileError` with a clear message on failure; the old
    file is untouched in that case."""
    path = os.path.abspath(os.path.expanduser(path))
    d = os.path.dirname(path)
    try:
        os.makedirs(d, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".yaml", dir=d)
    except OSError as e:
        raise ResultFileError(f"cannot write result to {path!r}: {e.strerror or e}") from e
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if keep_bak and os.path.exists(path):
            bak = path + ".bak"
            try:
                os.replace(path, bak)
            except OSError:
                pass
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


def save_if_better(result: CalibrationResult, path: str, force: bool = False) -> tuple[bool, str]:
    """Write ``result`` to ``path`` unless the file there holds a better one.

    Returns ``(written, reason)``. An unreadable existing file is kept as
    ``.bak`` and replaced. Raises :class:`ResultFileError` if writing fails."""
    old = None
    if os.path.exists(path) and not force:
        try:
            old = CalibrationResult.load(path)
        except ResultFileError:
            old = None
    if old is not None and not result.is_better_than(old):
        ro, to = old.sigma()
        rn, tn = result.sigma()
        return False, (f"kept {path}: it holds a better calibration "
                       f"(sigma {ro:.3f} deg / {to:.2f} mm vs new {rn:.3f} deg / {tn:.2f} mm)")
    write_atomic(path, result.to_yaml(), keep_bak=True)
    return True, f"wrote {path}"


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
                "extras": _plain(self.extras), "refused": dict(self.refused)}

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
