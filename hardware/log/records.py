"""MCAP records at the byte level (layouts from https://mcap.dev/spec): every record the
data section of a log may hold, parsed strictly so that damaged bytes are told apart from
an intact record, and chunks parsed with struct for speed."""

from __future__ import annotations

import io
import json
import struct
import zlib
from typing import Any

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Schema
from mcap.records import Message as McapMessage

MAGIC = b"\x89MCAP0\r\n"
RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
FOOTER = struct.Struct("<BQQQI")  # opcode, length, summary start, summary offset start, CRC
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, len(compression)
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_U16_U32 = struct.Struct("<HI")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_COMPRESSIONS = (b"", b"lz4", b"zstd")
MAX_CHUNK_BYTES = 1 << 30  # larger uncompressed sizes are taken for damage

#: Opcodes a data section holds (the summary's are not among them).
DATA_OPCODES = frozenset(
    {
        Opcode.HEADER,
        Opcode.SCHEMA,
        Opcode.CHANNEL,
        Opcode.MESSAGE,
        Opcode.CHUNK,
        Opcode.MESSAGE_INDEX,
        Opcode.ATTACHMENT,
        Opcode.METADATA,
        Opcode.DATA_END,
        Opcode.FOOTER,
    }
)

Record = tuple[int, int, bytes]  # a message record: (log time ns, channel id, data)


class Damaged(ValueError):
    """Bytes that do not parse as the record their opcode names."""


