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
        storage = self._writer.storage
        if _plain_mcap(storage):
            small = storage.write

            def write(connection: Any, stamp: int, data: bytes | memoryview) -> None:
                if memoryview(data).nbytes >= LARGE_MESSAGE:
                    _write_own_chunk(storage, connection, stamp, data)
                else:
                    small(connection, stamp, data)
            storage.write = write       # the Writer's own checks and counts stay in front
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=typestore())
            self.counts[topic] = 0
        # serialize_cdr's own buffer (serialize's bytes() would copy it once more)
        raw = msg if isinstance(msg, (bytes, bytearray, memoryview)) else \
            typestore().serialize_cdr(msg, msgtype)
        self._writer.write(self._connections[topic], int(stamp_ns), raw)
        self.counts[topic] += 1


LARGE_MESSAGE = 1 << 16     # bytes: a message this large goes into its own MCAP chunk


def _plain_mcap(storage: Any) -> bool:
    """Whether ``storage`` is rosbags' uncompressed MCAP writer with the state
    :func:`_write_own_chunk` keeps (rosbags 0.11's ``McapWriter``)."""
    from rosbags.rosbag2.storage_mcap import McapWriter
    return type(storage) is McapWriter and storage.compression == '' and all(
        hasattr(storage, a) for a in ('bio', 'chunk', 'chunks', 'channel_stats',
                                      'message_start_time', 'message_end_time'))


def _write_own_chunk(storage: Any, connection: Any, stamp: int,
                     data: bytes | bytearray | memoryview) -> None:
    """One message as its own uncompressed chunk of rosbags' MCAP writer, its bytes written
    to the file once: the writer's own path copies every message into a record buffer, the
    chunk buffer, the chunk's value and the chunk record before the file (0.5-1.5 s of the
    ~530 MB a 640x480 ``process`` run writes; the file write alone ~0.1 s).  The same records
    as ``McapWriter.write`` followed by ``close_chunk``: the pending chunk is closed first, then
    the chunk, its message index and its chunk index entry (written at close)."""
    from io import BytesIO

    from rosbags.rosbag2.storage_mcap import write_string, write_uint16, write_uint64
    if storage.chunk.bio.tell():
        storage.close_chunk()
    storage.message_start_time = min(stamp, storage.message_start_time)
    storage.message_end_time = max(stamp, storage.message_end_time)
    storage.channel_stats[connection.id] += 1
    n = memoryview(data).nbytes
    msg_len = 2 + 4 + 8 + 8 + n                   # channel, sequence, log and publish time
    content = 1 + 8 + msg_len                     # the message record: opcode, length, body
    head = BytesIO()
    head.write(b'\x06')                          # chunk record
    write_uint64(head, 8 + 8 + 8 + 4 + 4 + 8 + content)
    write_uint64(head, stamp)                     # message start / end time
    write_uint64(head, stamp)
    write_uint64(head, content)                   # uncompressed size
    head.write(b'\x00\x00\x00\x00')              # uncompressed crc: none
    write_string(head, '')                        # compression: none
    write_uint64(head, content)                   # records' size
    head.write(b'\x05')                          # message record
    write_uint64(head, msg_len)
    write_uint16(head, connection.id)
    head.write(b'\x00\x00\x00\x00')              # sequence
    write_uint64(head, stamp)
    write_uint64(head, stamp)
    bio = storage.bio
    chunk_start = bio.tell()
    bio.write(head.getbuffer())
    bio.write(data)
    chunk_end = bio.tell()
    index = BytesIO()                             # message index: the one message, offset 0
    index.write(b'\x07')
    write_uint64(index, 2 + 4 + 16)
    write_uint16(index, connection.id)
    index.write((16).to_bytes(4, 'little'))
    write_uint64(index, stamp)
    write_uint64(index, 0)
    bio.write(index.getbuffer())
    rec = BytesIO()                               # chunk index (close_chunk's layout)
    write_uint64(rec, stamp)
    write_uint64(rec, stamp)
    write_uint64(rec, chunk_start)
    write_uint64(rec, chunk_end - chunk_start)
    rec.write((10).to_bytes(4, 'little'))
    write_uint16(rec, connection.id)
    write_uint64(rec, chunk_end)
    write_uint64(rec, bio.tell() - chunk_end)
    write_string(rec, '')
    write_uint64(rec, content)
    write_uint64(rec, content)
    storage.chunks.append(rec)


