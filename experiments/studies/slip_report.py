"""The slip study's ranking, figures and report (`experiments.studies.slip_study`).

Intervals are 95 % percentile bootstraps over users (`N_BOOT` resamples, seeded): a
mean's interval resamples the users of one cell; a paired difference's resamples users
keeping each user's treated and baseline runs together, so what differs between them is
the mitigation, not the user.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from experiments.mitigations import set_name
from experiments.studies.tables import BOOT_SEED, markdown

N_BOOT = 5_000
BASELINE = "none"
# What the ranking and the figures show: (column, label, unit, lower is better)
METRICS: tuple[tuple[str, str, str], ...] = (
    ("phantom_area_m2", "phantom area", "m²"),
    ("phantom_area_max_m2", "largest phantom area", "m²"),
    ("ate_rmse_m", "ATE", "m"),
    ("heading_error_braking_deg", "heading error added while braking", "°"),
    ("drag_added_braked_turn_m", "drag added within 1 s of braked turns", "m"),
    ("over_steer_deg", "over-steer per braking episode", "°"),
    ("collisions_total", "collisions", "per trial"),
    ("braking_impulse_nms", "braking impulse", "N·m·s"),
)


def _values(rows: Sequence[dict[str, Any]], column: str) -> np.ndarray:
    return np.array([np.nan if r.get(column) is None else float(r[column]) for r in rows])


def mean_interval(values: np.ndarray, seed: int = BOOT_SEED) -> tuple[float, float, float]:
    """(mean, low, high): the 95 % bootstrap interval of the mean over the finite values
    (NaN when none; no interval from one)."""
    v = values[np.isfinite(values)]
    if len(v) == 0:
        return math.nan, math.nan, math.nan
    if len(v) == 1:
        return float(v[0]), math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, len(v), size=(N_BOOT, len(v)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(v.mean()), float(low), float(high)


def _group(rows, keys: tuple[str, ...]) -> dict[tuple, list[dict[str, Any]]]:
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    return groups


def ranking(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per surface × localizer × controller, per mitigation set other than none, per
    metric: the baseline's mean, the paired mean difference with its interval and the
    relative change (module docstring). Sorted by surface, localizer, controller and
    then by the phantom area's difference (the best first)."""
    out = []
    for (surface, loc, ctl), group in _group(rows, ("surface", "localizer", "controller")).items():
        by_mitigation = _group(group, ("mitigation",))
        base = {r["trial"]: r for r in by_mitigation.get((BASELINE,), [])}
        if not base:
            continue
        for (mitigation,), treated in by_mitigation.items():
            if mitigation == BASELINE:
                continue
            pairs = [(r, base[r["trial"]]) for r in treated if r["trial"] in base]
            entry: dict[str, Any] = {
                "surface": surface,
                "localizer": loc,
                "controller": ctl,
                "mitigation": mitigation,
                "users": len(pairs),
            }
            for column, _, _ in METRICS:
                t = _values([p[0] for p in pairs], column)
                b = _values([p[1] for p in pairs], column)
                diff, low, high = mean_interval(t - b)
                base_mean = float(np.nanmean(b)) if np.isfinite(b).any() else math.nan
                entry[column] = {
                    "baseline": base_mean,
                    "difference": diff,
                    "low": low,
                    "high": high,
                    "percent": 100.0 * diff / base_mean if base_mean else math.nan,
                }
            out.append(entry)
    out.sort(
        key=lambda e: (
            e["surface"],
            e["localizer"],
            e["controller"],
            np.nan_to_num(e["phantom_area_m2"]["difference"], nan=np.inf),
        )
    )
    return out


def _fmt(x: float, digits: int = 2) -> str:
    return "–" if not math.isfinite(x) else f"{x:+.{digits}f}"


