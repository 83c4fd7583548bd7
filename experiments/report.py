"""Figures of a replayed run (the occupancy map, trajectory, errors over time, the maps side
by side), of a comparison (every localizer's path on one log) and of the slip push.

Each figure has a builder that returns a matplotlib `Figure` (for tests, notebooks and
other formats: `fig.savefig("map.pdf")`); the writers save them as PNG. The figures are
built on `matplotlib.figure.Figure`, not pyplot: nothing global changes (importing this
module does not switch a notebook's backend) and nothing needs closing.

The same conventions in every figure: metric axes (x [m], y [m], equal aspect); maps with
occupied cells black, free white, unknown grey, drawn from the raster the map files hold
(`mapping.export.map_raster`); true obstacle outlines, the true path and the estimated
path in the same colours (Okabe–Ito, distinguishable with the common colour-vision
deficiencies); legends outside the axes; titles naming the log and the localizer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from experiments.metrics import GROUND_TRUTH, GpsFit, TruthNames, associate
from experiments.pipeline import Pipeline
from experiments.sharpness import ScanSharpness
from hardware.messages import BrakeCommand, Collision
from mapping.export import MapRaster, map_raster
from mapping.grid import GridExtent
from slam.trajectory import Trajectory

DPI = 150
UNKNOWN_GREY = 0.75  # grey level of unknown cells (occupied 0, free 1)
OUTLINE_COLOUR = "#D55E00"  # true obstacle outlines (vermillion)
OUTLINE_COLOUR_PLAIN = "0.55"  # the same without a map underneath
TRUTH_COLOUR = "#009E73"  # the true path (bluish green)
ESTIMATE_COLOUR = "#0072B2"  # the estimated path (blue)
COLLISION_COLOUR = "#CC0000"
# compare: one colour per localizer (the true path keeps TRUTH_COLOUR)
LOCALIZER_COLOURS = ("#0072B2", "#E69F00", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442", "0.2")
PAD_M = 0.3  # margin around what a map figure shows
# errors.png shades the ticks whose command brakes above this [N·m]
BRAKING_SHADE_NM = 0.1


def log_name(log: str | Path) -> str:
    """How figure titles name a log: a file by its name (no folders), a dataset as given."""
    p = Path(str(log))
    return p.name if p.suffix else str(log)


def save(fig: Figure, path: str | Path) -> Path:
    """Write a figure as PNG (everything drawn outside the axes included)."""
    path = Path(path)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    return path


# -- drawing pieces -------------------------------------------------------------------


def draw_map(ax: Axes, raster: MapRaster) -> None:
    """The trinary map in world metres; the axes' background is unknown too."""
    tri = raster.trinary
    img = np.where(tri == 1, 0.0, np.where(tri == 0, 1.0, UNKNOWN_GREY))
    ax.set_facecolor(str(UNKNOWN_GREY))
    ax.imshow(
        img,
        cmap="gray",
        vmin=0.0,
        vmax=1.0,
        origin="lower",
        extent=raster.extent,
        interpolation="none",
    )


