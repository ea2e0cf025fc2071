"""One streaming reader over the logs rosbags reads: ROS 1 bags (``.bag``), ROS 2 bag folders
(``metadata.yaml`` with sqlite3 or MCAP storage) and bare ``.mcap`` files. Messages come one at a
time (never the whole log in memory); every failure of the file (truncated, corrupt, an unknown
message type) is one :class:`~graphcal.errors.DatasetError` naming the log, the topic and what was
expected."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

from graphcal.errors import DatasetError

__all__ = ["LogTopic", "LogReader", "types_from_msg_dir", "log_kind", "default_typestore"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LogTopic:
    """A topic of the log: ``name``, ROS message type ``msgtype`` (``pkg/msg/Name``) and ``count``
    (messages, when the log's index says; 0 if unknown)."""

    name: str
    msgtype: str
    count: int


def log_kind(path: Path) -> str:
    """``ros1`` (a ``.bag`` file), ``ros2`` (a folder with ``metadata.yaml``), ``mcap`` (a bare
    ``.mcap`` file) or ``csv``; DatasetError for anything else."""
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return "ros2"
        raise DatasetError(path, "folder", "a ROS 2 bag folder with metadata.yaml", "no metadata.yaml")
    if not path.exists():
        raise DatasetError(path, "file", "an existing log file or ROS 2 bag folder", "nothing there")
    suffix = path.suffix.lower()
    if suffix in (".bag", ".mcap", ".csv"):
        return {".bag": "ros1", ".mcap": "mcap", ".csv": "csv"}[suffix]
    raise DatasetError(path, "file name", "a .bag, .mcap or .csv file, or a ROS 2 bag folder", path.name)


def types_from_msg_dir(msg_dir: Path) -> dict:
    """Message types from ``.msg`` files under ``msg_dir`` (``<pkg>/msg/<Name>.msg``, or
    ``<pkg>/<Name>.msg``): rosbags' type dictionary, ready to register."""
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    files = sorted(Path(msg_dir).rglob("*.msg"))
    if not files:
        raise DatasetError(msg_dir, "--msg-dir", "a folder with <pkg>/msg/<Name>.msg files", "no .msg file")
    for f in files:
        pkg = f.parent.parent.name if f.parent.name == "msg" else f.parent.name
        name = f"{pkg}/msg/{f.stem}"
        try:
            types.update(get_types_from_msg(f.read_text(encoding="utf-8"), name))
        except Exception as exc:  # rosbags' parser errors have several classes
            raise DatasetError(f, "definition", f"a ROS .msg definition of {name}", str(exc)) from None
    return types


def default_typestore(kind: str):
    """rosbags' type store for a log kind (``ros1``: Noetic, else Humble), with
    ``tf2_msgs/msg/TFMessage`` added where the store lacks it (Noetic's)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.fielddefs:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return store


class LogReader:
    """``with LogReader(path, extra_types) as r:`` ``r.topics`` and ``r.messages(topics)``.

    Args:
        path: a ``.bag`` file, a ROS 2 bag folder or a bare ``.mcap`` file.
        extra_types: message types to register (from :func:`types_from_msg_dir`), for types neither
            rosbags' type store nor the log's embedded definitions know.
    """

    def __init__(self, path: str | Path, extra_types: dict | None = None):
        self.path = Path(path)
        self.kind = log_kind(self.path)
        self.extra_types = dict(extra_types or {})
        self._reader: Any = None
        self._typestore: Any = None
        self._connections: list = []
        self.topics: dict[str, LogTopic] = {}

    def __enter__(self) -> LogReader:
        default = default_typestore(self.kind)
        try:
            if self.kind == "mcap":
                self._open_bare_mcap(default)
            else:
                from rosbags.highlevel import AnyReader

                self._reader = AnyReader([self.path], default_typestore=default)
                self._reader.open()
                self._typestore = self._reader.typestore
                self._connections = list(self._reader.connections)
                self._register_missing(default)
        except DatasetError:
            raise
        except Exception as exc:  # rosbags raises many classes for a damaged file
            raise DatasetError(self.path, "file", f"a readable {self._what()}", _reason(exc)) from None
        for c in self._connections:
            prev = self.topics.get(c.topic)
            if prev is not None and prev.msgtype != c.msgtype:
                raise DatasetError(self.path, f"topic {c.topic}", "one message type per topic",
                                   f"{prev.msgtype} and {c.msgtype}")
            self.topics[c.topic] = LogTopic(c.topic, c.msgtype, (prev.count if prev else 0) + int(c.msgcount or 0))
        return self

    def _what(self) -> str:
        return {"ros1": "ROS 1 bag", "ros2": "ROS 2 bag", "mcap": "MCAP file"}[self.kind]

    def _open_bare_mcap(self, default) -> None:
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.rosbag2.storage_mcap import McapReader
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        self._reader = McapReader(self.path)
        self._reader.open()
        self._connections = list(self._reader.connections)
        types: dict = {}
        for c in self._connections:
            if c.msgdef.format == MessageDefinitionFormat.MSG and c.msgdef.data:
                types.update(get_types_from_msg(c.msgdef.data, c.msgtype))
            elif c.msgdef.format == MessageDefinitionFormat.IDL and c.msgdef.data:
                types.update(get_types_from_idl(c.msgdef.data))
        self._typestore = get_typestore(Stores.EMPTY)
        self._typestore.register(types)
        self._register_missing(default)

    def _register_missing(self, default) -> None:
        """Register the user's types, then the default store's for types the log did not define."""
        have = set(self._typestore.fielddefs)
        extra = {k: v for k, v in self.extra_types.items() if k not in have}
        if extra:
            self._typestore.register(extra)
        have = set(self._typestore.fielddefs)
        missing = {k: v for k, v in default.fielddefs.items() if k not in have}
        if missing:
            self._typestore.register(missing)

    def __exit__(self, *exc) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # closing a damaged file may fail again; the first error counts
                pass

    def check_type_known(self, topic: str) -> None:
        """DatasetError when ``topic``'s message type cannot be deserialised (not in rosbags' store,
        not embedded in the log, not given with --msg-dir)."""
        t = self.topics[topic]
        if t.msgtype not in self._typestore.fielddefs:
            raise DatasetError(self.path, f"topic {topic}", f"a known message type (give the .msg of "
                               f"{t.msgtype} with --msg-dir)", t.msgtype)

    def messages(self, topics: Sequence[str], start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[tuple[str, int, Any]]:
        """``(topic, receive time in ns, raw bytes)`` of the ``topics``, in the log's order (receive
        time), received in [start_ns, stop_ns) when given (the log's index finds them without reading
        the rest); read lazily. Use :meth:`deserialize` on the bytes of the messages wanted."""
        conns = [c for c in self._connections if c.topic in set(topics)]
        if not conns:
            return
        try:
            it = iter(self._reader.messages(connections=conns, start=start_ns, stop=stop_ns))
        except Exception as exc:
            raise DatasetError(self.path, "file", f"a readable {self._what()}", _reason(exc)) from None
        n = 0
        try:
            # exceptions of the consumer are not raised here (a generator's caller gets them), so
            # this catches only the reader's
            for conn, t_ns, raw in it:
                n += 1
                yield conn.topic, t_ns, raw
        except Exception as exc:
            raise DatasetError(self.path, f"after message {n} of {', '.join(topics)}",
                               f"a complete {self._what()} (truncated or corrupt?)", _reason(exc)) from None

    def deserialize(self, raw, topic: str, t_ns: int) -> Any:
        """The message object of ``raw`` (bytes of ``topic`` received at ``t_ns``)."""
        msgtype = self.topics[topic].msgtype
        try:
            if self.kind == "ros1":
                return self._typestore.deserialize_ros1(raw, msgtype)
            return self._typestore.deserialize_cdr(raw, msgtype)
        except Exception as exc:
            raise DatasetError(self.path, f"topic {topic}, message at receive time {t_ns * 1e-9:.6f} s",
                               f"a valid {msgtype}", _reason(exc)) from None


def _reason(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) if exc.args else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
