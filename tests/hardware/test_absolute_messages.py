"""Compass headings and position fixes in a trial log: exact round trips through real MCAP
files, their topics and JSON schemas as any MCAP reader sees them."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

from mcap.reader import make_reader

from hardware.calibration import WalkerCalibration
from hardware.log import TOPICS, LogWriter, read_log
from hardware.messages import MESSAGE_TYPES, CompassHeading, PositionFix, VelocityOdometry


def bits(x: float) -> bytes:
    return struct.pack("<d", x)


def messages() -> list:
    """Awkward values: unknown σ (NaN), ±π, the smallest subnormal, a long epoch time."""
    t0 = 1115116000.462817
    return [
        VelocityOdometry(t0, 0.1, -0.2),
        CompassHeading(t0, math.pi, 0.25),
        PositionFix(t0, 0.106859, -1e6 / 7, 0.5),
        CompassHeading(t0 + 1 / 3, -math.pi + 1e-15),  # σ unknown: NaN
        PositionFix(t0 + 1 / 3, -0.0, 5e-324),
        CompassHeading(t0 + 2, 0.1, math.inf),
    ]


def test_the_types_are_messages_with_topics():
    assert CompassHeading in MESSAGE_TYPES and PositionFix in MESSAGE_TYPES
    assert TOPICS[CompassHeading] == "/compass"
    assert TOPICS[PositionFix] == "/fix"


def test_compass_and_fix_round_trip_exactly(tmp_path: Path):
    path = tmp_path / "abs.mcap"
    written = messages()
    with LogWriter(path, WalkerCalibration()) as log:
        for m in written:
            log.write(m)
    trial = read_log(path)
    assert trial.topics == {
        "/odometry/velocity": VelocityOdometry,
        "/compass": CompassHeading,
        "/fix": PositionFix,
    }
    got = list(trial.messages())
    assert [type(m) for m in got] == [type(m) for m in written]
    for a, b in zip(written, got, strict=True):
        for name in a.__slots__:
            u, v = getattr(a, name), getattr(b, name)
            assert isinstance(v, float)
            assert (math.isnan(u) and math.isnan(v)) or bits(u) == bits(v), (a, b)
    assert math.isnan(got[3].sigma_rad) and math.isnan(got[4].sigma_m)
    assert got[5].sigma_rad == math.inf


def test_plain_mcap_reader_sees_json_with_schema(tmp_path: Path):
    """Any MCAP reader gets strict JSON (NaN as the string "NaN") and a JSON Schema that
    names every field."""
    path = tmp_path / "abs.mcap"
    with LogWriter(path, WalkerCalibration()) as log:
        log.write(CompassHeading(2.0, -1.5))
        log.write(PositionFix(2.5, 3.0, -4.0, 0.5))
    with open(path, "rb") as f:
        seen = {
            channel.topic: (schema, json.loads(message.data))
            for schema, channel, message in make_reader(f).iter_messages()
        }
    schema, payload = seen["/compass"]
    assert schema.name == "walker.CompassHeading" and schema.encoding == "jsonschema"
    assert payload == {"t": 2.0, "heading_rad": -1.5, "sigma_rad": "NaN"}
    assert json.loads(schema.data)["required"] == ["t", "heading_rad", "sigma_rad"]
    schema, payload = seen["/fix"]
    assert schema.name == "walker.PositionFix"
    assert payload == {"t": 2.5, "x": 3.0, "y": -4.0, "sigma_m": 0.5}
    assert json.loads(schema.data)["required"] == ["t", "x", "y", "sigma_m"]
