"""Shared helpers of the dataset importer tests: where the real data is, small synthetic
dataset files, and message comparison."""

from __future__ import annotations

import gzip
import math
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from hardware.messages import LaserScan, Message

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"


def data_dir(name: str) -> Path:
    """../shared/data/<name>, or skip the test with the reason."""
    p = DATA / name
    if not p.exists():
        pytest.skip(f"dataset {name} not found at {p}")
    return p


def write_text(path: Path, text: str, gz: bool = False) -> Path:
    """Write `text` to path (gzip-compressed when gz), CRLF kept as given."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = text.encode()
    path.write_bytes(gzip.compress(data) if gz else data)
    return path


def assert_same_messages(a: list[Message], b: list[Message]) -> None:
    """Equal type and fields, arrays equal with the same dtype (LaserScan has eq=False)."""
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert type(x) is type(y)
        for f in fields(x):
            u, v = getattr(x, f.name), getattr(y, f.name)
            if isinstance(u, np.ndarray):
                assert u.dtype == v.dtype and np.array_equal(u, v, equal_nan=True)
            else:
                assert u == v or (isinstance(u, float) and math.isnan(u) and math.isnan(v))


def scans_of(messages: list[Message]) -> list[LaserScan]:
    return [m for m in messages if isinstance(m, LaserScan)]


# --- MRCLAM --------------------------------------------------------------------------

MRCLAM_HEADER = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\r\n# test\r\n"


def write_mrclam(folder: Path, gz: bool = False, groundtruth: bool = True) -> Path:
    """A tiny MRCLAM folder: robots 1 and 2, landmarks 6 and 7 (barcodes 63, 81), robot 2
    is barcode 14; barcode 99 is spurious. CRLF and TABs as in the originals."""
    ext = ".dat.gz" if gz else ".dat"

    def table(rows: list[str]) -> str:
        return MRCLAM_HEADER + "".join(f"  {r} \r\n" for r in rows)

    write_text(
        folder / f"Barcodes{ext}", table(["1 \t   5", "2 \t  14", "6 \t  63", "7 \t  81"]), gz
    )
    write_text(
        folder / f"Landmark_Groundtruth{ext}",
        table(["6 \t 1.0 \t 2.0 \t 0.001 \t 0.002", "7 \t -1.5 \t 0.5 \t 0.001 \t 0.002"]),
        gz,
    )
    for r in (1, 2):
        write_text(
            folder / f"Robot{r}_Odometry{ext}",
            table(
                [
                    "1000.000 \t 0.1 \t 0.0",
                    "1000.500 \t 0.1 \t 0.2",
                    "1001.000 \t 0.0 \t 0.0",
                    "1001.000 \t 0.05 \t 0.0",
                ]
            ),
            gz,
        )
        write_text(
            folder / f"Robot{r}_Measurement{ext}",
            table(
                [
                    "1000.200 \t 63 \t 1.5 \t 0.1",
                    "1000.200 \t 14 \t 2.0 \t -0.3",
                    "1000.700 \t 99 \t 3.0 \t 0.0",
                    "1000.900 \t 81 \t 2.5 \t 1.0",
                ]
            ),
            gz,
        )
        if groundtruth:
            write_text(
                folder / f"Robot{r}_Groundtruth{ext}",
                table(
                    [
                        "999.900 \t 0.0 \t 0.0 \t 0.0",
                        "1000.100 \t 0.02 \t 0.0 \t 0.0",
                        "1001.100 \t 0.1 \t 0.01 \t 3.2",
                    ]
                ),
                gz,
            )
    return folder


# --- CARMEN --------------------------------------------------------------------------


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _compose(a, b):
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def _inverse(a):
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2])


def write_carmen(
    path: Path,
    *,
    scans: int = 6,
    lines_per_scan: int = 7,
    beams: int = 180,
    gz: bool = False,
    backsteps: bool = True,
    seed: int = 0,
    ranges_m: tuple[float, float] = (1.0, 6.0),
) -> Path:
    """A GMapping-corrected CARMEN log like intel.gfs.log: a robot driving arcs with raw
    odometry printed to 6 significant digits (so the increments are not arc-consistent),
    corrected scan poses = raw pose + a growing correction, a reset ODOM line (timestamp
    0) and a NEFF line after each FLASER, and (backsteps) ODOM timestamps that step back
    inside segments. Scan k's last ODOM line has the scan's timestamp. Readings are
    uniform in `ranges_m`."""
    rng = np.random.default_rng(seed)
    lines = ["# synthetic CARMEN log", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    raw = (0.0, 0.0, 0.0)
    frame_origin_raw = raw  # raw pose at the last scan
    frame_origin_out = raw  # printed pose at the last scan (the reset pose)
    correction = (0.0, 0.0, 0.0)
    t = 0.0
    for k in range(scans + 1):
        n = lines_per_scan
        times = t + 0.2 * np.arange(1, n + 1)
        if backsteps and k % 2 == 1 and n >= 4:
            times[1], times[2] = times[2], times[1] - 0.35  # steps back
        for j in range(n):
            ds = 0.04 + 0.02 * rng.random() if k % 3 else 0.001 * rng.random()
            dth = 0.08 * math.sin(0.7 * k + 0.3 * j) + 0.01 * rng.standard_normal()
            half = 0.5 * dth
            chord = ds * (math.sin(half) / half if abs(half) > 1e-12 else 1.0)
            # a little lateral slip so the increments are not arcs
            step = (
                chord * math.cos(half),
                chord * math.sin(half) + 2e-4 * rng.standard_normal(),
                dth,
            )
            raw = _compose(raw, step)
            out = _compose(frame_origin_out, _compose(_inverse(frame_origin_raw), raw))
            ts = _fmt(times[j])
            x, y, th = (_fmt(v) for v in out)
            lines.append(f"ODOM {x} {y} {th} 0 0 0 {ts} pippo {ts}")
        t = float(times.max())
        if k == scans:
            break
        correction = _compose(correction, (0.01 * rng.standard_normal(), 0.01, 0.005))
        corr = _compose(correction, raw)
        pose = " ".join(_fmt(v) for v in corr)
        lo, hi = ranges_m
        ranges = " ".join(_fmt(v) for v in lo + (hi - lo) * rng.random(beams))
        ts = _fmt(times[-1])
        lines.append(f"FLASER {beams} {ranges} {pose} {pose} {ts} pippo {ts}")
        lines.append(f"ODOM {pose} 0 0 0 0 pippo 0")
        lines.append(f"NEFF {50 - k}")
        frame_origin_raw = raw
        frame_origin_out = tuple(float(_fmt(v)) for v in corr)
    return write_text(path, "\n".join(lines) + "\n", gz)


def chain_of(path: Path) -> tuple[list[tuple], list[tuple]]:
    """(reset poses after each scan, last ODOM pose before each scan) as printed."""
    opener = gzip.open if path.read_bytes()[:2] == b"\x1f\x8b" else open
    resets, ends = [], []
    last_odom = None
    after_scan = None
    with opener(path, "rt") as f:
        for line in f:
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "ODOM":
                pose = tuple(float(v) for v in tok[1:4])
                if after_scan is not None and pose == after_scan:
                    resets.append(pose)
                else:
                    last_odom = pose
                after_scan = None
            elif tok[0] == "FLASER":
                n = int(tok[1])
                ends.append(last_odom)
                after_scan = tuple(float(v) for v in tok[2 + n : 5 + n])
    return resets, ends


# --- Victoria Park -------------------------------------------------------------------


def write_victoria_park(folder: Path, gz: bool = True) -> Path:
    ext = ".csv.gz" if gz else ".csv"
    write_text(
        folder / f"aa3_dr{ext}",
        "# converted from aa3_dr.mat: time_ms,speed_mps,steering_rad\n"
        "21940,0.0,-0.0034\n22000,2.0,0.0\n22100,2.0,0.1\n22200,3.0,-0.2\n22300,0.0,0.0\n",
        gz,
    )
    write_text(
        folder / f"tree_detections{ext}",
        "# converted: scan_index,time_s,range_m,bearing_rad,diameter_m\n"
        f"0,21.95,10.0,{math.pi / 2},0.3\n0,21.95,5.0,0.5,0.2\n1,22.15,7.5,2.5,0.4\n",
        gz,
    )
    write_text(
        folder / f"aa3_gpsx{ext}",
        "# converted from aa3_gpsx.mat: timeGps_ms,Lo_m,La_m\n"
        "20967,-67.6,-41.7\n21968,-67.7,-41.6\n22168,-67.5,-41.8\n",
        gz,
    )
    return folder


# --- MTRX5700 ------------------------------------------------------------------------

MTRX_T0_S = 1115116000
MTRX_SCALE = 0.97  # the walker moves this much of what its velocities say
MTRX_START = (0.3, -0.2, 0.4)
MTRX_BEACONS = [(-2.531, -9.854), (3.83, -5.523), (13.761, 9.761)]


def _mtrx_stamp(t: float) -> str:
    us = round(t * 1e6)
    return f"{MTRX_T0_S + us // 1_000_000} {us % 1_000_000}"


def mtrx_truth(t: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The synthetic walker's true poses: exact arcs of MTRX_SCALE·(v, ω) from MTRX_START
    (integrated here with slam.motion, independently of the importer's own code)."""
    from slam.motion import apply_increment

    poses = [np.array(MTRX_START, dtype=float)]
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        poses.append(apply_increment(poses[-1], MTRX_SCALE * v[k] * dt, MTRX_SCALE * w[k] * dt))
    return np.array(poses)


