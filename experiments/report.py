"""Figures of a replayed run: trajectory vs ground truth, errors over time, maps side by side."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from experiments.metrics import associate
from experiments.pipeline import Pipeline
from mapping.grid import GridExtent
from slam.trajectory import Trajectory


def _draw_map(ax, grid: GridExtent, outlines, title: str) -> None:
    tri = grid.trinary()
    img = np.where(tri == 1, 0.0, np.where(tri == 0, 1.0, 0.75))
    x0, x1, y0, y1 = grid.extent
    ax.imshow(
        img,
        cmap="gray",
        vmin=0,
        vmax=1,
        origin="lower",
        extent=(x0, x1, y0, y1),
        interpolation="nearest",
    )
    for poly in outlines:
        closed = np.vstack([poly, poly[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="tab:red", lw=0.6)
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def write_figures(
    out: Path, pipeline: Pipeline, est: Trajectory, gt: Trajectory | None, outlines
) -> dict[str, Path]:
    files: dict[str, Path] = {}
    fig, ax = plt.subplots(figsize=(7, 5))
    for poly in outlines:
        closed = np.vstack([poly, poly[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="0.6", lw=0.6)
    if gt is not None:
        ax.plot(gt.poses[:, 0], gt.poses[:, 1], "k-", lw=1.2, label="ground truth")
    ax.plot(est.poses[:, 0], est.poses[:, 1], "-", color="tab:blue", lw=1.0, label="estimate")
    for c in pipeline.recorded.collisions:
        ax.plot(c.x, c.y, "x", color="tab:red", ms=6)
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("trajectory (red x: collisions)", fontsize=9)
    files["trajectory_png"] = out / "trajectory.png"
    fig.savefig(files["trajectory_png"], dpi=130, bbox_inches="tight")
    plt.close(fig)

    if gt is not None and len(est) > 1:
        t, e, g = associate(est, gt)
        pos = np.hypot(e[:, 0] - g[:, 0], e[:, 1] - g[:, 1])
        head = np.degrees(np.abs(np.angle(np.exp(1j * (e[:, 2] - g[:, 2])))))
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
        a1.plot(t - t[0], pos, color="tab:blue")
        a1.set_ylabel("position error [m]")
        a2.plot(t - t[0], head, color="tab:orange")
        a2.set_ylabel("heading error [deg]")
        a2.set_xlabel("time [s]")
        for c in pipeline.recorded.commands:
            if c.left_nm > 0.1 or c.right_nm > 0.1:
                a1.axvline(c.t - t[0], color="tab:red", alpha=0.03, lw=2)
        a1.set_title("unaligned errors against ground truth (red: braking)", fontsize=9)
        files["errors_png"] = out / "errors.png"
        fig.savefig(files["errors_png"], dpi=130, bbox_inches="tight")
        plt.close(fig)

    if pipeline.reference is not None and gt is not None and pipeline.mapper.grid.known().any():
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.8))
        _draw_map(a1, pipeline.reference.grid, outlines, "map from ground-truth poses")
        _draw_map(a2, pipeline.mapper.grid, outlines, "map from the localizer's poses")
        a2.plot(est.poses[:, 0], est.poses[:, 1], color="tab:blue", lw=0.6)
        files["maps_png"] = out / "maps_side_by_side.png"
        fig.savefig(files["maps_png"], dpi=130, bbox_inches="tight")
        plt.close(fig)
    return files


def plot_slip_push(results, path: Path) -> Path:
    """True and dead-reckoned paths of the straight pushes, one panel per surface (Fig 6.1)."""
    surfaces = list(dict.fromkeys(str(r.surface) for r in results))
    fig, axes = plt.subplots(
        1, len(surfaces), figsize=(5 * len(surfaces), 4), squeeze=False, sharex=True, sharey=True
    )
    colours = {"none": "k", "left": "tab:blue", "right": "tab:red", "both": "tab:green"}
    for ax, surface in zip(axes[0], surfaces, strict=True):
        for r in results:
            if str(r.surface) != surface:
                continue
            ax.plot(r.truth.poses[:, 0], r.truth.poses[:, 1], color="tab:orange", lw=3, alpha=0.5)
            ax.plot(
                r.dead_reckoning.poses[:, 0],
                r.dead_reckoning.poses[:, 1],
                color=colours[r.brakes],
                label=f"{r.brakes} braked",
            )
        ax.set_title(f"{surface} floor (orange: true path)", fontsize=9)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m] (dead-reckoned sideways drift)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower left")
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)
    return path