def opcode_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode-{opcode:#x}"


def stream(body: bytes) -> ReadDataStream:
    """A record body for mcap's record readers."""
    return ReadDataStream(io.BytesIO(body))


def _string(body: bytes, pos: int) -> tuple[str, int]:
    """A length-prefixed UTF-8 string at `pos` and the position after it."""
    (n,) = _U32.unpack_from(body, pos)
    end = pos + 4 + n
    if end > len(body):
        raise Damaged("string runs past its record")
    return body[pos + 4 : end].decode(), end


def _exactly(body: bytes, end: int, what: str) -> None:
    if end != len(body):
        raise Damaged(f"{what} fields do not fill the record")


# --------------------------------------------------------------------------- chunks


def chunk_head_plausible(head: bytes, length: int) -> bool:
    """Whether the first bytes of a chunk record's body (at least 44) are consistent with a
    chunk of `length` bytes: a known compression and sizes that add up. A cheap test before
    a candidate chunk is decompressed."""
    if len(head) < _CHUNK_HEAD.size:
        return False
    start, end, usize, _, clen = _CHUNK_HEAD.unpack_from(head, 0)
    pos = _CHUNK_HEAD.size
    if clen > 4 or len(head) < pos + clen + 8 or head[pos : pos + clen] not in _COMPRESSIONS:
        return False
    (dlen,) = _U64.unpack_from(head, pos + clen)
    return start <= end and usize <= MAX_CHUNK_BYTES and pos + clen + 8 + dlen == length


def chunk_records(body: bytes, validate: bool) -> tuple[list[Record], list[Any]]:
    """(messages, schema and channel records) of a chunk (MCAP spec layout), parsed with
    struct: message records are fixed-layout and by far the most numerous, so this is much
    faster than the generic record reader, which is kept for the rare schema and channel
    records. Messages come as plain tuples, in file order. `validate`: check the sizes and
    the CRC of the uncompressed records (raises Damaged)."""
    _, _, usize, crc, clen = _CHUNK_HEAD.unpack_from(body, 0)
    pos = _CHUNK_HEAD.size
    compression = body[pos : pos + clen].decode()
    (dlen,) = _U64.unpack_from(body, pos + clen)
    pos += clen + 8
    data = body[pos : pos + dlen]
    if len(data) != dlen:
        raise Damaged("truncated chunk")
    if validate and (pos + dlen != len(body) or usize > MAX_CHUNK_BYTES):
        raise Damaged("chunk sizes do not add up")
    if compression == "zstd":
        data = zstandard.decompress(data, usize)
    elif compression == "lz4":
        data = lz4.frame.decompress(data)
    elif compression:
        raise Damaged(f"unsupported chunk compression {compression!r}")
    if validate and (len(data) != usize or (crc and zlib.crc32(data) != crc)):
        raise Damaged("chunk CRC mismatch")
    messages: list[Record] = []
    others: list[Any] = []
    record_head, message_head = RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    head, mhead = RECORD_HEAD.size, _MESSAGE_HEAD.size
    pos, n = 0, len(data)
    while pos < n:
        opcode, length = record_head(data, pos)
        pos += head
        end = pos + length
        if end > n:
            raise Damaged("truncated record in chunk")
        if opcode == Opcode.MESSAGE:
            channel, _, log_ns, _ = message_head(data, pos)
            messages.append((log_ns, channel, data[pos + mhead : end]))
        elif opcode == Opcode.SCHEMA:
            others.append(Schema.read(stream(data[pos:end])))
        elif opcode == Opcode.CHANNEL:
            others.append(Channel.read(stream(data[pos:end])))
        pos = end
    return messages, others


def block_records(opcode: int, body: bytes, validate: bool = False) -> tuple[list[Record], list]:
    """(messages, schema and channel records) of a chunk or an unchunked message record."""
    if opcode == Opcode.CHUNK:
        return chunk_records(body, validate)
    rec = McapMessage.read(stream(body), len(body))
    return [(rec.log_time, rec.channel_id, rec.data)], []


# --------------------------------------------------------------------------- other records


def check_header(body: bytes) -> None:
    """A header record: profile and library strings, nothing else."""
    _, pos = _string(body, 0)
    _, pos = _string(body, pos)
    _exactly(body, pos, "header")


def parse_metadata(body: bytes) -> tuple[str, dict[str, Any]]:
    """(name, value) of a metadata record: a walker log's {"json": text} is the decoded JSON
    object, any other map itself."""
    name, pos = _string(body, 0)
    (size,) = _U32.unpack_from(body, pos)
    pos += 4
    end = pos + size
    _exactly(body, end, "metadata")
    entries: dict[str, str] = {}
    while pos < end:
        key, pos = _string(body, pos)
        entries[key], pos = _string(body, pos)
    if pos != end:
        raise Damaged("metadata map overruns its size")
    if set(entries) != {"json"}:
        return name, entries
    try:
        return name, json.loads(entries["json"])
    except ValueError:
        raise Damaged(f"metadata record {name!r} is not JSON") from None


def parse_attachment(body: bytes) -> Attachment:
    """An attachment record, its CRC checked when it has one."""
    name, pos = _string(body, 16)
    media_type, pos = _string(body, pos)
    (size,) = _U64.unpack_from(body, pos)
    pos += 8
    _exactly(body, pos + size + 4, "attachment")
    (crc,) = _U32.unpack_from(body, pos + size)
    if crc and zlib.crc32(memoryview(body)[: pos + size]) != crc:
        raise Damaged("attachment CRC mismatch")
    log_time, create_time = struct.unpack_from("<QQ", body, 0)
    return Attachment(create_time, log_time, name, media_type, body[pos : pos + size])


def check_message_index(body: bytes) -> None:
    """A message index record (channel id, then (log time, offset) pairs); the reader does
    not use its content."""
    _, size = _U16_U32.unpack_from(body, 0)
    if _U16_U32.size + size != len(body) or size % 16:
        raise Damaged("message index sizes do not add up")


def parse_declaration(opcode: int, body: bytes) -> Schema | Channel:
    """An unchunked schema or channel record."""
    data = stream(body)
    record = Schema.read(data) if opcode == Opcode.SCHEMA else Channel.read(data)
    _exactly(body, data.count, opcode_name(opcode))
    return record
