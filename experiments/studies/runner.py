"""Run a study's planned trials and keep them: the part the course and corner studies
share. `run_and_store` runs the RunSpecs on the chosen engine, turns each result into a
database row and writes results.db / results.csv; `write_json` writes study.json."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.simulation import RunSpec
from experiments.studies.engine import run_tasks
from experiments.studies.store import write_results
from experiments.studies.trial import run_trial


@dataclass
class StudyResult:
    """Every run's row, the study's summary table and the files written."""

    rows: list[dict[str, Any]]
    table: list[dict[str, Any]]
    files: dict[str, Path]


def run_and_store(
    specs: Sequence[RunSpec],
    out: Path,
    result_row: Callable[[dict[str, Any]], dict[str, Any]],
    columns: Sequence[str],
    *,
    engine: str,
    workers: int | None,
    address: str | None,
    progress: Callable[[int, int], None] | None,
    run: Callable[[RunSpec], dict[str, Any]] = run_trial,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Path]]:
    """(trial results, database rows, files) of the runs of `specs`, each run by `run`
    (a module-level function: `run_trial` by default)."""
    results = run_tasks(
        run, specs, engine=engine, workers=workers, address=address, progress=progress
    )
    rows = [result_row(r) for r in results]
    files = write_results(out, rows, columns, [(r["path"], r["estimate"]) for r in results])
    return results, rows, files


def write_json(path: Path, obj: dict[str, Any]) -> Path:
    path.write_text(json.dumps(obj, indent=2, default=str) + "\n")
    return path