class BagError(ValueError):
    """A path that is not a readable bag (the CLI prints it as one ``error:`` line)."""


def _storage_error(err: Exception) -> bool:
    from rosbags.rosbag2 import ReaderError
    return isinstance(err, (ReaderError, OSError, EOFError, KeyError, ValueError))


def _expected_counts(path: Path) -> dict[str, int]:
    """Messages per topic that metadata.yaml says the bag holds (empty if unreadable)."""
    import yaml
    try:
        info = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        return {t['topic_metadata']['name']: int(t['message_count'])
                for t in info['topics_with_message_count']}
    except Exception:  # noqa: BLE001 -- a damaged or foreign metadata file: no expectation
        return {}


def _check_bag_path(path: Path) -> None:
    if not path.exists():
        raise FileNotFoundError(f'bag {path} does not exist')
    if not path.is_dir() or not (path / 'metadata.yaml').exists():
        raise BagError(f'{path}: not a bag (expected a rosbag2 folder with metadata.yaml)')


def _scan_mcap(file: Path, wanted: Sequence[str] | None) -> tuple[list[BagMessage], str]:
    """Every complete message record of an MCAP file, in file order, reading past a damaged
    summary; returns (messages, '' or the reason the scan stopped early)."""
    import struct

    from rosbags.rosbag2.storage_mcap import decompress
    data = file.read_bytes()
    if data[:8] != b'\x89MCAP0\r\n':
        return [], f'{file.name}: not an MCAP file'
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    out: list[BagMessage] = []

    def string(buf: bytes, at: int) -> tuple[str, int]:
        (n,) = struct.unpack_from('<I', buf, at)
        return buf[at + 4:at + 4 + n].decode('utf-8', 'replace'), at + 4 + n

    def records(buf: bytes, pos: int, end: int, nested: bool) -> str:
        while pos < end:
            if pos + 9 > end:
                return f'record header cut at byte {pos}'
            op, (n,) = buf[pos], struct.unpack_from('<Q', buf, pos + 1)
            body = pos + 9
            if body + n > end:
                if op == 0x06 and not nested:      # a cut uncompressed chunk: its whole records
                    rec = buf[body:end]
                    comp, at = string(rec, 28) if len(rec) >= 32 else ('?', 0)
                    if comp == '' and len(rec) >= at + 8:
                        records(rec[at + 8:], 0, len(rec) - at - 8, True)
                return f'record (opcode {op:#x}) cut at byte {pos} of {end}'
            rec = buf[body:body + n]
            try:
                if op == 0x03:
                    (sid,) = struct.unpack_from('<H', rec, 0)
                    schemas[sid], _ = string(rec, 2)
                elif op == 0x04:
                    cid, sid = struct.unpack_from('<HH', rec, 0)
                    topic, _ = string(rec, 4)
                    channels[cid] = (topic, schemas.get(sid, ''))
                elif op == 0x05:
                    cid, _, log_time, _ = struct.unpack_from('<HIQQ', rec, 0)
                    if cid in channels:
                        topic, msgtype = channels[cid]
                        if wanted is None or topic in wanted:
                            out.append(BagMessage(topic, msgtype, int(log_time), rec[22:]))
                elif op == 0x06 and not nested:
                    _, _, size, crc = struct.unpack_from('<QQQI', rec, 0)
                    comp, at = string(rec, 28)
                    (clen,) = struct.unpack_from('<Q', rec, at)
                    inner = decompress(rec[at + 8:at + 8 + clen], comp, size, crc)
                    why = records(inner, 0, len(inner), True)
                    if why:
                        return f'chunk at byte {pos}: {why}'
                elif op == 0x02 and not nested:
                    return ''       # the footer
            except Exception as err:  # noqa: BLE001 -- a corrupt record ends the scan
                return f'record (opcode {op:#x}) at byte {pos} unreadable: {err}'
            pos = body + n
        return '' if nested else f'file ends at byte {end} without its footer'

    why = records(data, 8, len(data), False)
    return out, why and f'{file.name}: {why}'


