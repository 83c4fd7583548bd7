"""The figures of a replay and of a comparison (experiments.report): what each one shows —
metric axes with units, legends naming what is drawn and placed off the data, titles
naming the localizer and the log, the map figure's cells those of map.pgm, both panels of
the side-by-side on one extent — on small synthetic maps and paths, then as a replay and
a comparison write them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.figure import Figure

from experiments import report
from experiments.compare import compare
from experiments.metrics import GROUND_TRUTH, truth_names
from experiments.report import (
    UNKNOWN_GREY,
    errors_figure,
    map_figure,
    maps_figure,
    paths_figure,
    trajectory_figure,
)
from experiments.run import MAP_BAND_M, replay_log, simulate_trial
from hardware.log import read_log
from hardware.messages import Collision, LaserScan
from hardware.sim.world import World
from mapping.export import load_map_yaml, map_raster, save_map_server
from mapping.mapper import OccupancyMapper
from slam.trajectory import Trajectory

# A 4 m × 3 m room (walls mid-cell) with a pillar (its outline a square around it).
ROOM = np.array([[-1.525, -1.025], [2.525, -1.025], [2.525, 2.025], [-1.525, 2.025]])
BOX = np.array([[1.45, 0.85], [1.75, 0.85], [1.75, 1.15], [1.45, 1.15]])
OUTLINES = [ROOM, BOX]
MAP_LEGEND = ["occupied", "free", "unknown"]


PILLAR, PILLAR_R = np.array([1.6, 1.0]), 0.15  # round, so the room has a shadow behind it


def room_scan_map(offset=(0.0, 0.0)) -> OccupancyMapper:
    """The room and its pillar scanned from three poses, the map placed `offset` [m] away
    (as a localizer with that position error would place it)."""
    mapper = OccupancyMapper()
    a = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    for x, y in [(0.0, 0.0), (0.8, 0.5), (-0.6, 1.2)]:
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (2.525 - x) / c, (-1.525 - x) / c)
            ty = np.where(s > 0, (2.025 - y) / s, (-1.025 - y) / s)
        b = (PILLAR[0] - x) * c + (PILLAR[1] - y) * s
        disc = b**2 - ((PILLAR[0] - x) ** 2 + (PILLAR[1] - y) ** 2 - PILLAR_R**2)
        with np.errstate(invalid="ignore"):
            tp = np.where(disc >= 0, b - np.sqrt(disc), np.inf)
        ranges = np.minimum(np.minimum(tx, ty), np.where(tp > 0, tp, np.inf))
        scan = LaserScan(0.0, float(a[0]), float(a[1] - a[0]), ranges, 30.0)
        for _ in range(3):  # free cells need a few looks
            mapper.integrate_scan(scan, np.array([x + offset[0], y + offset[1], 0.0]))
    return mapper


@pytest.fixture(scope="module")
def maps():
    return room_scan_map().grid, room_scan_map((1.0, 0.5)).grid


def paths() -> tuple[Trajectory, Trajectory]:
    """A true path across the room and an estimate 0.3 m east and 0.4 m north of it."""
    t = np.linspace(0.0, 10.0, 101)
    truth = np.column_stack([np.linspace(-0.6, 0.8, 101), np.linspace(1.2, 0.0, 101), 0.1 * t])
    return Trajectory(t, truth + np.array([0.3, 0.4, 0.0])), Trajectory(t, truth)


def legend_texts(legend) -> list[str]:
    return [t.get_text() for t in legend.get_texts()]


def lines_equal_to(ax, xy: np.ndarray) -> int:
    return sum(np.array_equal(line.get_xydata(), xy) for line in ax.lines)


def assert_metric_axes(ax) -> None:
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"
    assert ax.get_aspect() == 1.0


def assert_off_the_axes(fig: Figure, legend, axes) -> None:
    fig.draw_without_rendering()
    box = legend.get_window_extent()
    for ax in axes:
        assert not box.overlaps(ax.get_window_extent())


def assert_within_limits(ax, xmin: float, xmax: float, ymin: float, ymax: float) -> None:
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert x0 <= xmin and xmax <= x1 and y0 <= ymin and ymax <= y1


# -- map.png ----------------------------------------------------------------------------


def test_map_figure_has_metric_axes_a_legend_off_the_map_and_names_the_run(maps):
    grid = maps[1]
    est, gt = paths()
    fig = map_figure(
        grid, OUTLINES, est.poses[:, :2], gt.poses[:, :2], localizer="ekf-slam", log="a/b/t.mcap"
    )
    (ax,) = fig.axes
    assert_metric_axes(ax)
    legend = ax.get_legend()
    assert legend_texts(legend) == [
        *MAP_LEGEND,
        "true obstacle outlines",
        "true path",
        "estimated path (ekf-slam)",
    ]
    assert_off_the_axes(fig, legend, [ax])
    title = ax.get_title()
    assert "ekf-slam" in title and "t.mcap" in title and "a/b" not in title
    assert lines_equal_to(ax, est.poses[:, :2]) == 1 and lines_equal_to(ax, gt.poses[:, :2]) == 1
    assert_within_limits(ax, *map_raster(grid).extent)
    assert_within_limits(ax, -1.525, 2.525, -1.025, 2.025)  # the room's outline


def test_map_figure_draws_the_cells_of_map_pgm(maps, tmp_path):
    grid = maps[0]
    yaml_path, _ = save_map_server(grid, tmp_path / "map.yaml")
    loaded = load_map_yaml(yaml_path)
    (ax,) = map_figure(grid, localizer="dead-reckoning", log="t.mcap").axes
    (image,) = ax.images
    tri = loaded.trinary  # row 0 = lowest y, as drawn with origin="lower"
    want = np.where(tri == 1, 0.0, np.where(tri == 0, 1.0, UNKNOWN_GREY))
    np.testing.assert_array_equal(image.get_array(), want)
    x0, y0, _ = loaded.origin
    ny, nx = tri.shape
    assert image.get_extent() == pytest.approx(
        [x0, x0 + nx * loaded.resolution, y0, y0 + ny * loaded.resolution]
    )
    assert {-1, 0, 1} <= set(np.unique(tri).tolist())
    # without outlines or paths the legend has the cells only
    assert legend_texts(ax.get_legend()) == MAP_LEGEND


def test_map_figure_shows_the_building_not_stray_long_range_returns():
    """A laser's stray returns far outside the building (single occupied cells) do not
    set the view, which holds the walls; the title counts the cells left out."""
    mapper = room_scan_map()
    a = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    ranges = np.full(720, np.inf)
    ranges[[10, 200, 400, 650]] = [24.0, 27.0, 25.5, 22.0]  # through the walls (a window)
    mapper.integrate_scan(
        LaserScan(0.0, float(a[0]), float(a[1] - a[0]), ranges, 30.0), np.zeros(3)
    )
    grid = mapper.grid
    assert map_raster(grid).extent[1] > 20.0  # the map itself keeps them
    fig = map_figure(grid, localizer="gtsam", log="seattle.log")
    (ax,) = fig.axes
    xmin, xmax = ax.get_xlim()
    ymin, ymax = ax.get_ylim()
    # the room's walls (x −1.525…2.525, y −1.025…2.025) with the figure's 0.3 m margin
    assert (xmin, xmax) == pytest.approx((-1.55 - 0.3, 2.55 + 0.3), abs=0.06)
    assert (ymin, ymax) == pytest.approx((-1.05 - 0.3, 2.05 + 0.3), abs=0.06)
    assert "4 occupied cells outside the view" in ax.get_title()


# -- maps_side_by_side.png -----------------------------------------------------------------


def test_side_by_side_panels_share_one_extent_and_draw_the_true_path_on_both(maps):
    reference, estimated = maps
    est, gt = paths()
    ref_box, est_box = map_raster(reference).extent, map_raster(estimated).extent
    assert ref_box != est_box  # the two maps cover different ground
    fig = maps_figure(
        reference,
        estimated,
        OUTLINES,
        est.poses[:, :2],
        gt.poses[:, :2],
        localizer="ekf-slam",
        log="out/demo/trial.mcap",
    )
    left, right = fig.axes
    assert left.get_xlim() == right.get_xlim() and left.get_ylim() == right.get_ylim()
    for ax, box in ((left, ref_box), (right, est_box)):
        assert_metric_axes(ax)
        assert_within_limits(ax, *ref_box)
        assert_within_limits(ax, *est_box)
        assert ax.images[0].get_extent() == pytest.approx(list(box))
    assert lines_equal_to(left, gt.poses[:, :2]) == 1
    assert lines_equal_to(left, est.poses[:, :2]) == 0
    assert lines_equal_to(right, gt.poses[:, :2]) == 1
    assert lines_equal_to(right, est.poses[:, :2]) == 1
    assert "true poses" in left.get_title()
    assert "ekf-slam" in right.get_title()
    assert "trial.mcap" in fig.get_suptitle() and "out/demo" not in fig.get_suptitle()
    (legend,) = fig.legends
    assert legend_texts(legend) == [
        *MAP_LEGEND,
        "true obstacle outlines",
        "true path",
        "estimated path (ekf-slam)",
    ]
    assert_off_the_axes(fig, legend, [left, right])


# -- trajectory.png, errors.png ---------------------------------------------------------


def test_trajectory_figure_names_the_paths_outlines_and_collisions():
    est, gt = paths()
    hits = [Collision(1.0, "front", "pillar", 0.5, 0.6), Collision(2.0, "side", "wall", 2.5, 0.0)]
    fig = trajectory_figure(est, gt, OUTLINES, hits, localizer="fastslam", log="x/run3.mcap")
    (ax,) = fig.axes
    assert_metric_axes(ax)
    legend = ax.get_legend()
    assert legend_texts(legend) == [
        "true obstacle outlines",
        "true path",
        "estimated path (fastslam)",
        "collisions (2)",
    ]
    assert_off_the_axes(fig, legend, [ax])
    assert "fastslam" in ax.get_title() and "run3.mcap" in ax.get_title()
    marks = [line for line in ax.lines if line.get_marker() == "x"]
    np.testing.assert_array_equal(marks[0].get_xydata(), [[0.5, 0.6], [2.5, 0.0]])
    assert_within_limits(ax, -1.525, 2.525, -1.025, 2.025)
    # a log without ground truth, world or collisions: the estimate alone
    (ax,) = trajectory_figure(est, None, [], localizer="fastslam", log="run3.mcap").axes
    assert legend_texts(ax.get_legend()) == ["estimated path (fastslam)"]


def test_errors_figure_plots_the_error_with_units():
    est, gt = paths()
    fig = errors_figure(est, gt, [], localizer="ekf-slam", log="t.mcap")
    pos_ax, head_ax = fig.axes
    assert pos_ax.get_ylabel() == "position error [m]"
    assert head_ax.get_ylabel() == "heading error [deg]"
    assert head_ax.get_xlabel() == "time [s]"
    assert "ekf-slam" in pos_ax.get_title() and "t.mcap" in pos_ax.get_title()
    np.testing.assert_allclose(pos_ax.lines[0].get_ydata(), 0.5)  # 0.3 east, 0.4 north
    np.testing.assert_allclose(head_ax.lines[0].get_ydata(), 0.0, atol=1e-9)


# -- compare's <log>_trajectories.png ----------------------------------------------------


def test_paths_figure_draws_each_localizer_the_true_path_and_the_outlines():
    est, gt = paths()
    drawn = {"dead-reckoning": est.poses[:, :2], "ekf-slam": gt.poses[:, :2] + 0.05}
    fig = paths_figure("trial", drawn, gt.poses[:, :2], OUTLINES)
    (ax,) = fig.axes
    assert_metric_axes(ax)
    legend = ax.get_legend()
    assert legend_texts(legend) == ["true obstacle outlines", "true path", *drawn]
    assert_off_the_axes(fig, legend, [ax])
    closed = [np.vstack([p, p[:1]]) for p in OUTLINES]
    assert all(lines_equal_to(ax, c) == 1 for c in closed)
    assert all(lines_equal_to(ax, xy) == 1 for xy in drawn.values())
    assert "trial" in ax.get_title() and "true path" in ax.get_title()
    # a dataset without a world or ground truth: the estimates alone
    (ax,) = paths_figure("robot1", drawn).axes
    assert legend_texts(ax.get_legend()) == list(drawn)
    assert len(ax.lines) == 2


# -- as a replay and a comparison write them --------------------------------------------


@pytest.fixture(scope="module")
def corner_trial(tmp_path_factory):
    path = tmp_path_factory.mktemp("fig") / "corner.mcap"
    simulate_trial("corner", path, seed=0, duration_s=8.0)
    return path


@pytest.fixture
def saved(monkeypatch):
    """The figures experiments.report saves, by file name (they are still written)."""
    figures: dict[str, Figure] = {}
    save = report.save

    def keep(fig, path):
        figures[path.name] = fig
        return save(fig, path)

    monkeypatch.setattr(report, "save", keep)
    return figures


def test_a_replay_writes_each_figure_naming_its_run(corner_trial, tmp_path, saved):
    res = replay_log(corner_trial, tmp_path, localizer="ekf-slam", figures=True)
    assert res.metrics["groundtruth_kind"] == "simulated"
    assert "true path" in legend_texts(saved["trajectory.png"].axes[0].get_legend())
    names = ["map.png", "trajectory.png", "errors.png", "maps_side_by_side.png"]
    assert sorted(saved) == sorted(names)
    for name in names:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert res.files["map_png"] == tmp_path / "map.png"
    for name in ("map.png", "trajectory.png"):
        title = saved[name].axes[0].get_title()
        assert "ekf-slam" in title and "corner.mcap" in title
    # the true outlines of the corner's walls on the map figure and the side-by-side
    walls = [p for _, p in res.world.footprint_polygons(*MAP_BAND_M)]
    closed = [np.vstack([p, p[:1]]) for p in walls]
    for ax in (saved["map.png"].axes[0], *saved["maps_side_by_side.png"].axes):
        assert all(lines_equal_to(ax, c) == 1 for c in closed)
    assert "ekf-slam" in saved["maps_side_by_side.png"].axes[1].get_title()


def test_a_replay_without_figures_still_writes_the_map_figure(corner_trial, tmp_path, saved):
    replay_log(corner_trial, tmp_path, figures=False, drag_metrics=False)
    assert list(saved) == ["map.png"]
    assert (tmp_path / "map.png").exists() and (tmp_path / "map.pgm").exists()


def test_a_replay_without_the_map_figure_writes_the_map_alone(corner_trial, tmp_path, saved):
    res = replay_log(corner_trial, tmp_path, figures=False, map_figure=False, drag_metrics=False)
    assert saved == {} and "map_png" not in res.files
    assert not (tmp_path / "map.png").exists() and (tmp_path / "map.pgm").exists()


def test_compare_draws_the_true_outlines_on_its_trajectories_figure(corner_trial, tmp_path, saved):
    res = compare([corner_trial], ["dead-reckoning", "ekf-slam"], seeds=1, out_dir=tmp_path)
    assert res.files["corner_figure"] == tmp_path / "corner_trajectories.png"
    assert "Its errors are against" not in res.files["report"].read_text()  # the true poses
    assert res.files["corner_figure"].exists()
    (ax,) = saved["corner_trajectories.png"].axes
    assert_metric_axes(ax)
    assert legend_texts(ax.get_legend()) == [
        "true obstacle outlines",
        "true path",
        "dead-reckoning",
        "ekf-slam",
    ]
    walls = World.from_dict(read_log(corner_trial).metadata["world"]).footprint_polygons(
        *MAP_BAND_M
    )
    grey = [line for line in ax.lines if line.get_color() == report.OUTLINE_COLOUR_PLAIN]
    assert len(walls) > 0 and len(grey) == len(walls)
    assert all(lines_equal_to(ax, np.vstack([p, p[:1]])) == 1 for _, p in walls)


def test_figures_name_a_stand_in_for_ground_truth_as_what_it_is(tmp_path, saved):
    """A CARMEN log's corrected poses are GMapping's output, not ground truth: the
    metrics say what the errors are against, and the figures call them so; a
    simulation's poses stay the true ones."""
    from hardware.datasets import open_dataset
    from tests.hardware.datasets.datasets_testdata import write_carmen

    path = write_carmen(tmp_path / "s.log", scans=6, beams=180)
    res = replay_log(
        open_dataset("carmen", path), tmp_path / "r", localizer="dead-reckoning", figures=True,
        drag_metrics=False,
    )  # fmt: skip
    assert res.metrics["groundtruth_kind"] == "slam-corrected"
    title = saved["errors.png"].axes[0].get_title()
    assert "against the corrected poses (SLAM output, not ground truth)" in title
    for name in ("map.png", "trajectory.png"):
        labels = legend_texts(saved[name].axes[0].get_legend())
        assert "corrected path (SLAM output)" in labels and "true path" not in labels
    left = saved["maps_side_by_side.png"].axes[0].get_title()
    assert left.startswith("map from the corrected poses")
    res = compare(
        [open_dataset("carmen", path)], ["dead-reckoning"], seeds=1, out_dir=tmp_path / "c"
    )
    (ax,) = saved["s_trajectories.png"].axes
    assert "corrected path (SLAM output)" in legend_texts(ax.get_legend())
    assert "against the corrected path (SLAM output)" in ax.get_title()
    report_md = res.files["report"].read_text()
    assert (
        "Its errors are against the corrected poses (SLAM output, not ground truth)." in report_md
    )
    assert truth_names(None) == truth_names("simulated") == GROUND_TRUTH