def draw_outlines(ax: Axes, outlines: Sequence[np.ndarray], colour: str = OUTLINE_COLOUR) -> None:
    for poly in outlines:
        closed = np.vstack([poly, poly[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color=colour, lw=0.7)


def draw_path(ax: Axes, xy: np.ndarray, colour: str, lw: float = 1.0) -> None:
    ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, lw=lw)


def metric_axes(ax: Axes) -> None:
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def map_legend_handles() -> list:
    """Legend entries of a map's cells."""
    edge = {"edgecolor": "0.3", "linewidth": 0.5}
    return [
        Patch(facecolor="black", label="occupied", **edge),
        Patch(facecolor="white", label="free", **edge),
        Patch(facecolor=str(UNKNOWN_GREY), label="unknown", **edge),
    ]


def line_handle(colour: str, label: str, lw: float = 1.2) -> Line2D:
    return Line2D([], [], color=colour, lw=lw, label=label)


def outline_handle(colour: str = OUTLINE_COLOUR) -> Line2D:
    return line_handle(colour, "true obstacle outlines", lw=0.9)


def legend_right(ax: Axes, handles: list) -> None:
    """The legend to the right of the axes, its top level with theirs (it covers nothing)."""
    ax.legend(
        handles=handles,
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        borderaxespad=0.0,
        fontsize=8,
        frameon=False,
    )


def bounds(
    rasters: Sequence[MapRaster] = (),
    paths: Sequence[np.ndarray | None] = (),
    outlines: Sequence[np.ndarray] = (),
    pad: float = PAD_M,
) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) holding the paths, the outlines and the bulk of each
    raster (`bulk_extent`), padded."""
    lo, hi = [], []
    for r in rasters:
        x0, x1, y0, y1 = bulk_extent(r)
        lo.append((x0, y0))
        hi.append((x1, y1))
    for xy in [p for p in paths if p is not None and len(p)] + list(outlines):
        xy = np.asarray(xy, float)[:, :2]
        lo.append(xy.min(axis=0))
        hi.append(xy.max(axis=0))
    if not lo:
        return -1.0, 1.0, -1.0, 1.0
    (x0, y0), (x1, y1) = np.min(lo, axis=0), np.max(hi, axis=0)
    return x0 - pad, x1 + pad, y0 - pad, y1 + pad


# a map's view is set by its occupied cells with at least STRUCTURE_CELLS occupied cells
# (themselves included) in the 5×5 cells around them: walls and furniture, not a laser's
# stray long-range returns (seattle has a few hundred single cells up to 130 m from a
# 50 m building, which would shrink the map to a patch in the middle)
STRUCTURE_CELLS = 4


def bulk_extent(raster: MapRaster) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) of the raster's structure (above), or of all its known
    cells when it has none."""
    occupied = (raster.trinary == 1).astype(np.float32)
    near = cv2.boxFilter(occupied, -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
    rows, cols = np.nonzero((occupied > 0) & (near >= STRUCTURE_CELLS - 0.5))
    if not len(rows):
        return raster.extent
    (x0, y0), res = raster.origin, raster.resolution
    return (
        x0 + cols.min() * res,
        x0 + (cols.max() + 1) * res,
        y0 + rows.min() * res,
        y0 + (rows.max() + 1) * res,
    )


def outside_note(raster: MapRaster, box: tuple[float, float, float, float]) -> str:
    """', N occupied cells outside the view' for the cells `box` leaves out, else ''."""
    rows, cols = np.nonzero(raster.trinary == 1)
    x = raster.origin[0] + (cols + 0.5) * raster.resolution
    y = raster.origin[1] + (rows + 0.5) * raster.resolution
    n = int(np.count_nonzero((x < box[0]) | (x > box[1]) | (y < box[2]) | (y > box[3])))
    return f", {n} occupied cells outside the view" if n else ""


def _figsize(
    box: tuple[float, float, float, float], axes_width: float, legend_width: float = 2.4
) -> tuple[float, float]:
    """Inches of a figure whose axes, `axes_width` wide, keep the aspect of box (within
    reason), with room for labels, title and a legend on the right."""
    x0, x1, y0, y1 = box
    ratio = float(np.clip((y1 - y0) / max(x1 - x0, 1e-9), 0.4, 1.5))
    return axes_width + legend_width, axes_width * ratio + 1.0


# -- figures of a replay --------------------------------------------------------------


def map_figure(
    grid: GridExtent,
    outlines: Sequence[np.ndarray] = (),
    estimated: np.ndarray | None = None,
    truth: np.ndarray | None = None,
    *,
    localizer: str,
    log: str | Path,
    names: TruthNames = GROUND_TRUTH,
) -> Figure:
    """map.png: the localizer's map (the cells of map.pgm) with the true obstacle
    outlines, the estimated path (N×2) and, when known, the true path."""
    raster = map_raster(grid)
    box = bounds([raster], [estimated, truth], outlines)
    fig = Figure(figsize=_figsize(box, 6.0), layout="constrained")
    ax = fig.add_subplot()
    draw_map(ax, raster)
    handles = map_legend_handles()
    if outlines:
        draw_outlines(ax, outlines)
        handles.append(outline_handle())
    if truth is not None:
        draw_path(ax, truth, TRUTH_COLOUR, lw=1.1)
        handles.append(line_handle(TRUTH_COLOUR, names.path))
    if estimated is not None:
        draw_path(ax, estimated, ESTIMATE_COLOUR)
        handles.append(line_handle(ESTIMATE_COLOUR, f"estimated path ({localizer})"))
    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[2], box[3])
    metric_axes(ax)
    ax.set_title(
        f"{log_name(log)}: occupancy map from the {localizer} poses "
        f"({raster.resolution * 100:g} cm cells{outside_note(raster, box)})",
        fontsize=9,
    )
    legend_right(ax, handles)
    return fig


