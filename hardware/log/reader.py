"""The replayer: the chunk scanning and parsing, and TrialLog (a trial log opened as a
message source)."""

from __future__ import annotations

import heapq
import io
import itertools
import json
import os
import struct
import warnings
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Header, Metadata, Schema
from mcap.records import Message as McapMessage

from hardware.calibration import WalkerCalibration
from hardware.errors import LogError
from hardware.log.codec import READERS, Companions, SchemaReader, Skip
from hardware.messages import Message

MAGIC = b"\x89MCAP0\r\n"


class LogRecoveryWarning(UserWarning):
    """A truncated or corrupt log was read up to its last intact record."""


class UnsupportedChannelWarning(UserWarning):
    """A channel (or its messages) that the replayer cannot turn into messages is skipped."""


@dataclass
class _Block:
    """A chunk (or an unchunked message record) in the data section, in file order."""

    offset: int
    start_ns: int
    end_ns: int
    channels: frozenset[int]


@dataclass
class _Role:
    main_topic: str
    reader: SchemaReader


def _record_stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, len(compression)
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


_Record = tuple[int, int, bytes]  # a message record: (log time ns, channel id, data)


def _chunk_records(body: bytes, validate: bool) -> tuple[list[_Record], list[Any]]:
    """(messages, schema and channel records) of a chunk (MCAP spec layout), parsed with
    struct: message records are fixed-layout and by far the most numerous, so this is much
    faster than the generic record reader, which is kept for the rare schema and channel
    records. Messages come as plain tuples, in file order."""
    _, _, usize, crc, clen = _CHUNK_HEAD.unpack_from(body, 0)
    pos = _CHUNK_HEAD.size
    compression = body[pos : pos + clen].decode()
    (dlen,) = struct.unpack_from("<Q", body, pos + clen)
    pos += clen + 8
    data = body[pos : pos + dlen]
    if len(data) != dlen:
        raise ValueError("truncated chunk")
    if compression == "zstd":
        data = zstandard.decompress(data, usize)
    elif compression == "lz4":
        data = lz4.frame.decompress(data)
    elif compression:
        raise ValueError(f"unsupported chunk compression {compression!r}")
    if validate and crc and zlib.crc32(data) != crc:
        raise ValueError("chunk CRC mismatch")
    messages: list[_Record] = []
    others: list[Any] = []
    record_head, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    head, mhead = _RECORD_HEAD.size, _MESSAGE_HEAD.size
    pos, n = 0, len(data)
    while pos < n:
        opcode, length = record_head(data, pos)
        pos += head
        end = pos + length
        if end > n:
            raise ValueError("truncated record in chunk")
        if opcode == Opcode.MESSAGE:
            channel, _, log_ns, _ = message_head(data, pos)
            messages.append((log_ns, channel, data[pos + mhead : end]))
        elif opcode == Opcode.SCHEMA:
            others.append(Schema.read(_record_stream(data[pos:end])))
        elif opcode == Opcode.CHANNEL:
            others.append(Channel.read(_record_stream(data[pos:end])))
        pos = end
    return messages, others


def _messages_in(opcode: int, body: bytes, validate: bool = False) -> tuple[list[_Record], list]:
    """(messages, schema and channel records) of a chunk or an unchunked message record."""
    if opcode == Opcode.CHUNK:
        return _chunk_records(body, validate)
    rec = McapMessage.read(_record_stream(body), len(body))
    return [(rec.log_time, rec.channel_id, rec.data)], []


