"""Path figures of the studies (matplotlib, PNG).

- `course_paths`: every user's true path of one cell over the course (obstacle
  footprints filled, the course route dashed), collisions marked by kind; user i has the
  same colour in every cell, so the paired users can be compared across figures.
- `course_overview`: the same for all cells on one page.
- `corner_sweep`: one sweep (thesis Figs 6.5–6.8): per setting the individual paths (thin)
  and their average (thick), with the walls.

Paths are the true rear-axle centre. Averages (`average_path`) are taken at equal arc
length from the start: each path is resampled every `ARC_STEP_M` and the average at
arc length s is the mean of the runs' positions at s, up to the shortest run's length
(so every point of the average is the mean of all runs). Time would mix users who push
at different speeds; x/y resampling fails where a path turns back.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hardware.sim.world import World

ARC_STEP_M = 0.02
KIND_STYLE = {
    "front": {"marker": "x", "color": "tab:red"},
    "side": {"marker": "^", "color": "tab:orange"},
    "rear-wheel": {"marker": "o", "color": "tab:purple"},
}


def resample_by_arclength(xy: np.ndarray, step: float = ARC_STEP_M) -> np.ndarray:
    """Points every `step` metres along the polyline `xy` (N×2), from its start."""
    xy = np.asarray(xy, float)
    if len(xy) < 2:
        return xy.copy()
    seg = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])
    s, xy = s[keep], xy[keep]
    if len(s) < 2:
        return xy[:1].copy()
    q = np.arange(0.0, s[-1] + 1e-12, step)
    return np.column_stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])])


def average_path(paths: Sequence[np.ndarray], step: float = ARC_STEP_M) -> np.ndarray:
    """Mean of `paths` (each N×2) at equal arc length, up to the shortest one's length."""
    res = [resample_by_arclength(p, step) for p in paths if len(p)]
    if not res:
        return np.zeros((0, 2))
    n = min(len(r) for r in res)
    return np.mean([r[:n] for r in res], axis=0)


def _draw_world(ax, world: World, route: bool = True) -> None:
    for _, poly in world.footprint_polygons():
        ax.fill(poly[:, 0], poly[:, 1], color="0.55", lw=0)
    if route:
        ax.plot(world.route[:, 0], world.route[:, 1], "--", color="0.75", lw=0.8, zorder=0)
    x0, x1, y0, y1 = world.bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)


def _user_colour(i: int):
    return plt.get_cmap("tab10")(i % 10)


def _draw_runs(ax, runs: Sequence[dict[str, Any]]) -> None:
    for r in runs:
        p = r["path"]
        if len(p):
            ax.plot(p[:, 1], p[:, 2], color=_user_colour(r["trial"]), lw=0.9, alpha=0.85)
        for _, kind, _, x, y in r["collisions"]:
            style = KIND_STYLE.get(kind, {"marker": "*", "color": "k"})
            ax.plot(x, y, ls="", ms=6, mew=1.4, mfc="none", **style)


def _legend(ax) -> None:
    handles = [
        plt.Line2D([], [], ls="", mfc="none", mew=1.4, label=k, **s) for k, s in KIND_STYLE.items()
    ]
    ax.legend(handles=handles, fontsize=7, loc="upper right", title="collisions", title_fontsize=7)


def course_paths(world: World, runs: Sequence[dict[str, Any]], title: str, path: Path) -> Path:
    """One cell: runs are dicts with `trial`, `path` (t, x, y, θ rows), `collisions`."""
    fig, ax = plt.subplots(figsize=(8, 6))
    _draw_world(ax, world)
    _draw_runs(ax, runs)
    _legend(ax)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def course_overview(
    world: World, cells: Sequence[tuple[str, Sequence[dict[str, Any]]]], path: Path
) -> Path:
    """All cells (title, runs) on one page, three per row."""
    n = len(cells)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.0 * rows), squeeze=False)
    for ax, (title, runs) in zip(axes.ravel(), cells, strict=False):
        _draw_world(ax, world)
        _draw_runs(ax, runs)
        ax.set_title(title, fontsize=8)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    _legend(axes.ravel()[0])
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def corner_sweep(
    world: World,
    settings: Sequence[tuple[str, Sequence[dict[str, Any]]]],
    title: str,
    path: Path,
) -> Path:
    """One sweep: settings are (label, runs); individual paths thin, averages thick."""
    fig, ax = plt.subplots(figsize=(6.5, 6))
    _draw_world(ax, world, route=False)
    cmap = plt.get_cmap("viridis")
    for k, (label, runs) in enumerate(settings):
        colour = cmap(k / max(len(settings) - 1, 1) * 0.9)
        xy = [r["path"][:, 1:3] for r in runs if len(r["path"])]
        for p in xy:
            ax.plot(p[:, 0], p[:, 1], color=colour, lw=0.6, alpha=0.35)
        for r in runs:
            for _, kind, _, x, y in r["collisions"]:
                style = KIND_STYLE.get(kind, {"marker": "*", "color": "k"})
                ax.plot(x, y, ls="", ms=5, mfc="none", marker=style["marker"], color=colour)
        avg = average_path(xy)
        if len(avg):
            ax.plot(avg[:, 0], avg[:, 1], color=colour, lw=2.2, label=label)
    pts = [r["path"][:, 1:3] for _, runs in settings for r in runs if len(r["path"])]
    if pts:
        allp = np.concatenate(pts)
        x0, x1, y0, y1 = world.bounds
        ax.set_xlim(max(x0, allp[:, 0].min() - 0.8), min(x1, allp[:, 0].max() + 0.8))
        ax.set_ylim(max(y0, allp[:, 1].min() - 0.8), min(y1, allp[:, 1].max() + 0.8))
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)
    return path
