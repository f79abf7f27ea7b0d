"""rosbag2 (MCAP) writing and reading without ROS, on top of rosbags and mcap.

Writing: :class:`BagWriter` produces a normal rosbag2 bag *directory*
(``metadata.yaml`` + one ``.mcap`` file) that ``ros2 bag play`` accepts.

Reading: :func:`read_bag` yields :class:`BagRecord` (topic, typename, stamp_ns,
raw CDR bytes) in log-time order.  ``path`` may be

* a rosbag2 directory with MCAP storage (with or without ``metadata.yaml``),
* a single ``.mcap`` file (no ``metadata.yaml`` needed),
* a rosbag2 directory with sqlite3 storage (``.db3``, read through rosbags).

MCAP data is read with the ``mcap`` package.  Deserialise ``raw`` with
``RosbagsFactory().deserialize(raw, typename)``.

Errors: a missing path, a directory without bag files, an empty file, a
bag without messages or a damaged/truncated file raise :class:`BagError`
(never a raw struct/Value error).  **Truncated MCAP files** (e.g. a recording
killed mid-write, no summary section) are read *linearly*: every message of
every complete chunk before the cut is yielded first (in file order, which is
log-time order for rosbag2 recordings), then ``BagError`` is raised
mentioning the truncation.  ``read_bag`` itself checks that the path exists
before returning the iterator, so a missing bag fails at the call.
"""
from __future__ import annotations

import heapq
import os
from pathlib import Path
from typing import Any, Iterator, NamedTuple

__all__ = ["BagError", "BagRecord", "BagWriter", "read_bag", "bag_topics", "bag_message_counts", "default_qos"]


class BagError(RuntimeError):
    """A bag could not be opened, written or completely read."""


class BagRecord(NamedTuple):
    topic: str
    typename: str
    stamp_ns: int  # log (receive/record) time, nanoseconds since epoch
    raw: bytes  # CDR-serialised message


def default_qos(topic: str, reliable: bool = True, transient_local: bool | None = None, depth: int = 10):
    """A rosbags ``Qos``: KEEP_LAST(depth), RELIABLE (or BEST_EFFORT), VOLATILE.

    ``/tf_static`` (or ``transient_local=True``) gets TRANSIENT_LOCAL durability
    so late subscribers still receive it on playback.
    """
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    if transient_local is None:
        transient_local = topic.rstrip("/").endswith("tf_static")
    zero = QosTime(0, 0)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=max(int(depth), 1),
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


