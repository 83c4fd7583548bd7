"""The walker board's serial line protocol (version 1): CRC-8 framing and the line types.

The protocol is specified in `hardware/firmware/PROTOCOL.md`; this module is its host
side, shared by the serial driver (`hardware.arduino`) and the pure-Python board
emulator (`hardware.board_emulator`), which speaks the board's side with the same codec.

    line = encode("B", 7, 120, 0)             # b"B,7,120,0*71\\n"
    msg = parse_board_line(b"T,1,10000,4,-2,0,0,1*..")   # -> Tick(...)

Parsing never acts on a bad line: it raises `LineError` whose `kind` says which counter
the line belongs to ("crc", "malformed", "overflow").
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

PROTOCOL_VERSION = 1
BAUD = 115200
MAX_LINE = 96  # bytes of a line, '*CC' included, '\n' not (the longest S line: 92)
TICK_TIMEOUT_FLAG = 0x01  # T flags bit 0: no valid B line within 300 ms (brakes released)
TICK_QUAD_ERROR_FLAG = 0x02  # T flags bit 1: a quadrature error since the last report
COMMAND_TIMEOUT_S = 0.3  # the board releases both brakes this long after the last B line
UINT32 = 1 << 32
GYRO_LSB_PER_10DPS = 1310  # an MPU-6050 at ±250 °/s: 131 LSB per °/s (H announces it)
_I16 = (-(1 << 15), (1 << 15) - 1)

_VERSION_RE = re.compile(rb"^[0-9A-Za-z._-]{1,16}$")


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS: polynomial 0x07, init 0, no reflection, no final XOR."""
    return _crc8(data)


def _make_table() -> list[int]:
    table = []
    for byte in range(256):
        c = byte
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    return table


_TABLE = _make_table()


def _crc8(data: bytes) -> int:
    c = 0
    for b in data:
        c = _TABLE[c ^ b]
    return c


def encode(kind: str, *fields: int | str) -> bytes:
    """One protocol line: kind and fields joined by commas, '*', the CRC, '\\n'."""
    payload = ",".join([kind, *(str(f) for f in fields)]).encode("ascii")
    line = payload + b"*%02X" % _crc8(payload)
    if len(line) > MAX_LINE:
        raise ValueError(f"protocol line longer than {MAX_LINE} bytes: {line!r}")
    return line + b"\n"


class LineError(ValueError):
    """A line that must not be acted on; `kind` is the counter it belongs to:
    'crc' (wrong checksum), 'malformed' (no '*CC', unknown type, bad or missing field),
    'overflow' (longer than MAX_LINE)."""

    def __init__(self, kind: str, line: bytes, why: str) -> None:
        super().__init__(f"{kind}: {why}: {line[:40]!r}")
        self.kind = kind
        self.line = line


def split(line: bytes) -> tuple[bytes, list[bytes]]:
    """Check a line's framing and CRC; return its type letter and raw fields."""
    line = line.rstrip(b"\r\n")
    if len(line) > MAX_LINE:
        raise LineError("overflow", line, "line too long")
    payload, star, cc = line.rpartition(b"*")
    if not star or len(cc) != 2:
        raise LineError("malformed", line, "no *CC checksum")
    try:
        expected = int(cc, 16)
    except ValueError:
        raise LineError("malformed", line, "checksum is not hex") from None
    if _crc8(payload) != expected:
        raise LineError("crc", line, "checksum mismatch")
    parts = payload.split(b",")
    if len(parts[0]) != 1:
        raise LineError("malformed", line, "type is not one letter")
    return parts[0], parts[1:]


def _int(raw: bytes, lo: int, hi: int, line: bytes) -> int:
    if not re.fullmatch(rb"-?[0-9]{1,11}", raw):
        raise LineError("malformed", line, f"field {raw!r} is not an integer")
    v = int(raw)
    if not lo <= v <= hi:
        raise LineError("malformed", line, f"field {v} outside [{lo}, {hi}]")
    return v


_U32 = (0, UINT32 - 1)
_I32 = (-(1 << 31), (1 << 31) - 1)
_PWM = (0, 255)


def gyro_rate(raw: int, lsb_per_10dps: int) -> float:
    """A T line's gyro field [LSB] as a yaw rate [rad/s], with the scale H announced."""
    return math.radians(raw * 10.0 / lsb_per_10dps)


def gyro_raw(rate_rad_s: float, lsb_per_10dps: int = GYRO_LSB_PER_10DPS) -> int:
    """A yaw rate [rad/s] as the gyro's int16 output (rounded, saturated at its range)."""
    lsb = round(math.degrees(rate_rad_s) * lsb_per_10dps / 10.0)
    return min(max(lsb, _I16[0]), _I16[1])


# -- board -> host -----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Handshake:
    """`gyro_lsb_per_10dps`: the scale of the T lines' gyro field (LSB per 10 °/s),
    None when the board has no gyro (the optional sixth field)."""

    proto: int
    firmware: str
    rate_hz: int
    cpr: int
    reset_flags: int
    gyro_lsb_per_10dps: int | None = None

    RESET_CAUSES = ((1, "power-on"), (2, "external"), (4, "brown-out"), (8, "watchdog"))

    @property
    def reset_cause(self) -> str:
        names = [n for bit, n in self.RESET_CAUSES if self.reset_flags & bit]
        return "+".join(names) or "unknown"

    def line(self) -> bytes:
        fields = (self.proto, self.firmware, self.rate_hz, self.cpr, self.reset_flags)
        gyro = () if self.gyro_lsb_per_10dps is None else (self.gyro_lsb_per_10dps,)
        return encode("H", *fields, *gyro)