def _salvage(path: Path, topics: Sequence[str] | None, first_error: Exception
             ) -> tuple[list[BagMessage], str]:
    """What can be read of a bag the indexed reader refused: (messages by stamp, damage)."""
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise BagError(f'{path}: unreadable bag ({first_error})') from first_error
    msgs: list[BagMessage] = []
    reasons = []
    for f in files:
        got, why = _scan_mcap(f, topics)
        msgs += got
        if why:
            reasons.append(why)
    msgs.sort(key=lambda m: m.stamp_ns)
    return msgs, '; '.join(reasons) or str(first_error)


def damage_line(path: Path, read: Sequence[BagMessage] | dict[str, int], reason: str,
                topics: Sequence[str] | None = None) -> str:
    """One line naming what a damaged bag lost: per topic, expected minus read."""
    counts = read if isinstance(read, dict) else _count(read)
    expected = {t: n for t, n in _expected_counts(path).items()
                if topics is None or t in topics}
    lost = {t: n - counts.get(t, 0) for t, n in expected.items() if n > counts.get(t, 0)}
    total = sum(counts.values())
    if lost:
        what = ', '.join(f'{t}: {n}' for t, n in sorted(lost.items()))
        return (f'{path} is damaged ({reason}): read {total} of {sum(expected.values())} '
                f'messages; lost {sum(lost.values())} ({what})')
    return f'{path} is damaged ({reason}): read {total} messages; the rest of the file is lost'


def _count(msgs: Sequence[BagMessage]) -> dict[str, int]:
    out: dict[str, int] = {}
    for m in msgs:
        out[m.topic] = out.get(m.topic, 0) + 1
    return out


def read_messages(path: str | Path, topics: Sequence[str] | None = None,
                  damage: list[str] | None = None) -> Iterator[BagMessage]:
    """Messages in log-time order (raw CDR bytes), optionally restricted to ``topics``.

    A damaged bag (truncated or corrupt MCAP, bad index) is read as far as possible: every
    complete message is yielded, then one line naming what was lost is appended to ``damage``
    (or, without a ``damage`` list, a BagError is raised after the last message)."""
    from rosbags.rosbag2 import Reader
    path = Path(path)
    _check_bag_path(path)
    topics = None if topics is None else [t.lstrip('/') for t in topics]
    done: dict[str, int] = {}
    try:
        with Reader(path) as reader:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            for conn, stamp, raw in reader.messages(connections=conns):
                done[conn.topic] = done.get(conn.topic, 0) + 1
                yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(raw))
        return
    except Exception as err:  # noqa: BLE001 -- storage errors of every kind
        if not _storage_error(err) and type(err).__module__.split('.')[0] != 'rosbags':
            raise
        first = err
    msgs, reason = _salvage(path, topics, first)
    # continue after what the indexed reader already yielded (per topic, in stamp order)
    skip = dict(done)
    for m in msgs:
        if skip.get(m.topic, 0) > 0:
            skip[m.topic] -= 1
            continue
        done[m.topic] = done.get(m.topic, 0) + 1
        yield m
    line = damage_line(path, done, reason, topics)
    if damage is None:
        raise BagError(line)
    damage.append(line)


def bag_info(path: str | Path) -> dict[str, Any]:
    """Topics with types and counts, duration, start/end (ns); a damaged bag is described by
    what can be read of it (and ``damaged``: the reason)."""
    from rosbags.rosbag2 import Reader
    path = Path(path)
    _check_bag_path(path)
    try:
        with Reader(path) as reader:
            return {'topics': {c.topic: {'type': c.msgtype, 'count': c.msgcount}
                               for c in reader.connections},
                    'start_ns': reader.start_time, 'end_ns': reader.end_time,
                    'duration_s': reader.duration / 1e9, 'messages': reader.message_count}
    except Exception as err:  # noqa: BLE001
        if not _storage_error(err) and type(err).__module__.split('.')[0] != 'rosbags':
            raise
        msgs, reason = _salvage(path, None, err)
    topics: dict[str, dict[str, Any]] = {}
    for m in msgs:
        t = topics.setdefault(m.topic, {'type': m.msgtype, 'count': 0})
        t['count'] += 1
    start = msgs[0].stamp_ns if msgs else 0
    end = msgs[-1].stamp_ns if msgs else 0
    return {'topics': topics, 'start_ns': start, 'end_ns': end,
            'duration_s': (end - start) / 1e9, 'messages': len(msgs), 'damaged': reason}
