"""Statistics and tables of the studies: thesis Table 6.3 and the corner sweeps.

Change against the baseline (`percent_change`): the point estimate is
100 · (Σ treated / Σ baseline − 1) over the same users, i.e. the change of the mean
collisions per trial. Its 95 % confidence interval is a *paired percentile bootstrap over
users*: users (trial indices) are resampled with replacement, each resample keeps every
chosen user's treated and baseline counts together (the pairing), the ratio is
recomputed, and the 2.5th and 97.5th percentiles of `N_BOOT` resamples are the interval.
Resamples whose baseline total is 0 have no ratio and are left out (`Change.resamples`
counts those kept); with no baseline collisions at all the change is undefined ("n/a"),
and a single user gives no interval. The bootstrap generator is seeded, so the interval
is reproducible. With few users the interval is crude (with 3 users there are only 10
distinct resamples); it says how little a small study shows rather than hiding it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

N_BOOT = 10_000
BOOT_SEED = 20_260_101
KINDS = ("front", "side", "rear_wheel")


@dataclass(frozen=True)
class Change:
    """Percent change of the mean against a baseline with its confidence interval."""

    percent: float
    low: float
    high: float
    resamples: int  # bootstrap resamples with a defined ratio

    def text(self) -> str:
        if math.isnan(self.percent):
            return "n/a"
        if math.isnan(self.low):
            return f"{self.percent:+.0f}% [no CI: 1 user]"
        return f"{self.percent:+.0f}% [{self.low:+.0f}, {self.high:+.0f}]"


def percent_change(
    treated: Sequence[float],
    baseline: Sequence[float],
    *,
    n_boot: int = N_BOOT,
    level: float = 0.95,
    seed: int = BOOT_SEED,
) -> Change:
    """100·(Σ treated / Σ baseline − 1) with a paired percentile-bootstrap interval;
    `treated[i]` and `baseline[i]` are the same user (module docstring)."""
    t = np.asarray(treated, dtype=float)
    b = np.asarray(baseline, dtype=float)
    if t.shape != b.shape or t.ndim != 1 or len(t) == 0:
        raise ValueError(f"need two equally long, non-empty series, got {t.shape} and {b.shape}")
    if b.sum() <= 0:
        return Change(math.nan, math.nan, math.nan, 0)
    point = 100.0 * (t.sum() / b.sum() - 1.0)
    if len(t) < 2:
        return Change(float(point), math.nan, math.nan, 0)
    idx = np.random.default_rng(seed).integers(0, len(t), size=(n_boot, len(t)))
    bt, bb = t[idx].sum(axis=1), b[idx].sum(axis=1)
    ok = bb > 0
    ratios = 100.0 * (bt[ok] / bb[ok] - 1.0)
    alpha = 100.0 * (1.0 - level) / 2.0
    low, high = np.percentile(ratios, [alpha, 100.0 - alpha])
    return Change(float(point), float(low), float(high), int(ok.sum()))


def collision_table(
    rows: Iterable[dict[str, Any]],
    baseline: str = "none",
    groups: Sequence[str] = ("localizer", "surface"),
) -> list[dict[str, Any]]:
    """Thesis Table 6.3 per group (localizer, surface) and controller.

    rows: one per run with `controller`, the group keys, `trial` and
    `collisions_front|side|rear_wheel|total`. Returns one dict per (group, controller)
    with `trials`, mean per trial (`front`, `side`, `rear_wheel`, `total`), the sums
    (`sum_front`, ...), `finished` (share of runs that completed the route) and `change`
    (a `Change` of the total against `baseline` over the same trials; None for the
    baseline itself or when the group has no baseline runs).
    """
    rows = list(rows)
    cells: dict[tuple, dict[str, dict[int, dict[str, Any]]]] = {}
    order: list[str] = []
    for r in rows:
        key = tuple(r[g] for g in groups)
        cells.setdefault(key, {}).setdefault(r["controller"], {})[int(r["trial"])] = r
        if r["controller"] not in order:
            order.append(r["controller"])
    out = []
    for key, by_ctl in cells.items():
        base = by_ctl.get(baseline)
        for ctl in [c for c in order if c in by_ctl]:
            runs = by_ctl[ctl]
            trials = sorted(runs)
            entry: dict[str, Any] = dict(zip(groups, key, strict=True))
            entry.update(controller=ctl, trials=len(trials))
            for k in (*KINDS, "total"):
                vals = np.array([runs[i][f"collisions_{k}"] for i in trials], dtype=float)
                entry[k] = float(vals.mean())
                entry[f"sum_{k}"] = int(vals.sum())
            finished = [bool(runs[i].get("finished_route")) for i in trials]
            entry["finished"] = float(np.mean(finished))
            entry["change"] = None
            if base is not None and ctl != baseline:
                common = [i for i in trials if i in base]
                if common:
                    entry["change"] = percent_change(
                        [runs[i]["collisions_total"] for i in common],
                        [base[i]["collisions_total"] for i in common],
                    )
            out.append(entry)
    return out


def mean_of(rows: Iterable[dict[str, Any]], key: str) -> float:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else math.nan


def markdown(headers: Sequence[str], body: Iterable[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def collision_rows(table: Sequence[dict[str, Any]], baseline: str = "none") -> list[list[str]]:
    """Table 6.3 as text cells: group, controller, trials, mean per trial
    (front / side / rear-wheel / total), totals, change vs baseline, route completed."""
    body = []
    for e in table:
        change = e["change"]
        body.append(
            [
                e.get("localizer", ""),
                str(e.get("surface", "")),
                e["controller"],
                str(e["trials"]),
                f"{e['front']:.2f}",
                f"{e['side']:.2f}",
                f"{e['rear_wheel']:.2f}",
                f"{e['total']:.2f}",
                f"{e['sum_front']} / {e['sum_side']} / {e['sum_rear_wheel']}",
                ("baseline" if e["controller"] == baseline else "—")
                if change is None
                else change.text(),
                f"{100 * e['finished']:.0f} %",
            ]
        )
    return body


def collision_headers(baseline: str = "none") -> tuple[str, ...]:
    return (
        "localizer",
        "surface",
        "controller",
        "trials",
        "front / trial",
        "side / trial",
        "rear-wheel / trial",
        "total / trial",
        "totals F / S / R",
        f"total vs {baseline} [95 % CI]",
        "route completed",
    )
