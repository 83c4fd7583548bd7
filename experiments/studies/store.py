"""A study's results on disk: SQLite (one row per run) and CSV, as `experiments.compare`.

`write_results(out, rows, columns, paths)` (re)creates `results.db` and `results.csv`
for this study's runs only. The `runs` table has one column per entry of `columns`
(numbers REAL or INTEGER, the rest TEXT; dicts and lists stored as JSON); the `paths`
table holds each run's true and estimated path (JSON lists of [t, x, y, θ] rows) so
figures can be redrawn without re-running.

    sqlite3 results.db "SELECT controller, AVG(collisions_total) FROM runs GROUP BY 1"
"""

from __future__ import annotations

import csv
import json
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _sql_type(values: list[Any]) -> str:
    vals = [v for v in values if v is not None and v != ""]
    if vals and all(isinstance(v, bool | int) for v in vals):
        return "INTEGER"
    if vals and all(isinstance(v, int | float) and not isinstance(v, bool) for v in vals):
        return "REAL"
    return "TEXT"


def _cell(v: Any) -> Any:
    if isinstance(v, dict | list | tuple):
        return json.dumps(v, default=str)
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, np.generic):
        return v.item()
    return v


def _rounded(a: np.ndarray) -> list:
    a = np.asarray(a, float)
    if a.size == 0:
        return []
    out = np.column_stack([np.round(a[:, 0], 3), np.round(a[:, 1:3], 4), np.round(a[:, 3], 5)])
    return out.tolist()


def write_results(
    out: Path,
    rows: Sequence[dict[str, Any]],
    columns: Sequence[str],
    paths: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
) -> dict[str, Path]:
    """Write `rows` (dicts with at least `columns`) to out/results.db and out/results.csv;
    `paths[i]` = (true path, estimated path) of rows[i]. Returns the files."""
    out.mkdir(parents=True, exist_ok=True)
    db_path, csv_path = out / "results.db", out / "results.csv"
    db_path.unlink(missing_ok=True)  # this study's runs only, like the CSV
    types = {c: _sql_type([r.get(c) for r in rows]) for c in columns}
    db = sqlite3.connect(db_path)
    try:
        cols = ", ".join(f'"{c}" {types[c]}' for c in columns)
        db.execute(f"CREATE TABLE runs (id INTEGER PRIMARY KEY, {cols})")
        db.execute("CREATE TABLE paths (run_id INTEGER PRIMARY KEY, truth TEXT, estimate TEXT)")
        marks = ", ".join("?" for _ in columns)
        names = ", ".join(f'"{c}"' for c in columns)
        for i, r in enumerate(rows):
            cur = db.execute(
                f"INSERT INTO runs ({names}) VALUES ({marks})", [_cell(r.get(c)) for c in columns]
            )
            if paths is not None:
                truth, est = paths[i]
                db.execute(
                    "INSERT INTO paths VALUES (?, ?, ?)",
                    (cur.lastrowid, json.dumps(_rounded(truth)), json.dumps(_rounded(est))),
                )
        db.commit()
    finally:
        db.close()
    with csv_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow(["" if r.get(c) is None else _cell(r.get(c)) for c in columns])
    return {"results_db": db_path, "results_csv": csv_path}