class TrialLog:
    """A trial log opened for replay: calibration, metadata, attachments and messages; a
    message source (`hardware.source.Source`).

    Opening scans the whole file once (without needing its summary), so problems are
    reported here: `LogError` for files that cannot be used, `LogRecoveryWarning` for a
    truncated or corrupt file, `UnsupportedChannelWarning` for channels it skips.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.metadata: dict[str, dict[str, Any]] = {}
        self.attachments: dict[str, bytes] = {}
        self.complete = False  # False: truncated or corrupt, read up to the damage
        self._blocks: list[_Block] = []
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._counts: dict[int, list[int]] = {}  # channel -> [count, first ns, last ns]
        problem = self._scan()
        raw_cal = self.metadata.pop("calibration", None)
        if raw_cal is None:
            self._fail(
                f"truncated at byte {problem[0]} before the calibration record"
                if problem
                else "no calibration record"
            )
        try:
            self.calibration = WalkerCalibration.from_dict(raw_cal)
        except (TypeError, ValueError) as e:
            self._fail(f"invalid calibration record: {e}")
        self._roles: dict[int, _Role] = {}
        #: readable topics -> message type
        self.topics: dict[str, type] = {}
        self._classify()
        counts = [
            self._counts[c] for c, r in self._roles.items() if r.reader.build and c in self._counts
        ]
        #: number of messages (companions not counted)
        self.message_count = sum(c[0] for c in counts)
        #: (first, last) log time [s], None if there are no messages
        self.time_range = (
            (min(c[1] for c in counts) / 1e9, max(c[2] for c in counts) / 1e9) if counts else None
        )
        if problem:
            offset, what = problem
            if self.message_count == 0:
                self._fail(f"{what} at byte {offset} before any message")
            first, last = self.time_range or (0.0, 0.0)
            hint = " (writer killed or still writing?)" if what == "truncated" else ""
            warnings.warn(
                LogRecoveryWarning(
                    f"{self.path.name}: {what} at byte {offset}{hint}; recovered "
                    f"{self.message_count} messages spanning {last - first:.3f} s "
                    f"(log time {first:.3f} to {last:.3f} s)"
                ),
                stacklevel=3,
            )

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[Message]:
        """Messages on `topics` (default all readable ones) in log-time order."""
        wanted = None if topics is None else set(topics)
        channels = {c for c, r in self._roles.items() if wanted is None or r.main_topic in wanted}
        state: dict[str, Companions] = {}
        skipped: set[str] = set()
        for ns, channel, data in self._records(channels):
            role = self._roles[channel]
            if role.main_topic in skipped:
                continue
            comp = state.setdefault(role.main_topic, {})
            try:
                payload = role.reader.parse(data)
                if role.reader.build is None:
                    comp[role.reader.schema.name] = (ns, payload)
                    continue
                msg = role.reader.build(payload, ns, comp)
            except Skip as e:
                skipped.add(role.main_topic)
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping {role.main_topic!r}: {e}"
                    ),
                    stacklevel=2,
                )
                continue
            except Exception as e:
                topic = self._channels[channel].topic
                self._fail(f"cannot decode the message on {topic!r} at {ns} ns: {e!r}")
            yield msg

    def __iter__(self) -> Iterator[Message]:
        return self.messages()

    def close(self) -> None:
        """Nothing to release: every `messages()` iteration opens the file itself."""

    # -- scanning

    def _fail(self, what: str) -> NoReturn:
        raise LogError(f"{self.path}: {what}")

    def _open(self) -> io.BufferedReader:
        try:
            return open(self.path, "rb")
        except FileNotFoundError:
            self._fail("no such file")
        except IsADirectoryError:
            self._fail("is a directory, not a log file")
        except PermissionError:
            self._fail("permission denied")
        except OSError as e:
            self._fail(f"cannot open: {e.strerror}")

    def _scan(self) -> tuple[int, str] | None:
        """Read the data section; (byte offset, what) of the first damage, None if intact."""
        with self._open() as f:
            try:
                size = os.fstat(f.fileno()).st_size
                magic = f.read(len(MAGIC))
            except OSError as e:
                self._fail(f"cannot read: {e.strerror}")
            if not magic:
                self._fail("empty file (0 bytes)")
            if magic != MAGIC:
                if MAGIC.startswith(magic):
                    self._fail(f"truncated in the header ({size} bytes)")
                self._fail(f"not an MCAP file (starts with {magic!r})")
            offset = len(MAGIC)
            seen_header = False
            while True:
                head = f.read(9)
                if len(head) < 9:
                    what = "truncated"
                    break
                opcode, length = struct.unpack("<BQ", head)
                if length > size - offset - 9:
                    what = "truncated"
                    break
                body = f.read(length)
                try:
                    if not seen_header:
                        if opcode != Opcode.HEADER:
                            self._fail("not an MCAP file (no header record)")
                        Header.read(_record_stream(body))
                        seen_header = True
                    elif opcode in (Opcode.CHUNK, Opcode.MESSAGE):
                        self._scan_block(offset, opcode, body)
                    elif opcode == Opcode.SCHEMA:
                        schema = Schema.read(_record_stream(body))
                        self._schemas[schema.id] = schema
                    elif opcode == Opcode.CHANNEL:
                        channel = Channel.read(_record_stream(body))
                        self._channels[channel.id] = channel
                    elif opcode == Opcode.METADATA:
                        self._add_metadata(Metadata.read(_record_stream(body)))
                    elif opcode == Opcode.ATTACHMENT:
                        att = Attachment.read(_record_stream(body))
                        self.attachments[att.name] = att.data
                    elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                        self.complete = True
                        return None
                except LogError:
                    raise
                except Exception:
                    what = f"corrupt {_opcode_name(opcode)} record"
                    break
                offset += 9 + length
            if not seen_header:
                self._fail(f"truncated in the header ({size} bytes)")
            return offset, what

    def _scan_block(self, offset: int, opcode: int, body: bytes) -> None:
        messages, others = _messages_in(opcode, body, validate=True)
        for rec in others:
            if isinstance(rec, Schema):
                self._schemas[rec.id] = rec
            else:
                self._channels[rec.id] = rec
        if not messages:
            return
        per_channel: dict[int, list[int]] = {}
        for ns, c, _ in messages:
            per_channel.setdefault(c, []).append(ns)
        for c, times in per_channel.items():
            stats = self._counts.setdefault(c, [0, times[0], times[0]])
            stats[0] += len(times)
            stats[1], stats[2] = min(stats[1], *times), max(stats[2], *times)
        start = min(ns for ns, _, _ in messages)
        end = max(ns for ns, _, _ in messages)
        self._blocks.append(_Block(offset, start, end, frozenset(per_channel)))

    def _add_metadata(self, record: Metadata) -> None:
        if set(record.metadata) == {"json"}:
            try:
                self.metadata[record.name] = json.loads(record.metadata["json"])
            except ValueError as e:
                self._fail(f"metadata record {record.name!r} is not JSON: {e}")
        else:
            self.metadata[record.name] = dict(record.metadata)

    def _classify(self) -> None:
        for cid, channel in sorted(self._channels.items()):
            schema = self._schemas.get(channel.schema_id)
            reader = READERS.get(schema.name) if schema else None
            main = channel.topic if reader and reader.build else channel.metadata.get("main_topic")
            if (
                reader is None
                or schema is None
                or (schema.encoding, channel.message_encoding)
                != (reader.schema.encoding, reader.schema.message_encoding)
                or not main
            ):
                name = schema.name if schema else "(none)"
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping channel {channel.topic!r} with unsupported "
                        f"schema {name!r} ({channel.message_encoding})"
                    ),
                    stacklevel=4,
                )
                continue
            self._roles[cid] = _Role(main, reader)
            if reader.cls is not None:
                self.topics[main] = reader.cls

    def _records(self, channels: set[int]) -> Iterator[tuple[int, int, bytes]]:
        """(log time, channel, data) of the messages on `channels`, in log-time order
        (ties in file order)."""
        blocks = [b for b in self._blocks if b.channels & channels]
        disjoint = all(a.end_ns <= b.start_ns for a, b in itertools.pairwise(blocks))
        with self._open() as f:
            if disjoint:
                # Blocks follow each other in time (a recorder writes them so): a stable
                # sort within each block is the global order.
                for block in blocks:
                    recs = [r for r in self._read_block(f, block) if r[1] in channels]
                    recs.sort(key=_log_time)
                    yield from recs
                return
            heap: list[tuple[int, int, int, Any]] = [(b.start_ns, b.offset, -1, b) for b in blocks]
            heapq.heapify(heap)
            while heap:
                _, offset, index, item = heapq.heappop(heap)
                if index >= 0:
                    yield item
                    continue
                for i, rec in enumerate(self._read_block(f, item)):
                    if rec[1] in channels:
                        heapq.heappush(heap, (rec[0], offset, i, rec))

    def _read_block(self, f: io.BufferedReader, block: _Block) -> list[_Record]:
        try:
            f.seek(block.offset)
            opcode, length = struct.unpack("<BQ", f.read(9))
            return _messages_in(opcode, f.read(length))[0]
        except Exception as e:
            self._fail(f"changed or unreadable while replaying (byte {block.offset}): {e!r}")


def _log_time(record: _Record) -> int:
    return record[0]


def _opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode-{opcode:#x}"


def read_log(path: str | os.PathLike[str]) -> TrialLog:
    """Open a trial log for replay (see TrialLog)."""
    return TrialLog(path)


LogReader = TrialLog  # alias


def replay(path: str | os.PathLike[str], topics: Iterable[str] | None = None) -> Iterator[Message]:
    """All messages of a trial log (or those on `topics`) in log-time order."""
    yield from read_log(path).messages(topics)