def maps_figure(
    reference: GridExtent,
    estimated_map: GridExtent,
    outlines: Sequence[np.ndarray],
    estimated: np.ndarray,
    truth: np.ndarray,
    *,
    localizer: str,
    log: str | Path,
    names: TruthNames = GROUND_TRUTH,
) -> Figure:
    """maps_side_by_side.png: the map from the true poses (with the true path) next to
    the map from the localizer's (with the estimated and the true path), on the same
    extent, true obstacle outlines on both, one legend below."""
    rasters = [map_raster(reference), map_raster(estimated_map)]
    box = bounds(rasters, [estimated, truth], outlines)
    w, h = _figsize(box, 5.6, legend_width=0.0)
    fig = Figure(figsize=(2 * w + 0.8, h + 0.2), layout="constrained")
    left, right = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, raster in zip((left, right), rasters, strict=True):
        draw_map(ax, raster)
        draw_outlines(ax, outlines)
        draw_path(ax, truth, TRUTH_COLOUR, lw=1.1)
        metric_axes(ax)
    draw_path(right, estimated, ESTIMATE_COLOUR)
    left.set_xlim(box[0], box[1])
    left.set_ylim(box[2], box[3])
    left.set_title(f"map from {names.poses}{outside_note(rasters[0], box)}", fontsize=9)
    right.set_title(f"map from the {localizer} poses{outside_note(rasters[1], box)}", fontsize=9)
    fig.suptitle(f"{log_name(log)}: the same frames mapped at two sets of poses", fontsize=10)
    handles = [
        *map_legend_handles(),
        *([outline_handle()] if outlines else []),
        line_handle(TRUTH_COLOUR, names.path),
        line_handle(ESTIMATE_COLOUR, f"estimated path ({localizer})"),
    ]
    fig.legend(
        handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False
    )
    return fig