def ranking_table(entries: Sequence[dict[str, Any]]) -> str:
    """The ranking as a markdown table: per metric 'difference [low, high] (±%)'."""
    headers = ["surface", "localizer", "controller", "mitigation", "users"] + [
        f"Δ {label} [{unit}]" for _, label, unit in METRICS
    ]
    body = []
    for e in entries:
        cells = [e["surface"], e["localizer"], e["controller"], e["mitigation"], e["users"]]
        for column, _, _ in METRICS:
            d = e[column]
            pct = "" if not math.isfinite(d["percent"]) else f" ({d['percent']:+.0f} %)"
            cells.append(f"{_fmt(d['difference'])} [{_fmt(d['low'])}, {_fmt(d['high'])}]{pct}")
        body.append(cells)
    return markdown(headers, body)


def cell_means_table(rows: Sequence[dict[str, Any]]) -> str:
    """Means per cell with their 95 % intervals."""
    keys = ("surface", "localizer", "mitigation", "controller")
    headers = [*keys, "users"] + [f"{label} [{unit}]" for _, label, unit in METRICS]
    body = []
    for key, group in _group(rows, keys).items():
        cells: list[Any] = [*key, len(group)]
        for column, _, _ in METRICS:
            m, low, high = mean_interval(_values(group, column))
            cells.append("–" if not math.isfinite(m) else f"{m:.2f} [{low:.2f}, {high:.2f}]")
        body.append(cells)
    return markdown(headers, body)


def figures(rows: Sequence[dict[str, Any]], fig_dir: Path) -> dict[str, Path]:
    """Per metric, its mean against the surface's slip coefficient with 95 % bands, a
    line per localizer × mitigation set × controller."""
    fig_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    lines = _group(rows, ("localizer", "mitigation", "controller"))
    for column, label, unit in METRICS:
        fig, ax = plt.subplots(figsize=(7.0, 4.5))
        for (loc, mitigation, ctl), group in lines.items():
            by_k = _group(group, ("slip_k",))
            ks = sorted(k for (k,) in by_k)
            stats = np.array([mean_interval(_values(by_k[(k,)], column)) for k in ks])
            if not np.isfinite(stats[:, 0]).any():
                continue
            (line,) = ax.plot(ks, stats[:, 0], marker="o", label=f"{loc} · {mitigation} · {ctl}")
            ax.fill_between(ks, stats[:, 1], stats[:, 2], color=line.get_color(), alpha=0.15)
        ax.set_xlabel("slip ratio at full brake force (surface)")
        ax.set_ylabel(f"{label} [{unit}]")
        ax.set_title(f"{label}: mean over users, 95 % bootstrap band")
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout()
        path = fig_dir / f"{column}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files[f"figure_{column}"] = path
    return files


def write_report(study, out: Path, rows, entries, files) -> Path:
    """report.md: the design, the ranking of the mitigations, the cell means, figures."""
    lines = [
        f"# Slip study: {study.course}",
        "",
        f"{study.trials} simulated users × surfaces {', '.join(study.surfaces)} × localizers "
        f"{', '.join(study.localizers)} × mitigations "
        f"{', '.join(set_name(c) for c in study.mitigations)} × controllers "
        f"{', '.join(study.controllers)}; at most {study.duration_s:g} s per trial; seeds "
        f"{study.seed}–{study.trial_seed(study.trials - 1)}.",
        "",
        "User i has seed SEED + i in every cell (paired design). Each run is the closed loop "
        "with the localizer and mitigations live, then its log replayed with the same for "
        "the drag metrics. Intervals: 95 % percentile bootstrap over users.",
        "",
        "## Ranking of the mitigations (paired difference against none; lower is better)",
        "",
        ranking_table(entries) if entries else "(no baseline 'none' in the study)",
        "",
        "## Means per cell",
        "",
        cell_means_table(rows),
        "",
        "## Figures (each metric against slip severity)",
        "",
    ]
    lines += [f"![{label}](figures/{column}.png)" for column, label, _ in METRICS]
    lines += ["", "Files: `results.db` (tables `runs`, `paths`), `results.csv`, `study.json`."]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
