"""The obstacle-course study (thesis Table 6.3) with simulated users.

N users walk the course (`thesis-course` by default) in every cell controller ×
localizer × surface. User i (trial index i) has seed SEED + i: their `UserProfile` is
`UserProfile.sample(SEED + i)` and the simulator (slip noise, sensor noise, the user's
drifting sense of heading) runs with the same seed, so every cell meets exactly the same
users and the same noise — a paired design: a difference between two controllers in one
user's trial is the controllers' doing, not the user's. Localizers with a `seed` field
get the trial seed too.

Outputs (in the study folder): `results.db` / `results.csv` (one row per run: cell,
controller and localizer configs, seed, user profile, collisions by kind, route
completion, ATE and phantom area of the controller's own map, braking impulse, ...),
`table.md` (Table 6.3: collisions per trial by kind, totals, change of the total against
`none` with a paired-bootstrap 95 % CI, see `tables`), `figures/paths_<cell>.png` (each
user's path over the course) and `figures/paths_all.png`, `report.md`, `study.json` (the
study's configuration) and, unless disabled, each run's trial log under
`runs/<cell>/trial<i>.mcap` (replayable with `walkerslam replay`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from control.base import CONTROLLERS
from experiments.config import configure
from experiments.simulation import RunSpec
from experiments.studies import figures, tables
from experiments.studies.runner import StudyResult, run_and_store, write_json
from hardware.errors import ConfigError
from hardware.sim.slip import surface_coefficient
from hardware.sim.user import UserProfile
from hardware.sim.world import load_world
from slam.base import LOCALIZERS

METRIC_COLUMNS = (
    "collisions_front",
    "collisions_side",
    "collisions_rear_wheel",
    "collisions_total",
    "finished_route",
    "sim_time_s",
    "distance_m",
    "ate_rmse_m",
    "ate_rmse_unaligned_m",
    "final_position_error_m",
    "map_precision",
    "phantom_area_m2",
    "braking_impulse_nms",
    "min_clearance_m",
    "wall_time_s",
)
COLUMNS = (
    "study",
    "cell",
    "controller",
    "localizer",
    "surface",
    "trial",
    "seed",
    "duration_s",
    *METRIC_COLUMNS,
    "user_profile",
    "controller_config",
    "localizer_config",
    "collisions",
    "log",
    "config",
)


@dataclass(frozen=True)
class CourseStudy:
    """What a course study runs. settings: {controller or localizer name: {field: value}}
    applied to that name's default config."""

    controllers: tuple[str, ...] = ("none", "open-loop")
    localizers: tuple[str, ...] = ("dead-reckoning",)
    surfaces: tuple[str, ...] = ("dusty",)
    trials: int = 10
    seed: int = 0
    duration_s: float = 300.0
    course: str = "thesis-course"
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    keep_logs: bool = True
    baseline: str = "none"

    def validate(self) -> None:
        """Fail before any run: unknown names, bad settings, bad numbers."""
        for name, what in ((self.controllers, "controller"), (self.localizers, "localizer")):
            if not name:
                raise ConfigError(f"no {what}s given")
        for names in (self.controllers, self.localizers, self.surfaces):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ConfigError(f"repeated names: {', '.join(dup)}")
        for c in self.controllers:
            configure(CONTROLLERS, c, None, self.settings.get(c, {}))
        for loc in self.localizers:
            configure(LOCALIZERS, loc, None, self.settings.get(loc, {}))
        unknown = sorted(set(self.settings) - set(self.controllers) - set(self.localizers))
        if unknown:
            raise ConfigError(f"settings for names not in the study: {', '.join(unknown)}")
        if not self.surfaces:
            raise ConfigError("no surfaces given")
        for s in self.surfaces:
            surface_coefficient(s)
        if self.trials < 1:
            raise ConfigError(f"trials must be >= 1, got {self.trials}")
        if not self.duration_s > 0:
            raise ConfigError(f"duration must be > 0, got {self.duration_s}")
        load_world(self.course)

    def trial_seed(self, trial: int) -> int:
        return self.seed + trial

    def cells(self) -> list[tuple[str, str, str]]:
        """(controller, localizer, surface) of every cell, in table order."""
        return [
            (c, loc, s) for loc in self.localizers for s in self.surfaces for c in self.controllers
        ]


def cell_name(controller: str, localizer: str, surface: str) -> str:
    return f"{controller}_{localizer}_{surface}"


def plan(study: CourseStudy, out: Path) -> list[RunSpec]:
    """Every run of the study (trial-major within a cell, cells in table order)."""
    specs = []
    for controller, localizer, surface in study.cells():
        cell = cell_name(controller, localizer, surface)
        for i in range(study.trials):
            seed = study.trial_seed(i)
            log = out / "runs" / cell / f"trial{i:03d}.mcap"
            specs.append(
                RunSpec(
                    course=study.course,
                    controller=controller,
                    localizer=localizer,
                    surface=surface,
                    seed=seed,
                    duration_s=study.duration_s,
                    controller_overrides=tuple(study.settings.get(controller, {}).items()),
                    localizer_overrides=tuple(study.settings.get(localizer, {}).items()),
                    user_profile=UserProfile.sample(seed),
                    log_path=str(log) if study.keep_logs else None,
                    labels={"study": "course", "cell": cell, "trial": i},
                )
            )
    return specs


