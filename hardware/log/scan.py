"""Reading a log's data section front to back, past damaged bytes.

Every record is length-prefixed and parsed strictly (`records`); chunks carry a CRC of
their records. A record that does not parse, or whose length runs past the end of the
file, starts a damaged span, and the scan resynchronises on the next intact record: it
looks forward byte by byte for one that parses as a chunk whose CRC holds, or as a
metadata or attachment record (the records a walker log has outside its chunks). A
damaged span thus loses one chunk (half a second of a recording) and the message indexes
after it, not the rest of the file. When no intact record follows, the span runs to the
end of the data section: a file cut short ("truncated"), or damage in its last chunk.

For a damaged log the summary is read too, if it is intact (its CRC holds): it repeats the
schemas and channels that the writer declares only inside the chunk where each is first
used, so a lost chunk that held a first declaration does not make the channel unreadable,
and its indexes name the chunks, metadata and attachments that a damaged span held.
"""

from __future__ import annotations

import io
import os
import re
import zlib
from dataclasses import dataclass, field
from typing import Any

from mcap.opcode import Opcode
from mcap.records import AttachmentIndex, Channel, ChunkIndex, MetadataIndex, Schema, Statistics

from hardware.errors import LogError
from hardware.log.records import (
    DATA_OPCODES,
    FOOTER,
    MAGIC,
    RECORD_HEAD,
    Damaged,
    Record,
    block_records,
    check_header,
    check_message_index,
    chunk_head_plausible,
    chunk_records,
    opcode_name,
    parse_attachment,
    parse_declaration,
    parse_metadata,
    stream,
)

_TAIL = FOOTER.size + len(MAGIC)  # the footer record and the closing magic
# Opcodes a resynchronisation may land on: records with a CRC (chunks, attachments) or
# with enough structure to be recognised (metadata).
_RESYNC_OPCODES = re.compile(b"[%c%c%c]" % (Opcode.CHUNK, Opcode.ATTACHMENT, Opcode.METADATA))
_WINDOW = 1 << 20  # bytes searched per read while resynchronising
_PEEK = 64  # bytes enough to judge a candidate record's head


@dataclass
class Block:
    """A chunk (or an unchunked message record) in the data section, in file order."""

    offset: int
    start_ns: int
    end_ns: int
    channels: frozenset[int]


@dataclass(frozen=True)
class Damage:
    """Bytes [start, end) of the file that the scan could not read."""

    start: int
    end: int
    what: str  # "truncated", "corrupt chunk record", "unreadable bytes", ...

    @property
    def truncated(self) -> bool:
        return self.what == "truncated"