def sharpness_figure(sharp: ScanSharpness, *, localizer: str, log: str | Path) -> Figure:
    """sharpness.png: a laser replay's scan hits at the localizer's poses (and at the
    reference's, side by side), each coloured by the spread across the wall around it
    at the coarsest scale (50 cm; experiments.sharpness): walls seen twice a few
    decimetres apart show up warm, where a loop was not closed or a scan was misplaced."""
    cfg = sharp.scales[-1]
    panels = [f"{localizer} poses"]
    spreads = [sharp.estimated[-1]]
    if sharp.reference is not None:
        panels.append("reference poses")
        spreads.append(sharp.reference[-1])
    xy = np.concatenate([sp.xy for sp in spreads] + [np.zeros((0, 2))])
    box = (
        tuple(np.r_[xy.min(axis=0) - 1.0, xy.max(axis=0) + 1.0][[0, 2, 1, 3]])
        if len(xy)
        else (0.0, 1.0, 0.0, 1.0)
    )
    ratio = (box[3] - box[2]) / max(box[1] - box[0], 1e-9)
    w = 5.6 if ratio <= 1.3 else max(7.5 / ratio, 2.5)  # a tall map: narrower panels
    fig = Figure(
        figsize=(len(panels) * (w + 0.8) + 1.2, min(w * ratio, 9.0) + 1.2), layout="constrained"
    )
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharex=True, sharey=True))
    vmax = 0.15
    art = None
    for ax, name, sp in zip(axes, panels, spreads, strict=True):
        order = np.argsort(sp.spread_m)  # the widest on top
        art = ax.scatter(
            *sp.xy[order].T, c=sp.spread_m[order], s=0.4, cmap="viridis", vmin=0.0,
            vmax=vmax, rasterized=True, linewidths=0,
        )  # fmt: skip
        median = float(np.median(sp.spread_m)) if len(sp.spread_m) else float("nan")
        ax.set_title(f"hits at the {name}: median spread {100 * median:.1f} cm", fontsize=9)
        ax.set_facecolor("#f4f4f4")
        metric_axes(ax)
    axes[0].set_xlim(box[0], box[1])
    axes[0].set_ylim(box[2], box[3])
    if art is not None:
        bar = fig.colorbar(art, ax=list(axes), shrink=0.8, extend="max")
        bar.set_label(f"spread across the wall within {cfg.radius_m:g} m [m]", fontsize=8)
    fig.suptitle(
        f"{log_name(log)}: the same scans at two sets of poses (thinner walls: more"
        " consistent poses)",
        fontsize=10,
    )
    return fig


def trajectory_figure(
    est: Trajectory,
    gt: Trajectory | None,
    outlines: Sequence[np.ndarray],
    collisions: Sequence[Collision] = (),
    *,
    localizer: str,
    log: str | Path,
    names: TruthNames = GROUND_TRUTH,
) -> Figure:
    """trajectory.png: the estimated path against the true one among the true obstacle
    outlines, with the simulated collisions."""
    truth = gt.poses[:, :2] if gt is not None else None
    fig, ax, handles, box = _path_axes([est.poses[:, :2]], truth, outlines, (1.3, None), names)
    draw_path(ax, est.poses[:, :2], ESTIMATE_COLOUR)
    handles.append(line_handle(ESTIMATE_COLOUR, f"estimated path ({localizer})"))
    if collisions:
        ax.plot([c.x for c in collisions], [c.y for c in collisions], "x", color=COLLISION_COLOUR)
        handles.append(
            Line2D(
                [],
                [],
                marker="x",
                ls="none",
                color=COLLISION_COLOUR,
                label=f"collisions ({len(collisions)})",
            )
        )
    against = f" against the {names.path}" if truth is not None else ""
    title = f"{log_name(log)}: {localizer} path{against}"
    return _finish_path_axes(fig, ax, handles, box, title)


