"""Compare localizers on recorded trials: every localizer on every log, stochastic ones
over several seeds; results as CSV, SQLite (one row per run, with its config) and a
Markdown report with the table (mean ± std over seeds) and trajectory figures."""

from __future__ import annotations

import csv
import json
import math
import sqlite3
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from experiments.calibration_override import CalibrationOverride
from experiments.config import configure
from experiments.metrics import GROUND_TRUTH, truth_names
from experiments.mitigations import check_calibration, check_source, resolve
from experiments.run import (
    MAP_BAND_M,
    ReplayResult,
    check_gyro,
    message_types,
    replay_log,
    source_metadata,
)
from hardware.datasets import Dataset
from hardware.log import TrialLog, read_log
from slam.base import LOCALIZERS

Source = str | Path | TrialLog | Dataset

COLUMNS = (
    "log",
    "localizer",
    "seed",
    "ate_rmse_m",
    "ate_rmse_unaligned_m",
    "rpe_trans_m",
    "relations_trans_mean_m",
    "relations_rot_mean_deg",
    "gps_rmse_m",
    "gps_rmse_unaligned_m",
    "landmark_rmse_m",
    "wall_spread_m",
    "phantom_area_m2",
    "runtime_s",
    "realtime_factor",
)
NUMERIC = COLUMNS[3:]


def is_stochastic(localizer: str) -> bool:
    """A localizer whose config has a `seed` is run once per seed."""
    return any(f.name == "seed" for f in fields(LOCALIZERS.spec(localizer).config_type))


def parse_localizers(text: str) -> list[str]:
    names = LOCALIZERS.names()
    if text == "all":
        return names
    wanted = [n.strip() for n in text.split(",") if n.strip()]
    for n in wanted:
        LOCALIZERS.spec(n)  # raises UnknownNameError listing the valid names
    return wanted


@dataclass
class CompareResult:
    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    files: dict[str, Path]


def _row(log: str, localizer: str, seed: int | None, res: ReplayResult) -> dict[str, Any]:
    m = res.metrics
    row: dict[str, Any] = {"log": log, "localizer": localizer, "seed": "" if seed is None else seed}
    for key in NUMERIC:
        v = m.get(key)
        row[key] = "" if v is None or (isinstance(v, float) and math.isnan(v)) else v
    return row


MEAN_OVER_LOGS = "mean over logs"


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and std over seeds per (log, localizer); empty where not applicable.

    With several logs, each localizer also gets a row (log = MEAN_OVER_LOGS) holding the
    mean and std over the logs of its per-log means: the accuracy targets of dataset
    benchmarks (e.g. MRCLAM robots 1–5) are means over robots."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["log"], r["localizer"]), []).append(r)
    out = []
    for (log, loc), rs in groups.items():
        out.append({"log": log, "localizer": loc, "runs": len(rs), **_stats(rs)})
    if len({r["log"] for r in rows}) > 1:
        for loc in dict.fromkeys(r["localizer"] for r in rows):
            per_log = [
                {k: ("" if s[k] is None else s[k][0]) for k in NUMERIC}
                for s in out
                if s["localizer"] == loc and s["log"] != MEAN_OVER_LOGS
            ]
            out.append(
                {"log": MEAN_OVER_LOGS, "localizer": loc, "runs": len(per_log), **_stats(per_log)}
            )
    return out


def _stats(rows: list[dict[str, Any]]) -> dict[str, tuple[float, float] | None]:
    out: dict[str, tuple[float, float] | None] = {}
    for key in NUMERIC:
        vals = np.array([r[key] for r in rows if r[key] != ""], dtype=float)
        out[key] = (float(vals.mean()), float(vals.std())) if len(vals) else None
    return out


def source_name(source: Source) -> str:
    """The name a source's rows get: a log's file stem, a dataset's name."""
    if isinstance(source, Dataset):
        return source.name.replace("/", "_")
    return Path(source.path if isinstance(source, TrialLog) else source).stem