def result_row(res: dict[str, Any]) -> dict[str, Any]:
    """One results-table row from a `run_trial` result."""
    spec: RunSpec = res["spec"]
    m, cfg = res["metrics"], res["config"]
    row: dict[str, Any] = {
        "study": spec.labels.get("study"),
        "cell": spec.labels.get("cell"),
        "controller": spec.controller,
        "localizer": spec.localizer,
        "surface": str(spec.surface),
        "trial": spec.labels.get("trial"),
        "seed": spec.seed,
        "duration_s": spec.duration_s,
    }
    for k in METRIC_COLUMNS:
        row[k] = m.get(k)
    row.update(
        user_profile=asdict(spec.user_profile) if spec.user_profile else None,
        controller_config=cfg["controller_config"],
        localizer_config=cfg["localizer_config"],
        collisions=[list(c) for c in res["collisions"]],
        log=spec.log_path,
        config=cfg,
    )
    return row


def run_course_study(
    study: CourseStudy,
    out_dir: str | Path,
    *,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> StudyResult:
    study.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    specs = plan(study, out)
    results, rows, files = run_and_store(
        specs,
        out,
        result_row,
        COLUMNS,
        engine=engine,
        workers=workers,
        address=address,
        progress=progress,
    )
    table = tables.collision_table(rows, study.baseline)
    files.update(_figures(study, out, rows, results))
    files["table"] = out / "table.md"
    files["table"].write_text(_table_md(study, table) + "\n")
    files["study"] = write_json(
        out / "study.json",
        {
            "command": "course-study",
            **asdict(study),
            "engine": engine,
            "runs": len(rows),
            "users": [asdict(UserProfile.sample(study.trial_seed(i))) for i in range(study.trials)],
        },
    )
    files["report"] = _report(study, out, rows, table, files)
    return StudyResult(rows, table, files)


def _figures(study, out: Path, rows, results) -> dict[str, Path]:
    world = load_world(study.course)
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    files: dict[str, Path] = {}
    by_cell: dict[str, list[dict[str, Any]]] = {}
    for row, res in zip(rows, results, strict=True):
        by_cell.setdefault(row["cell"], []).append(
            {"trial": row["trial"], "path": res["path"], "collisions": res["collisions"]}
        )
    overview = []
    for controller, localizer, surface in study.cells():
        cell = cell_name(controller, localizer, surface)
        runs = by_cell.get(cell, [])
        n = sum(len(r["collisions"]) for r in runs)
        title = (
            f"{controller} · {localizer} · {surface}: {len(runs)} users, "
            f"{n / max(len(runs), 1):.2f} collisions per trial"
        )
        files[f"paths_{cell}"] = figures.course_paths(
            world, runs, title, fig_dir / f"paths_{cell}.png"
        )
        overview.append((title, runs))
    files["paths_all"] = figures.course_overview(world, overview, fig_dir / "paths_all.png")
    return files


def _table_md(study: CourseStudy, table) -> str:
    return tables.markdown(
        tables.collision_headers(study.baseline), tables.collision_rows(table, study.baseline)
    )


def _other_metrics_md(rows) -> str:
    """The means per controller × localizer × surface of the metrics besides collisions."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["controller"], r["localizer"], r["surface"]), []).append(r)
    return tables.markdown(
        (
            "controller",
            "localizer",
            "surface",
            "runs",
            "sim time s",
            "distance m",
            "ATE m",
            "phantom m²",
            "braking N·m·s",
            "min clearance m",
        ),
        [
            [
                *key,
                len(rs),
                f"{tables.mean_of(rs, 'sim_time_s'):.1f}",
                f"{tables.mean_of(rs, 'distance_m'):.1f}",
                f"{tables.mean_of(rs, 'ate_rmse_m'):.3f}",
                f"{tables.mean_of(rs, 'phantom_area_m2'):.2f}",
                f"{tables.mean_of(rs, 'braking_impulse_nms'):.1f}",
                f"{tables.mean_of(rs, 'min_clearance_m'):.3f}",
            ]
            for key, rs in groups.items()
        ],
    )


def _report(study: CourseStudy, out: Path, rows, table, files) -> Path:
    """report.md: the design, the collision table, the other metrics, the figures."""
    other = _other_metrics_md(rows)
    settings = "; ".join(f"{n}: {v}" for n, v in study.settings.items()) or "defaults"
    lines = [
        f"# Course study: {study.course}",
        "",
        f"{study.trials} simulated users × controllers {', '.join(study.controllers)} × "
        f"localizers {', '.join(study.localizers)} × surfaces {', '.join(study.surfaces)}; "
        f"at most {study.duration_s:g} s per trial; seeds {study.seed}–"
        f"{study.trial_seed(study.trials - 1)}; config settings: {settings}.",
        "",
        "User i has seed SEED + i in every cell (same `UserProfile`, same simulator noise): "
        "the design is paired. Change of the total against "
        f"`{study.baseline}`: 100·(Σ total / Σ baseline total − 1) over the same users, with "
        "a 95 % paired percentile bootstrap over users (10 000 resamples, seeded).",
        "",
        "## Collisions (thesis Table 6.3)",
        "",
        _table_md(study, table),
        "",
        "## Other metrics (means per run)",
        "",
        "ATE and phantom area are those of the localizer and map the controller used.",
        "",
        other,
        "",
        "## Paths",
        "",
        "True paths of each user (same colour = same user in every cell); markers: "
        "collisions (x front, ^ side, o rear wheel).",
        "",
        f"![all cells](figures/{files['paths_all'].name})",
        "",
    ]
    for controller, localizer, surface in study.cells():
        cell = cell_name(controller, localizer, surface)
        lines.append(f"- [{controller} · {localizer} · {surface}](figures/paths_{cell}.png)")
    lines += [
        "",
        "Files: `results.db` (tables `runs`, `paths`), `results.csv`, `table.md`, "
        "`study.json`" + (", trial logs in `runs/`." if study.keep_logs else "."),
    ]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
