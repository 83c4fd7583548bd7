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
) -> Path:
    """A GMapping-corrected CARMEN log like intel.gfs.log: a robot driving arcs with raw
    odometry printed to 6 significant digits (so the increments are not arc-consistent),
    corrected scan poses = raw pose + a growing correction, a reset ODOM line (timestamp
    0) and a NEFF line after each FLASER, and (backsteps) ODOM timestamps that step back
    inside segments. Scan k's last ODOM line has the scan's timestamp."""
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
        ranges = " ".join(_fmt(v) for v in 1.0 + 5.0 * rng.random(beams))
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