def compare(
    logs: Sequence[Source],
    localizers: Sequence[str],
    seeds: int,
    out_dir: str | Path,
    progress: Callable[[str], None] | None = None,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    calibration: CalibrationOverride | None = None,
    mitigations: Sequence[str] = (),
) -> CompareResult:
    """Every localizer on every source; `overrides` = {localizer: {field path: value}}
    changes fields of a localizer's default config, after the settings the source
    proposes (its metadata "localizer_settings", e.g. a dataset's fitted noise levels):
    `experiments.config.configure`. calibration: a file whose wheel diameters and track
    replace every source's (`experiments.calibration_override`). mitigations: applied to
    every localizer (`experiments.mitigations`; one that does not apply to one of them,
    or needs what a source lacks, fails before any run).

    (Its length is this docstring and the loop over sources, localizers and seeds.)"""
    for loc in localizers:
        check_calibration(resolve(mitigations, loc), calibration)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.db").unlink(missing_ok=True)  # this comparison's runs only, like the CSV
    db = sqlite3.connect(out / "results.db")
    db.execute(
        "CREATE TABLE runs (id INTEGER PRIMARY KEY, log TEXT, localizer TEXT, "
        "seed INTEGER, metrics TEXT, config TEXT, " + ", ".join(f"{c} REAL" for c in NUMERIC) + ")"
    )
    rows: list[dict[str, Any]] = []
    figures: dict[str, _LogPaths] = {}
    for source in logs:
        trial = source if isinstance(source, TrialLog | Dataset) else read_log(source)
        name = source_name(source)
        for loc in localizers:
            user = dict((overrides or {}).get(loc, {}))
            mitigated = resolve(mitigations, loc)
            check_source(mitigated, message_types(trial), name)
            settings = {**mitigated.localizer_settings, **user}
            built = configure(LOCALIZERS, loc, source_metadata(trial), settings)  # fail first
            check_gyro(built.config, trial, name)
            for seed in range(seeds) if is_stochastic(loc) else [None]:
                over = user if seed is None else {**user, "seed": seed}
                run_dir = out / name / loc / ("run" if seed is None else f"seed{seed}")
                if progress is not None:
                    progress(f"{name} · {loc}" + ("" if seed is None else f" · seed {seed}"))
                res = replay_log(
                    trial,
                    run_dir,
                    localizer=loc,
                    localizer_overrides=over,
                    figures=False,
                    reference_map=False,
                    drag_metrics=False,
                    calibration=calibration,
                    mitigations=mitigations,
                )
                row = _row(name, loc, seed, res)
                rows.append(row)
                _store(db, name, loc, seed, res, row, run_dir)
                if seed in (None, 0):
                    figures.setdefault(name, _LogPaths()).keep(loc, res)
    db.close()
    files = {"results_db": out / "results.db", "results_csv": out / "results.csv"}
    with files["results_csv"].open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows)
    files.update(_report(out, summary, figures))
    return CompareResult(rows, summary, files)


def _store(db, name: str, loc: str, seed, res: ReplayResult, row, run_dir: Path) -> None:
    """One run into results.db: its metrics, its config.json and the numeric columns."""
    config = json.loads((run_dir / "config.json").read_text())
    db.execute(
        "INSERT INTO runs (log, localizer, seed, metrics, config, "
        + ", ".join(NUMERIC)
        + ") VALUES (?, ?, ?, ?, ?, "
        + ", ".join("?" for _ in NUMERIC)
        + ")",
        (
            name,
            loc,
            seed,
            json.dumps(res.metrics, default=str),
            json.dumps(config),
            *[None if row[k] == "" else float(row[k]) for k in NUMERIC],
        ),
    )
    db.commit()


def _fmt(v: tuple[float, float] | None, runs: int) -> str:
    if v is None:
        return ""
    return f"{v[0]:.3f}" if runs == 1 else f"{v[0]:.3f} ± {v[1]:.3f}"


@dataclass
class _LogPaths:
    """What a log's trajectory figure draws: each localizer's path (seed 0 of a
    stochastic one), the true path and the true obstacle outlines, when known."""

    paths: dict[str, np.ndarray] = field(default_factory=dict)
    truth: np.ndarray | None = None
    truth_kind: str | None = None  # metrics groundtruth_kind
    outlines: list[np.ndarray] = field(default_factory=list)

    def keep(self, localizer: str, res: ReplayResult) -> None:
        if res.pipeline is None:
            return
        self.paths[localizer] = res.pipeline.localizer.trajectory().poses[:, :2]
        gt = res.pipeline.recorded.groundtruth_trajectory()
        if gt is not None:
            self.truth = gt.poses[:, :2]
            self.truth_kind = res.metrics.get("groundtruth_kind")
        if res.world is not None and not self.outlines:
            self.outlines = [p for _, p in res.world.footprint_polygons(*MAP_BAND_M)]


def _report(out: Path, summary, figures: dict[str, _LogPaths]) -> dict[str, Path]:
    from experiments.report import paths_figure, save

    files: dict[str, Path] = {}
    lines = [
        "# Localizer comparison",
        "",
        "Mean ± std over seeds for stochastic localizers; empty where not applicable.",
        "",
        "| " + " | ".join(["log", "localizer", "runs", *NUMERIC]) + " |",
        "|" + "---|" * (3 + len(NUMERIC)),
    ]
    for s in summary:
        cells = [s["log"], s["localizer"], str(s["runs"])] + [
            _fmt(s[k], s["runs"]) for k in NUMERIC
        ]
        lines.append("| " + " | ".join(cells) + " |")
    for name, drawn in figures.items():
        names = truth_names(drawn.truth_kind)
        fig = paths_figure(name, drawn.paths, drawn.truth, drawn.outlines, names)
        path = save(fig, out / f"{name}_trajectories.png")
        files[f"{name}_figure"] = path
        lines += ["", f"## {name}", ""]
        if names != GROUND_TRUTH:  # (a kind is kept only with a truth)
            lines += [f"Its errors are against {names.against}.", ""]
        lines.append(f"![trajectories]({path.name})")
    files["report"] = out / "report.md"
    files["report"].write_text("\n".join(lines) + "\n")
    return files
