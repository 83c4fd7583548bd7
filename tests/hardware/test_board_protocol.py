"""The board's line protocol (hardware/firmware/PROTOCOL.md): CRC-8, line types, framing."""

from __future__ import annotations

import math

import pytest

from hardware import board_protocol as bp


def test_crc8_check_value_and_single_bit_errors():
    assert bp.crc8(b"123456789") == 0xF4  # CRC-8/SMBUS check value
    line = b"T,41,410000,1024,-7,0,0,0"
    good = bp.crc8(line)
    for i in range(len(line)):
        for bit in range(8):
            flipped = bytearray(line)
            flipped[i] ^= 1 << bit
            assert bp.crc8(bytes(flipped)) != good


@pytest.mark.parametrize(
    "msg",
    [
        bp.Tick(0, 0, 0, 0, 0, 0, 1),
        bp.Tick(2**32 - 1, 2**32 - 1, -(2**31), 2**31 - 1, 255, 17, 3),
        bp.Status(1, 2, 3, 4, 5, 6, 7, 2**32 - 1),
        bp.Handshake(1, "0.1.0-rc1", 100, 256, 9),
        bp.Tick(5, 50000, 1, 2, 0, 0, 0, gyro_z=-32768),
        bp.Tick(2**32 - 1, 2**32 - 1, -(2**31), 2**31 - 1, 255, 17, 3, gyro_z=32767),
        bp.Handshake(1, "1.0.0", 100, 256, 1, gyro_lsb_per_10dps=1310),
    ],
)
def test_board_lines_round_trip(msg):
    line = msg.line()
    assert line.endswith(b"\n") and len(line) - 1 <= bp.MAX_LINE
    assert bp.parse_board_line(line) == msg


@pytest.mark.parametrize("msg", [bp.Query(), bp.Brake(7, 120, 0), bp.Configure(250)])
def test_host_lines_round_trip(msg):
    assert bp.parse_host_line(msg.line()) == msg


def test_documented_example_line():
    assert bp.encode("B", 7, 120, 0) == b"B,7,120,0*71\n"


@pytest.mark.parametrize(
    ("line", "kind"),
    [
        (b"T,1,2,3,4,5,6,7*00", "crc"),
        (b"T,1,2,3,4,5,6,7", "malformed"),  # no checksum
        (b"garbage", "malformed"),
        (b"x" * 120, "overflow"),
    ],
)
def test_bad_lines_are_classified(line, kind):
    with pytest.raises(bp.LineError) as e:
        bp.parse_board_line(line)
    assert e.value.kind == kind


def _framed(payload: bytes) -> bytes:
    return payload + b"*%02X" % bp.crc8(payload)


@pytest.mark.parametrize(
    "payload",
    [
        b"T,1,2,3",  # too few fields
        b"T,1,2,3,4,256,0,0",  # PWM out of range
        b"T,1,2,3,4,x,0,0",  # not a number
        b"T,-1,2,3,4,5,6,7",  # negative sequence number
        b"Z,1",  # unknown type
        b"H,1,bad version!,100,256,1",
    ],
)
def test_well_framed_but_invalid_lines_are_malformed(payload):
    with pytest.raises(bp.LineError) as e:
        bp.parse_board_line(_framed(payload))
    assert e.value.kind == "malformed"


def test_host_side_rejects_out_of_range_brake_and_rate():
    for payload in (b"B,1,300,0", b"B,1,0", b"C,0", b"C,501"):
        with pytest.raises(bp.LineError):
            bp.parse_host_line(_framed(payload))


def test_splitter_partial_lines_overflow_and_chunks():
    sp = bp.LineSplitter()
    tick = bp.Tick(3, 30000, 1, 2, 0, 0, 0).line()
    # the tail of a line sent before the port opened, then a line split across reads
    out = sp.feed(b"5,0,0,1*4C\n" + tick[:10]) + sp.feed(tick[10:])
    assert out == [b"5,0,0,1*4C", tick[:-1]]
    with pytest.raises(bp.LineError):
        bp.parse_board_line(out[0])
    out = sp.feed(b"y" * 200 + b"\r\n" + tick)
    assert len(out) == 2 and isinstance(out[0], bp.LineError) and out[0].kind == "overflow"
    assert bp.parse_board_line(out[1]) == bp.Tick(3, 30000, 1, 2, 0, 0, 0)
    assert sp.feed(b"\n\r\n") == []  # empty lines are not lines


def test_the_gyro_fields_are_optional_and_checked():
    """A board without an IMU sends the lines as before (no gyro); a gyro value outside
    int16, or a zero scale, is malformed; fields after those known are ignored."""
    plain = bp.parse_board_line(bp.encode("T", 1, 10000, 3, 4, 0, 0, 1))
    assert plain == bp.Tick(1, 10000, 3, 4, 0, 0, 1) and plain.gyro_z is None
    assert bp.parse_board_line(bp.encode("H", 1, "1.0.0", 100, 256, 1)).gyro_lsb_per_10dps is None
    assert bp.parse_board_line(bp.encode("T", 1, 2, 3, 4, 0, 0, 0, -7, 99)).gyro_z == -7
    for bad in (bp.encode("T", 1, 2, 3, 4, 0, 0, 0, 32768), bp.encode("H", 1, "1", 100, 256, 1, 0)):
        with pytest.raises(bp.LineError) as e:
            bp.parse_board_line(bad)
        assert e.value.kind == "malformed"


def test_gyro_scale_conversions():
    """131 LSB per °/s: 1310 per 10 °/s; rates round to the nearest LSB and saturate."""
    assert bp.gyro_raw(math.radians(10.0)) == 1310
    assert bp.gyro_raw(math.radians(-1.0) / 131 * 2.4) == -2
    assert bp.gyro_rate(1310, 1310) == pytest.approx(math.radians(10.0), rel=1e-15)
    assert (bp.gyro_raw(math.radians(400.0)), bp.gyro_raw(-10.0)) == (32767, -32768)
    for raw in (-32768, -1, 0, 1, 4321, 32767):
        assert bp.gyro_raw(bp.gyro_rate(raw, 1310)) == raw