def gps_figure(
    est: Trajectory,
    fit: GpsFit,
    errors: Mapping[str, float],
    landmarks: np.ndarray,
    *,
    localizer: str,
    log: str | Path,
) -> Figure:
    """gps.png: the estimated path and its landmark map, aligned (SE(2)) onto the GPS
    fixes the metric keeps (`fit`, experiments.metrics.fit_gps; `errors` its
    gps_errors), over those fixes and the jumps it left out."""
    inside, screen, kept = fit.fixes, fit.screen, fit.kept
    path = est.poses[:, :2]
    if fit.alignment is not None:
        r, t = fit.alignment
        path = path @ r.T + t
        landmarks = np.asarray(landmarks, dtype=float).reshape(-1, 2) @ r.T + t
    fig, ax, handles, box = _path_axes([path, inside[:, 1:]], None, [], (1.0, None))
    ax.plot(*kept[:, 1:].T, ".", ms=1.5, color=TRUTH_COLOUR)
    handles.append(
        Line2D([], [], marker=".", ls="none", color=TRUTH_COLOUR, label=f"GPS ({len(kept)} fixes)")
    )
    jumps = inside[~screen.kept]
    if len(jumps):
        ax.plot(*jumps[:, 1:].T, "x", ms=4, color=COLLISION_COLOUR)
        handles.append(
            Line2D(
                [], [], marker="x", ls="none", color=COLLISION_COLOUR,
                label=f"GPS jumps left out ({len(jumps)})",
            )
        )  # fmt: skip
    draw_path(ax, path, ESTIMATE_COLOUR)
    handles.append(line_handle(ESTIMATE_COLOUR, f"estimated path ({localizer}), aligned"))
    if len(landmarks):
        ax.plot(*landmarks.T, "o", ms=2, mfc="none", color="black", mew=0.6)
        handles.append(
            Line2D(
                [], [], marker="o", ls="none", mfc="none", color="black",
                label=f"its landmarks ({len(landmarks)})",
            )
        )  # fmt: skip
    title = (
        f"{log_name(log)}: {localizer} against the GPS — RMSE {errors['gps_rmse_m']:.2f} m "
        f"aligned, {errors['gps_rmse_unaligned_m']:.2f} m not; {screen.dropouts} dropouts "
        f"({screen.dropout_s:.0f} s)"
    )
    return _finish_path_axes(fig, ax, handles, box, title)


def _path_axes(
    paths: Sequence[np.ndarray],
    truth: np.ndarray | None,
    outlines: Sequence[np.ndarray],
    truth_lw: tuple[float, float | None],
    names: TruthNames = GROUND_TRUTH,
) -> tuple[Figure, Axes, list, tuple[float, float, float, float]]:
    """A path figure's axes sized to the paths, the truth and the outlines, with the
    outlines and the true path (line width, legend line width) drawn: (fig, ax, legend
    handles, extent)."""
    box = bounds([], [*paths, truth], outlines)
    fig = Figure(figsize=_figsize(box, 5.5), layout="constrained")
    ax = fig.add_subplot()
    handles = []
    if outlines:
        draw_outlines(ax, outlines, OUTLINE_COLOUR_PLAIN)
        handles.append(outline_handle(OUTLINE_COLOUR_PLAIN))
    if truth is not None:
        draw_path(ax, truth, TRUTH_COLOUR, lw=truth_lw[0])
        legend_lw = {} if truth_lw[1] is None else {"lw": truth_lw[1]}
        handles.append(line_handle(TRUTH_COLOUR, names.path, **legend_lw))
    return fig, ax, handles, box


def _finish_path_axes(fig: Figure, ax: Axes, handles: list, box, title: str) -> Figure:
    """The extent, metric axes, the title and the legend right of the axes."""
    ax.set_xlim(box[0], box[1])
    ax.set_ylim(box[2], box[3])
    metric_axes(ax)
    ax.set_title(title, fontsize=9)
    legend_right(ax, handles)
    return fig


def errors_figure(
    est: Trajectory,
    gt: Trajectory,
    commands: Sequence[BrakeCommand],
    *,
    localizer: str,
    log: str | Path,
    names: TruthNames = GROUND_TRUTH,
) -> Figure:
    """errors.png: unaligned position and heading error over time, braking shaded."""
    t, e, g = associate(est, gt)
    pos = np.hypot(e[:, 0] - g[:, 0], e[:, 1] - g[:, 1])
    head = np.degrees(np.abs(np.angle(np.exp(1j * (e[:, 2] - g[:, 2])))))
    fig = Figure(figsize=(7, 4.5))
    a1, a2 = fig.subplots(2, 1, sharex=True)
    a1.plot(t - t[0], pos, color="tab:blue")
    a1.set_ylabel("position error [m]")
    a2.plot(t - t[0], head, color="tab:orange")
    a2.set_ylabel("heading error [deg]")
    a2.set_xlabel("time [s]")
    for c in commands:
        if c.left_nm > BRAKING_SHADE_NM or c.right_nm > BRAKING_SHADE_NM:
            a1.axvline(c.t - t[0], color="tab:red", alpha=0.03, lw=2)
    a1.set_title(
        f"{log_name(log)}: {localizer}, unaligned errors against {names.against} (red: braking)",
        fontsize=9,
    )
    return fig