class BagWriter:
    """Context manager writing a rosbag2 MCAP bag directory at ``path``.

    >>> with BagWriter('out_bag') as bw:
    ...     bw.write('/scan', 'sensor_msgs/msg/LaserScan', stamp_ns, scan_msg)

    ``msg`` is a rosbags dataclass (serialised to CDR here) or already
    serialised CDR ``bytes``.  Connections are registered on first use of a
    topic; ``qos`` (a rosbags ``Qos``) can be given on that first write,
    default :func:`default_qos`.  ``path`` must not exist yet (rosbag2 rule).
    """

    def __init__(self, path: str | os.PathLike, typestore: Any = None, version: int = 9, compress: bool = False):
        self.path = Path(path)
        self.compress = bool(compress)
        self._typestore = typestore
        self._version = version
        self._writer = None
        self._conns: dict[str, Any] = {}
        self.count = 0

    @property
    def typestore(self):
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.ROS2_JAZZY)
        return self._typestore

    def open(self) -> "BagWriter":
        """Create the bag; with ``compress`` its MCAP chunks are zstd-compressed
        (as ``ros2 bag record --storage-preset-profile zstd_fast``; every reader
        decompresses transparently), falling back to plain chunks where the
        rosbags version has no storage compression."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        if self.path.exists():
            raise BagError(f"cannot write bag: {self.path} already exists")
        try:
            self._writer = Writer(self.path, version=self._version, storage_plugin=StoragePlugin.MCAP)
            if self.compress:
                try:
                    from rosbags.rosbag2 import CompressionFormat, CompressionMode

                    self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
                except (ImportError, AttributeError, ValueError):
                    pass
            self._writer.open()
        except Exception as exc:
            self._writer = None
            raise BagError(f"cannot create bag {self.path}: {exc}") from exc
        return self

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        if self._writer is not None:
            w, self._writer = self._writer, None
            try:
                w.close()
            except Exception as exc:
                raise BagError(f"cannot finish bag {self.path}: {exc}") from exc

    def write(self, topic: str, typename: str, stamp_ns: int, msg: Any, qos: Any = None) -> None:
        """Append ``msg`` on ``topic`` with log time ``stamp_ns`` (int nanoseconds)."""
        if self._writer is None:
            raise BagError("BagWriter is not open (use it as a context manager)")
        conn = self._conns.get(topic)
        if conn is None:
            try:
                conn = self._writer.add_connection(
                    topic,
                    typename,
                    typestore=self.typestore,
                    offered_qos_profiles=[qos if qos is not None else default_qos(topic)],
                )
            except Exception as exc:
                raise BagError(f"cannot add topic {topic} ({typename}): {exc}") from exc
            self._conns[topic] = conn
        elif conn.msgtype != typename:
            raise BagError(f"topic {topic} was registered as {conn.msgtype}, not {typename}")
        if isinstance(msg, (bytes, bytearray, memoryview)):
            raw = msg
        else:
            raw = self.typestore.serialize_cdr(msg, typename)
        self._writer.write(conn, int(stamp_ns), raw)
        self.count += 1


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------
def _resolve(path: str | os.PathLike) -> tuple[str, list[Path]]:
    """Return (kind, files): kind 'mcap' (list of .mcap files) or 'rosbags' (directory)."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"bag not found: {p}")
    if p.is_file():
        if p.stat().st_size == 0:
            raise BagError(f"bag file is empty (0 bytes): {p}")
        if p.suffix == ".mcap":
            return "mcap", [p]
        if p.suffix == ".db3":
            return "rosbags", [p.parent]
        raise BagError(f"not a bag file (expected .mcap or a rosbag2 directory): {p}")
    meta = p / "metadata.yaml"
    mcaps: list[Path] = []
    if meta.is_file():
        try:
            import yaml

            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = info.get("storage_identifier", "")
            rel = info.get("relative_file_paths", [])
        except Exception as exc:
            raise BagError(f"cannot parse {meta}: {exc}") from exc
        if storage == "sqlite3":
            return "rosbags", [p]
        mcaps = [p / r for r in rel if str(r).endswith(".mcap")]
        missing = [str(m) for m in mcaps if not m.is_file()]
        if missing:
            raise BagError(f"bag {p} lists files that do not exist: {missing}")
    if not mcaps:
        mcaps = sorted(p.glob("*.mcap"))
        if not mcaps:
            if any(p.glob("*.db3")):
                return "rosbags", [p]
            raise BagError(f"no bag files (.mcap/.db3) in directory {p}")
    for m in mcaps:
        if m.stat().st_size == 0:
            raise BagError(f"bag file is empty (0 bytes): {m}")
    return "mcap", mcaps


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _iter_mcap_file(path: Path) -> Iterator[BagRecord]:
    from mcap.reader import NonSeekingReader, make_reader

    try:
        f = open(path, "rb")
    except OSError as exc:
        raise BagError(f"cannot open {path}: {exc}") from exc
    truncated_note = ""
    with f:
        try:
            reader = make_reader(f)
            summary = None
            try:
                summary = reader.get_summary()
            except Exception:  # noqa: BLE001 - any summary failure means: read linearly
                summary = None  # no/invalid summary: truncated or unindexed; read linearly
            if summary is not None and summary.chunk_indexes:
                it = reader.iter_messages(log_time_order=True)
            else:
                f.seek(0)
                # log_time_order=True would buffer the whole file before yielding anything;
                # linear (file) order streams, and rosbag2 appends in arrival order.
                it = NonSeekingReader(f).iter_messages(log_time_order=False)
                truncated_note = " (file has no summary section: it is probably truncated)"
            for schema, channel, message in it:
                yield BagRecord(
                    channel.topic,
                    schema.name if schema is not None else "",
                    int(message.log_time),
                    bytes(message.data),
                )
        except BagError:
            raise
        except Exception as exc:
            raise BagError(
                f"bag file {path} is damaged or truncated{truncated_note}: {_describe(exc)}"
            ) from exc


