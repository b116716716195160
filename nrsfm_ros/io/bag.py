"""Bags through rosbags with the Jazzy typestore: MCAP by default, sqlite3 readable.

Messages are stored as CDR bytes; live recording writes the bytes it receives untouched and
replay publishes them untouched, so nothing is (de)serialised twice.
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from .errors import MessageError


@lru_cache(maxsize=1)
def typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def serialize(msg: Any, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(raw: bytes | memoryview, msgtype: str) -> Any:
    try:
        return typestore().deserialize_cdr(raw, msgtype)
    except Exception as err:  # rosbags raises several types for corrupt CDR
        raise MessageError('data', f'{len(raw)} bytes', f'not a valid {msgtype}: {err}') from err


# Topics that replay must publish transient-local (latched), by name.
LATCHED_TOPICS = ('registration/reference',)


@dataclass(frozen=True)
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int
    raw: bytes


class BagWriter:
    """``with BagWriter(path) as w: w.write(topic, msgtype, msg_or_cdr_bytes, stamp_ns)``."""

    def __init__(self, path: str | Path, storage: str = 'mcap') -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        if storage not in ('mcap', 'sqlite3'):
            raise ValueError(f"storage={storage!r}: expected 'mcap' or 'sqlite3'")
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f'{self.path} exists; choose another output or delete it')
        plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._connections: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=typestore())
            self.counts[topic] = 0
        raw = msg if isinstance(msg, (bytes, bytearray, memoryview)) else serialize(msg, msgtype)
        self._writer.write(self._connections[topic], int(stamp_ns), raw)
        self.counts[topic] += 1


def read_messages(path: str | Path, topics: Sequence[str] | None = None) -> Iterator[BagMessage]:
    """Messages in log-time order (raw CDR bytes), optionally restricted to ``topics``."""
    from rosbags.rosbag2 import Reader
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'bag {path} does not exist')
    with Reader(path) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        for conn, stamp, raw in reader.messages(connections=conns):
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(raw))


def bag_info(path: str | Path) -> dict[str, Any]:
    """Topics with types and counts, duration, start/end (ns)."""
    from rosbags.rosbag2 import Reader
    with Reader(Path(path)) as reader:
        return {'topics': {c.topic: {'type': c.msgtype, 'count': c.msgcount}
                           for c in reader.connections},
                'start_ns': reader.start_time, 'end_ns': reader.end_time,
                'duration_s': reader.duration / 1e9, 'messages': reader.message_count}