def write_mtrx5700(folder: Path, seed: int = 0, rows: int = 900, gz: bool = False) -> Path:
    """A small MTRX5700 folder as the originals are (CRLF, `%` headers): velocity rows every
    0.1 s, every 8th with a fix (true + N(0, 0.5 m)), every 10th with a compass heading
    (true heading in [0, 2π) + N(0, 0.25 rad)), three beacons; seeded."""
    rng = np.random.default_rng(seed)
    t = 0.462817 + 0.1 * np.arange(rows)
    v = np.round(0.3 + 0.1 * np.sin(t / 5.0), 6)
    w = np.round(0.25 * np.sin(t / 7.0), 6)
    truth = mtrx_truth(t, v, w)
    ext = ".gz" if gz else ""
    head = "% {name}\r\n% \r\n% simulated test data\r\n%\r\n% columns\r\n"
    vel = [f"{_mtrx_stamp(ti)} {vi:.6f} {wi:.6f}\r\n" for ti, vi, wi in zip(t, v, w, strict=True)]
    fixes, headings = [], []
    for k in range(0, rows, 8):
        x, y = truth[k, :2] + rng.normal(0.0, 0.5, 2)
        fixes.append(f"{_mtrx_stamp(t[k])} {x:.6f} {y:.6f}\r\n")
    for k in range(0, rows, 10):
        heading = truth[k, 2] % (2 * math.pi) + rng.normal(0.0, 0.25)
        headings.append(f"{_mtrx_stamp(t[k])} {heading:.6f}\r\n")
    beacons = [f"{x:.3f} {y:.3f}\r\n" for x, y in MTRX_BEACONS]
    for name, lines in (
        ("velocityObs.txt", vel),
        ("positionObs.txt", fixes),
        ("compassObs.txt", headings),
        ("laserFeatures.txt", beacons),
    ):
        write_text(folder / (name + ext), head.format(name=name) + "".join(lines), gz)
    return folder