def _iter_rosbags_dir(path: Path) -> Iterator[BagRecord]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
            for conn, stamp, raw in reader.messages():
                yield BagRecord(conn.topic, conn.msgtype, int(stamp), bytes(raw))
    except BagError:
        raise
    except Exception as exc:
        raise BagError(f"cannot read bag {path}: {_describe(exc)}") from exc


def read_bag(path: str | os.PathLike, topics: list[str] | None = None) -> Iterator[BagRecord]:
    """Iterate over the messages of a bag in log-time order.

    ``path``: bag directory or a single ``.mcap`` file; ``topics``: optional
    filter.  The path is validated immediately (``BagError`` if missing or
    empty); damage found while reading raises ``BagError`` after the
    complete messages before it were yielded.  A bag holding no message
    raises ``BagError`` too.
    """
    kind, files = _resolve(path)
    wanted = set(topics) if topics is not None else None

    def gen() -> Iterator[BagRecord]:
        if kind == "rosbags":
            source: Iterator[BagRecord] = _iter_rosbags_dir(files[0])
        elif len(files) == 1:
            source = _iter_mcap_file(files[0])
        else:  # split bag: merge the (individually ordered) files by log time
            source = heapq.merge(*(_iter_mcap_file(f) for f in files), key=lambda r: r.stamp_ns)
        n = 0
        for rec in source:
            n += 1
            if wanted is None or rec.topic in wanted:
                yield rec
        if n == 0:
            raise BagError(f"bag {path} contains no messages")

    return gen()


def bag_topics(path: str | os.PathLike) -> dict[str, str]:
    """Map topic -> typename of a bag (directory or single .mcap file).

    Uses the MCAP summary (or rosbags metadata for sqlite3 bags); a file
    without a readable summary (truncated) raises ``BagError``.
    """
    kind, files = _resolve(path)
    if kind == "rosbags":
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        try:
            with AnyReader([files[0]], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
                return {c.topic: c.msgtype for c in reader.connections}
        except Exception as exc:
            raise BagError(f"cannot read bag {files[0]}: {_describe(exc)}") from exc
    from mcap.reader import make_reader

    out: dict[str, str] = {}
    for fpath in files:
        try:
            with open(fpath, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception as exc:
            raise BagError(f"bag file {fpath} is damaged or truncated: {_describe(exc)}") from exc
        if summary is None:
            raise BagError(f"bag file {fpath} has no summary section (truncated or unindexed)")
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            out[ch.topic] = schema.name if schema is not None else ""
    return out


def bag_message_counts(path: str | os.PathLike) -> dict[str, int]:
    """Topic -> number of messages from the MCAP summary statistics; empty
    when the bag has none (truncated, sqlite3): a progress display only."""
    try:
        kind, files = _resolve(path)
    except BagError:
        return {}
    if kind != "mcap":
        return {}
    from mcap.reader import make_reader

    out: dict[str, int] = {}
    for fpath in files:
        try:
            with open(fpath, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - no readable summary: no counts
            return {}
        if summary is None or summary.statistics is None:
            return {}
        for cid, n in summary.statistics.channel_message_counts.items():
            ch = summary.channels.get(cid)
            if ch is not None:
                out[ch.topic] = out.get(ch.topic, 0) + int(n)
    return out
