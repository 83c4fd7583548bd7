"""How fast the datasets' text tables are read: every table of MRCLAM datasets 1 and 7
(robots 1-5) and Victoria Park, through `hardware.datasets.textio.read_table` as the
importers call it.

Usage: .venv/bin/python benchmarks/bench_dataset_tables.py [--repeat N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import hardware.datasets.mrclam as mrclam
import hardware.datasets.victoria_park as victoria_park
from hardware.datasets import open_dataset
from hardware.datasets.textio import read_table

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def read_all() -> dict[str, float]:
    """Open every dataset, timing its read_table calls: files, rows, seconds."""
    spent = {"files": 0, "rows": 0, "s": 0.0}

    def timed(path, columns, **kw):
        t0 = time.perf_counter()
        table = read_table(path, columns, **kw)
        spent["s"] += time.perf_counter() - t0
        spent["files"] += 1
        spent["rows"] += len(table)
        return table

    mrclam.read_table = victoria_park.read_table = timed
    try:
        for folder in ("mrclam_dataset1", "mrclam_dataset7"):
            for robot in (1, 2, 3, 4, 5):
                if any((DATA / folder).glob(f"Robot{robot}_Odometry.dat*")):
                    open_dataset("mrclam", DATA / folder, robot=robot, calibration="none")
        open_dataset("victoria-park", DATA / "victoria_park")
    finally:
        mrclam.read_table = victoria_park.read_table = read_table
    return spent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="runs (the fastest is reported)")
    args = ap.parse_args()
    best = min((read_all() for _ in range(args.repeat)), key=lambda r: r["s"])
    print(
        f"{best['files']} tables, {best['rows']} rows: {best['s']:.2f} s "
        f"({1e6 * best['s'] / best['rows']:.2f} µs per row)"
    )


if __name__ == "__main__":
    main()