@dataclass(frozen=True, slots=True)
class Tick:
    """`gyro_z`: the gyro's z rate [LSB, int16] read for this report, None when the
    board has no gyro or the read failed (the optional eighth field)."""

    seq: int
    t_us: int
    left: int
    right: int
    pwm_left: int
    pwm_right: int
    flags: int
    gyro_z: int | None = None

    @property
    def timed_out(self) -> bool:
        return bool(self.flags & TICK_TIMEOUT_FLAG)

    def line(self) -> bytes:
        gyro = () if self.gyro_z is None else (self.gyro_z,)
        return encode(
            "T",
            self.seq,
            self.t_us,
            self.left,
            self.right,
            self.pwm_left,
            self.pwm_right,
            self.flags,
            *gyro,
        )


@dataclass(frozen=True, slots=True)
class Status:
    rx_lines: int
    rx_bad_crc: int
    rx_malformed: int
    rx_overflow: int
    cmd_timeouts: int
    cmd_seq_gaps: int
    quad_errors: int
    last_cmd_seq: int

    def line(self) -> bytes:
        return encode("S", *(getattr(self, f) for f in self.__dataclass_fields__))


BoardMessage = Handshake | Tick | Status


def parse_board_line(line: bytes) -> BoardMessage:
    """A line the board sent → Handshake, Tick or Status; LineError if it is bad."""
    kind, f = split(line)
    if kind == b"T":
        if len(f) < 7:
            raise LineError("malformed", line, "T needs 7 fields")
        return Tick(
            _int(f[0], *_U32, line),
            _int(f[1], *_U32, line),
            _int(f[2], *_I32, line),
            _int(f[3], *_I32, line),
            _int(f[4], *_PWM, line),
            _int(f[5], *_PWM, line),
            _int(f[6], 0, 255, line),
            _int(f[7], *_I16, line) if len(f) > 7 else None,
        )
    if kind == b"S":
        if len(f) < 8:
            raise LineError("malformed", line, "S needs 8 fields")
        return Status(*(_int(x, *_U32, line) for x in f[:8]))
    if kind == b"H":
        if len(f) < 5:
            raise LineError("malformed", line, "H needs 5 fields")
        if not _VERSION_RE.match(f[1]):
            raise LineError("malformed", line, "bad firmware version")
        return Handshake(
            _int(f[0], 0, 255, line),
            f[1].decode("ascii"),
            _int(f[2], 1, 500, line),
            _int(f[3], 1, 1 << 20, line),
            _int(f[4], 0, 255, line),
            _int(f[5], 1, 65535, line) if len(f) > 5 else None,
        )
    raise LineError("malformed", line, f"unknown board line type {kind!r}")


# -- host -> board -----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Query:
    def line(self) -> bytes:
        return encode("Q")


@dataclass(frozen=True, slots=True)
class Brake:
    seq: int
    pwm_left: int
    pwm_right: int

    def line(self) -> bytes:
        return encode("B", self.seq % UINT32, self.pwm_left, self.pwm_right)


@dataclass(frozen=True, slots=True)
class Configure:
    rate_hz: int

    def line(self) -> bytes:
        return encode("C", self.rate_hz)


HostMessage = Query | Brake | Configure


def parse_host_line(line: bytes) -> HostMessage:
    """A line the host sent → Query, Brake or Configure; LineError if it is bad."""
    kind, f = split(line)
    if kind == b"Q":
        return Query()
    if kind == b"B":
        if len(f) < 3:
            raise LineError("malformed", line, "B needs 3 fields")
        return Brake(_int(f[0], *_U32, line), _int(f[1], *_PWM, line), _int(f[2], *_PWM, line))
    if kind == b"C":
        if len(f) < 1:
            raise LineError("malformed", line, "C needs 1 field")
        return Configure(_int(f[0], 1, 500, line))
    raise LineError("malformed", line, f"unknown host line type {kind!r}")


class LineSplitter:
    """Bytes in, complete lines out. A line longer than MAX_LINE is reported once as an
    overflow and the rest of it, up to the next newline, discarded. A partial line (the
    tail of one sent before the port opened) comes out as a line and fails to parse."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._overflowing = False

    def feed(self, data: bytes) -> list[bytes | LineError]:
        out: list[bytes | LineError] = []
        start = 0
        while True:
            nl = data.find(b"\n", start)
            if nl < 0:
                self._append(data[start:], out)
                return out
            self._append(data[start:nl], out)
            line, self._buf = bytes(self._buf), bytearray()
            if not self._overflowing and line.strip(b"\r"):
                out.append(line)
            self._overflowing = False
            start = nl + 1

    def _append(self, data: bytes, out: list[bytes | LineError]) -> None:
        if self._overflowing:
            return
        self._buf += data
        if len(self._buf) > MAX_LINE + 1:  # + a '\r'
            out.append(LineError("overflow", bytes(self._buf), "line too long"))
            self._buf = bytearray()
            self._overflowing = True
