"""Figures of the drag metrics (`experiments.drag`, which computes them without matplotlib):
`drag.png`, phantom area, obstacle drag and steering over a trial, and
`controller_replay.png`, the logged against the recomputed brake commands.

Each has a builder returning a matplotlib `Figure` and a writer saving it as PNG; the
figures are built on `matplotlib.figure.Figure`, not pyplot (no global state, nothing to
close).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from experiments.drag import CommandRecomputer, DragConfig, PhantomSeries, brake_yaw_rate
from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand

DPI = 130

# (times, commands under test, required commands): the over-steer series of drag.png
SteerSeries = tuple[np.ndarray, np.ndarray, np.ndarray]


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    return path


def _shade_braking(ax: Axes, t: np.ndarray, engaged: np.ndarray, t0: float) -> None:
    edges = np.diff(np.concatenate([[0], engaged.astype(int), [0]]))
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        ax.axvspan(t[a] - t0, t[min(b, len(t) - 1)] - t0, color="tab:red", alpha=0.12, lw=0)


def _phantom_panel(ax: Axes, phantom: PhantomSeries, t0: float) -> None:
    t = np.array(phantom.t) - t0
    ax.plot(t, phantom.phantom, color="tab:blue", label="estimated map")
    if np.isfinite(phantom.reference).any():
        ax.plot(t, phantom.reference, color="k", lw=0.8, label="map at true poses")
    ax.set_ylabel("phantom area [m²]")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("drag over the trial (red: a brake engaged)", fontsize=9)


def _frames_panel(ax: Axes, frames: dict[str, np.ndarray], config: DragConfig, t0: float) -> None:
    tt = frames["t"] - t0
    ax.plot(tt, frames["mean_m"], color="tab:blue", lw=0.8, label="absolute")
    ax.plot(
        tt,
        frames["local_mean_m"],
        color="tab:orange",
        lw=0.8,
        label=f"added in {config.local_window_s:g} s",
    )
    bt = frames["braked_turn"]
    ax.plot(tt[bt], frames["local_mean_m"][bt], ".", color="tab:red", ms=3, label="braked turn")
    ax.set_ylabel("obstacle drag [m]")
    ax.legend(fontsize=8, loc="upper left")


def _steer_panel(
    ax: Axes,
    steer: SteerSeries,
    calibration: WalkerCalibration,
    config: DragConfig,
    t0: float,
) -> None:
    st, tested, ref = steer
    u_t = np.degrees(brake_yaw_rate(tested[:, 0], tested[:, 1], calibration, config))
    u_r = np.degrees(brake_yaw_rate(ref[:, 0], ref[:, 1], calibration, config))
    ax.step(st - t0, u_t, where="post", color="tab:blue", lw=0.8, label="commanded")
    ax.step(st - t0, u_r, where="post", color="k", lw=0.8, label="required (true pose, map)")
    ax.set_ylabel("brake yaw rate [°/s]")
    ax.legend(fontsize=8, loc="upper left")


def drag_figure(
    phantom: PhantomSeries | None,
    frames: dict[str, np.ndarray],
    steer: SteerSeries | None,
    commands: Sequence[BrakeCommand],
    calibration: WalkerCalibration,
    config: DragConfig,
) -> Figure:
    """One panel per series present, over time from the first sample or command: phantom
    area of the estimated and the reference map, per-frame drag (absolute, added within
    the local window, braked turns marked), steering commanded vs required; the ticks
    with a brake engaged shaded."""
    panels = [
        name
        for name, present in (
            ("phantom", phantom is not None),
            ("frames", bool(frames)),
            ("steer", steer is not None),
        )
        if present
    ]
    fig = Figure(figsize=(8, 2.4 * len(panels)))
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    ct = np.array([c.t for c in commands])
    level = np.array([max(c.left_nm, c.right_nm) for c in commands])
    engaged = level - calibration.brake.torque_off_nm > config.brake_threshold_nm
    starts = []
    if phantom is not None and phantom.t:
        starts.append(phantom.t[0])
    if frames:
        starts.append(float(frames["t"][0]))
    if len(ct):
        starts.append(float(ct[0]))
    t0 = min(starts, default=0.0)
    for ax, panel in zip(axes, panels, strict=True):
        if len(ct):
            _shade_braking(ax, ct, engaged, t0)
        if panel == "phantom":
            _phantom_panel(ax, phantom, t0)
        elif panel == "frames":
            _frames_panel(ax, frames, config, t0)
        else:
            _steer_panel(ax, steer, calibration, config, t0)
    axes[-1].set_xlabel("time [s]")
    return fig


def plot_drag(
    path: Path,
    phantom: PhantomSeries | None,
    frames: dict[str, np.ndarray],
    steer: SteerSeries | None,
    commands: Sequence[BrakeCommand],
    calibration: WalkerCalibration,
    config: DragConfig,
) -> Path:
    """drag.png (`drag_figure`)."""
    return _save(drag_figure(phantom, frames, steer, commands, calibration, config), path)


def controller_replay_figure(recomputer: CommandRecomputer) -> Figure:
    """Logged vs recomputed brake torque per wheel."""
    t, logged, recomputed = recomputer.arrays()
    t0 = t[0] if len(t) else 0.0
    fig = Figure(figsize=(8, 4.2))
    axes = fig.subplots(2, 1, sharex=True)
    for k, (ax, wheel) in enumerate(zip(axes, ("left", "right"), strict=True)):
        ax.step(t - t0, logged[:, k], where="post", color="k", lw=1.4, alpha=0.6, label="logged")
        ax.step(
            t - t0,
            recomputed[:, k],
            where="post",
            color="tab:orange",
            lw=0.8,
            label=f"recomputed ({recomputer.name})",
        )
        ax.set_ylabel(f"{wheel} torque [N·m]")
        ax.legend(fontsize=8, loc="upper left")
    axes[0].set_title("brake commands: logged vs recomputed on the replay", fontsize=9)
    axes[-1].set_xlabel("time [s]")
    return fig


def plot_controller_replay(path: Path, recomputer: CommandRecomputer) -> Path:
    """controller_replay.png (`controller_replay_figure`)."""
    return _save(controller_replay_figure(recomputer), path)
