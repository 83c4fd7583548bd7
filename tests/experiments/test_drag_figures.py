"""The drag figures (experiments.drag_figures) on known series, and the split: the drag
metrics module holds no plotting code and loads none."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import experiments.drag
from experiments.drag import DragConfig, brake_yaw_rate
from experiments.drag_figures import controller_replay_figure, drag_figure, plot_drag
from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand

CAL = WalkerCalibration()
OFF = CAL.brake.torque_off_nm
CFG = DragConfig()


def legend_texts(ax) -> list[str]:
    return [t.get_text() for t in ax.get_legend().get_texts()]


def series():
    """10 s at 10 Hz from t = 100 s: a left brake 2–4 s and a right one 6–7 s."""
    t = 100.0 + np.arange(0.0, 10.0, 0.1)
    left = np.where((t >= 102) & (t < 104), 1.5, OFF)
    right = np.where((t >= 106) & (t < 107), 2.0, OFF)
    commands = [
        BrakeCommand(float(a), float(b), float(c)) for a, b, c in zip(t, left, right, strict=True)
    ]
    phantom = SimpleNamespace(
        t=list(t[::10]), phantom=list(np.linspace(0, 2, 10)), reference=[0.0] * 10
    )
    frames = {
        "t": t,
        "mean_m": np.linspace(0, 1, len(t)),
        "local_mean_m": np.full(len(t), 0.05),
        "braked_turn": (t >= 102) & (t < 104),
    }
    tested = np.column_stack([left, right])
    steer = (t, tested, np.column_stack([left * 0.5, right]))
    return commands, phantom, frames, steer


def test_drag_figure_has_one_panel_per_series_with_units_and_legends():
    commands, phantom, frames, steer = series()
    fig = drag_figure(phantom, frames, steer, commands, CAL, CFG)
    top, middle, bottom = fig.axes
    assert top.get_ylabel() == "phantom area [m²]"
    assert middle.get_ylabel() == "obstacle drag [m]"
    assert bottom.get_ylabel() == "brake yaw rate [°/s]"
    assert bottom.get_xlabel() == "time [s]"
    assert legend_texts(top) == ["estimated map", "map at true poses"]
    assert legend_texts(middle) == ["absolute", "added in 1 s", "braked turn"]
    assert legend_texts(bottom) == ["commanded", "required (true pose, map)"]
    # time from the first sample; the two braking spans shaded on every panel
    spans = [p.get_x() for p in top.patches]
    assert spans == pytest.approx([2.0, 6.0])
    assert len(middle.patches) == len(bottom.patches) == 2
    t, tested, _ = steer
    commanded = bottom.lines[0]
    np.testing.assert_allclose(commanded.get_xdata(), t - t[0])
    want = np.degrees(brake_yaw_rate(tested[:, 0], tested[:, 1], CAL, CFG))
    np.testing.assert_allclose(commanded.get_ydata(), want)
    assert want.max() > 0 > want.min()  # the left brake turns left, the right one right


def test_drag_figure_leaves_out_what_was_not_measured(tmp_path):
    commands, _, frames, _ = series()
    fig = drag_figure(None, frames, None, commands, CAL, CFG)
    (ax,) = fig.axes
    assert ax.get_ylabel() == "obstacle drag [m]" and ax.get_xlabel() == "time [s]"
    path = plot_drag(tmp_path / "drag.png", None, frames, None, commands, CAL, CFG)
    assert path.read_bytes()[:4] == b"\x89PNG"


def test_controller_replay_figure_shows_both_series_per_wheel():
    t = np.arange(0.0, 2.0, 0.5)
    logged = np.array([[OFF, OFF], [1.0, OFF], [1.0, OFF], [OFF, 2.0]])
    recomputed = logged + np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.0], [0.0, -1.0]])
    fake = SimpleNamespace(name="open-loop", arrays=lambda: (t, logged, recomputed))
    left, right = controller_replay_figure(fake).axes
    assert left.get_ylabel() == "left torque [N·m]" and right.get_ylabel() == "right torque [N·m]"
    assert right.get_xlabel() == "time [s]"
    assert legend_texts(left) == ["logged", "recomputed (open-loop)"]
    np.testing.assert_array_equal(right.lines[1].get_ydata(), recomputed[:, 1])


def test_the_drag_metrics_module_has_no_plotting_code():
    source = Path(experiments.drag.__file__).read_text()
    imported, defined = set(), set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module or "")
        elif isinstance(node, ast.FunctionDef):
            defined.add(node.name)
    assert not any(m.split(".")[0] == "matplotlib" for m in imported)
    assert not any("plot" in name or "figure" in name for name in defined)
    assert {"over_steer", "write_frames_csv", "controller_replay_summary"} <= defined
    # nor does importing it load figure code (matplotlib.path comes with experiments.metrics)
    figure_code = ("matplotlib.figure", "matplotlib.pyplot", "experiments.drag_figures")
    check = (
        "import sys, experiments.drag; "
        f"print(sorted(m for m in sys.modules if m in {figure_code!r}))"
    )
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