@dataclass
class Summary:
    """A log's summary section, CRC checked: declarations and indexes."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[ChunkIndex] = field(default_factory=list)
    metadata: list[MetadataIndex] = field(default_factory=list)
    attachments: list[AttachmentIndex] = field(default_factory=list)
    statistics: Statistics | None = None


@dataclass
class Contents:
    """What a scan of the data section found."""

    blocks: list[Block] = field(default_factory=list)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    counts: dict[int, list[int]] = field(default_factory=dict)  # channel -> [n, first, last ns]
    damage: list[Damage] = field(default_factory=list)
    ended: bool = False  # the data section's end was reached: the writer closed the log
    summary: Summary | None = None  # read only for a damaged log

    @property
    def undeclared(self) -> list[int]:
        """Channels that have messages but no declaration (or whose schema is missing)."""
        return sorted(
            c
            for c in self.counts
            if c not in self.channels or self.channels[c].schema_id not in self.schemas
        )


def scan(f: io.BufferedReader, path: os.PathLike[str]) -> Contents:
    """Read the data section of the open log `f` (at its start); LogError if the file is
    not an MCAP file or holds no intact record."""
    try:
        size = os.fstat(f.fileno()).st_size
        magic = f.read(len(MAGIC))
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror}") from None
    if not magic:
        raise LogError(f"{path}: empty file (0 bytes)")
    if magic != MAGIC:
        if MAGIC.startswith(magic):
            raise LogError(f"{path}: truncated in the header ({size} bytes)")
        raise LogError(f"{path}: not an MCAP file (starts with {magic!r})")
    scanner = _Scanner(f, size)
    scanner.run()
    out = scanner.out
    if not scanner.found_any:
        if out.damage[0].truncated:
            raise LogError(f"{path}: truncated in the header ({size} bytes)")
        raise LogError(f"{path}: not an MCAP file (no header record)")
    if out.damage or out.undeclared:
        out.summary = scanner.summary()
    if out.summary is not None:  # declarations the lost spans held
        for sid, schema in out.summary.schemas.items():
            out.schemas.setdefault(sid, schema)
        for cid, channel in out.summary.channels.items():
            out.channels.setdefault(cid, channel)
    return out


class _Scanner:
    def __init__(self, f: io.BufferedReader, size: int) -> None:
        self.f = f
        self.size = size
        self.out = Contents()
        self.found_any = False  # an intact record after the magic
        self._tail: tuple[int, bytes] | None = None

    def run(self) -> None:
        """Records from the header on, until the data end, the end of the file, or damage
        that no intact record follows."""
        f, out = self.f, self.out
        offset = len(MAGIC)
        expect_header = True
        while True:
            head = f.read(RECORD_HEAD.size)
            if len(head) < RECORD_HEAD.size:
                out.damage.append(Damage(offset, self.size, "truncated"))
                return
            opcode, length = RECORD_HEAD.unpack(head)
            what = "truncated"
            if length <= self.size - offset - RECORD_HEAD.size:
                body = f.read(length)
                try:
                    if expect_header:
                        if opcode != Opcode.HEADER:
                            raise Damaged("no header record")
                        check_header(body)
                    elif self._record(offset, opcode, body):
                        self.found_any = out.ended = True
                        return
                    self.found_any = True
                    expect_header = False
                    offset += RECORD_HEAD.size + length
                    continue
                except Exception:
                    known = opcode in DATA_OPCODES
                    what = f"corrupt {opcode_name(opcode)} record" if known else "unreadable bytes"
                    if expect_header:
                        what = "corrupt header record"
            expect_header = False
            if not self._skip_damage(offset, what):
                return
            offset = out.damage[-1].end
            f.seek(offset)

    def _skip_damage(self, offset: int, what: str) -> bool:
        """Record the damaged span that starts at `offset`; whether an intact record
        follows it (where the span ends)."""
        found = self._resync(offset)
        if found is None:
            limit = self.data_end()
            self.out.damage.append(Damage(offset, limit, what))
            self.out.ended = limit < self.size  # what follows is a closed log's summary
            return False
        if what == "truncated":  # not the end of the file: a corrupt length
            what = "corrupt record length"
        self.out.damage.append(Damage(offset, found, what))
        return True

    def _record(self, offset: int, opcode: int, body: bytes) -> bool:
        """Take in one record (raises on damage); True at the end of the data section."""
        out = self.out
        if opcode == Opcode.CHUNK or opcode == Opcode.MESSAGE:
            self._block(offset, *block_records(opcode, body, validate=True))
        elif opcode == Opcode.MESSAGE_INDEX:
            check_message_index(body)
        elif opcode == Opcode.SCHEMA or opcode == Opcode.CHANNEL:
            self._declare([parse_declaration(opcode, body)])
        elif opcode == Opcode.METADATA:
            name, value = parse_metadata(body)
            out.metadata[name] = value
        elif opcode == Opcode.ATTACHMENT:
            att = parse_attachment(body)
            out.attachments[att.name] = att.data
        elif opcode == Opcode.DATA_END or opcode == Opcode.FOOTER:
            return True
        else:  # a second header, or a record that belongs to the summary
            raise Damaged(f"{opcode_name(opcode)} record in the data section")
        return False

    def _declare(self, records: list[Any]) -> None:
        for rec in records:
            if isinstance(rec, Schema):
                self.out.schemas[rec.id] = rec
            else:
                self.out.channels[rec.id] = rec

    def _block(self, offset: int, messages: list[Record], others: list[Any]) -> None:
        self._declare(others)
        if not messages:
            return
        per_channel: dict[int, list[int]] = {}
        for ns, c, _ in messages:
            per_channel.setdefault(c, []).append(ns)
        for c, times in per_channel.items():
            stats = self.out.counts.setdefault(c, [0, times[0], times[0]])
            stats[0] += len(times)
            stats[1], stats[2] = min(stats[1], *times), max(stats[2], *times)
        start = min(ns for ns, _, _ in messages)
        end = max(ns for ns, _, _ in messages)
        self.out.blocks.append(Block(offset, start, end, frozenset(per_channel)))

    # -- resynchronisation and the summary

    def tail(self) -> tuple[int, bytes]:
        """(where the data section ends, the summary's bytes): of a closed log with an
        intact footer and summary (CRC checked), else (the file size, b"")."""
        if self._tail is None:
            self._tail = read_tail(self.f, self.size) or (self.size, b"")
        return self._tail

    def data_end(self) -> int:
        return self.tail()[0]

    def summary(self) -> Summary | None:
        data = self.tail()[1]
        return parse_summary(data) if data else None

    def _resync(self, offset: int) -> int | None:
        """Offset of the first intact chunk, metadata or attachment record after `offset`
        that ends within the data section, None if there is none."""
        limit = self.data_end()
        pos = offset + 1
        while pos + RECORD_HEAD.size <= limit:
            buf = self._read_at(pos, min(_WINDOW + _PEEK, limit - pos))
            for m in _RESYNC_OPCODES.finditer(buf, 0, _WINDOW):
                i = m.start()
                if self._intact_at(pos + i, buf[i : i + _PEEK], limit):
                    return pos + i
            pos += _WINDOW
        return None

    def _intact_at(self, p: int, head: bytes, limit: int) -> bool:
        """Whether an intact chunk, metadata or attachment record starts at `p`."""
        if len(head) < _PEEK:
            head = self._read_at(p, _PEEK)
        if len(head) < RECORD_HEAD.size:
            return False
        opcode, length = RECORD_HEAD.unpack_from(head, 0)
        if length > limit - p - RECORD_HEAD.size:
            return False
        if opcode == Opcode.CHUNK and not chunk_head_plausible(head[RECORD_HEAD.size :], length):
            return False
        body = self._read_at(p + RECORD_HEAD.size, length)
        try:
            if opcode == Opcode.CHUNK:
                chunk_records(body, validate=True)
            elif opcode == Opcode.METADATA:
                parse_metadata(body)
            else:
                parse_attachment(body)
        except Exception:
            return False
        return True

    def _read_at(self, pos: int, n: int) -> bytes:
        self.f.seek(pos)
        return self.f.read(n)


def read_tail(f: io.BufferedReader, size: int) -> tuple[int, bytes] | None:
    """(where the data section ends, the summary's bytes) from an intact footer whose
    summary CRC holds; None for a file without one (cut short, still being written,
    damaged at its end)."""
    if size < 2 * len(MAGIC) + _TAIL:
        return None
    f.seek(size - _TAIL)
    tail = f.read(_TAIL)
    if len(tail) != _TAIL or tail[FOOTER.size :] != MAGIC:
        return None
    opcode, length, start, _, crc = FOOTER.unpack_from(tail, 0)
    footer_at = size - _TAIL
    if opcode != Opcode.FOOTER or length != FOOTER.size - RECORD_HEAD.size:
        return None
    if start and not len(MAGIC) < start <= footer_at:
        return None
    data = b""
    if start:
        f.seek(start)
        data = f.read(footer_at - start)
    if crc and zlib.crc32(tail[: FOOTER.size - 4], zlib.crc32(data)) != crc:
        return None
    return (start or footer_at), data


_SUMMARY_RECORDS: dict[int, Any] = {
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.STATISTICS: Statistics,
}


def parse_summary(data: bytes) -> Summary | None:
    """The records of a summary section; None if they do not parse."""
    summary = Summary()
    pos = 0
    try:
        while pos < len(data):
            opcode, length = RECORD_HEAD.unpack_from(data, pos)
            body = data[pos + RECORD_HEAD.size : pos + RECORD_HEAD.size + length]
            pos += RECORD_HEAD.size + length
            kind = _SUMMARY_RECORDS.get(opcode)
            rec = kind.read(stream(body)) if kind is not None else None
            if isinstance(rec, Schema):
                summary.schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                summary.channels[rec.id] = rec
            elif isinstance(rec, ChunkIndex):
                summary.chunks.append(rec)
            elif isinstance(rec, MetadataIndex):
                summary.metadata.append(rec)
            elif isinstance(rec, AttachmentIndex):
                summary.attachments.append(rec)
            elif isinstance(rec, Statistics):
                summary.statistics = rec
    except Exception:
        return None
    return summary