def write_map_png(
    path: str | Path,
    grid: GridExtent,
    outlines: Sequence[np.ndarray],
    est: Trajectory,
    gt: Trajectory | None,
    *,
    localizer: str,
    log: str | Path,
    names: TruthNames = GROUND_TRUTH,
) -> Path:
    """A replay's map.png (`map_figure`)."""
    truth = gt.poses[:, :2] if gt is not None else None
    fig = map_figure(
        grid, outlines, est.poses[:, :2], truth, localizer=localizer, log=log, names=names
    )
    return save(fig, path)


def write_figures(
    out: Path,
    pipeline: Pipeline,
    est: Trajectory,
    gt: Trajectory | None,
    outlines,
    *,
    localizer: str,
    log: str | Path,
    sharpness: ScanSharpness | None = None,
    names: TruthNames = GROUND_TRUTH,
) -> dict[str, Path]:
    """trajectory.png; with ground truth errors.png, and with the reference map too
    maps_side_by_side.png; with a laser replay's `sharpness` sharpness.png."""
    named = {"localizer": localizer, "log": log}
    rec = pipeline.recorded
    files = {
        "trajectory_png": save(
            trajectory_figure(est, gt, outlines, rec.collisions, **named, names=names),
            out / "trajectory.png",
        )
    }
    if gt is not None and len(est) > 1:
        files["errors_png"] = save(
            errors_figure(est, gt, rec.commands, **named, names=names), out / "errors.png"
        )
    if pipeline.reference is not None and gt is not None and pipeline.mapper.grid.known().any():
        fig = maps_figure(
            pipeline.reference.grid,
            pipeline.mapper.grid,
            outlines,
            est.poses[:, :2],
            gt.poses[:, :2],
            **named,
            names=names,
        )
        files["maps_png"] = save(fig, out / "maps_side_by_side.png")
    if sharpness is not None:
        files["sharpness_png"] = save(sharpness_figure(sharpness, **named), out / "sharpness.png")
    return files


# -- a comparison ---------------------------------------------------------------------


def paths_figure(
    name: str,
    paths: Mapping[str, np.ndarray],
    truth: np.ndarray | None = None,
    outlines: Sequence[np.ndarray] = (),
    names: TruthNames = GROUND_TRUTH,
) -> Figure:
    """compare's `<log>_trajectories.png`: each localizer's path (N×2, keyed by its name)
    on one log, the true path and the true obstacle outlines when known."""
    fig, ax, handles, box = _path_axes(list(paths.values()), truth, outlines, (1.5, 1.5), names)
    for k, (label, xy) in enumerate(paths.items()):
        colour = LOCALIZER_COLOURS[k % len(LOCALIZER_COLOURS)]
        draw_path(ax, xy, colour, lw=0.9)
        handles.append(line_handle(colour, label))
    against = f" against the {names.path}" if truth is not None else ""
    return _finish_path_axes(fig, ax, handles, box, f"{name}: estimated paths{against}")


# -- the slip push --------------------------------------------------------------------


def plot_slip_push(results, path: Path) -> Path:
    """True and dead-reckoned paths of the straight pushes, one panel per surface (Fig 6.1)."""
    surfaces = list(dict.fromkeys(str(r.surface) for r in results))
    fig = Figure(figsize=(5 * len(surfaces), 4))
    axes = fig.subplots(1, len(surfaces), squeeze=False, sharex=True, sharey=True)
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
    return path
