"""The slip study: how much each encoder-slip mitigation removes of what slip does.

Every cell of surface (slip severity) × localizer × mitigation set × controller is walked
by the same N simulated users (user i has seed SEED + i in every cell: the same
`UserProfile`, the same simulator noise — a paired design, as in the course study). A run
is the closed loop with the localizer and its mitigations live (they steer the brakes
through the map), recorded; the log is then replayed with the same localizer and
mitigations to measure the drag (`experiments.run.replay_log`: phantom area over time,
obstacle drag, over-steer against the same controller at the true pose).

Per run (results.db): collisions by kind, ATE (aligned and not), the heading error
added while braking, the final heading error, phantom area (final and largest), obstacle
drag (absolute, and added within 1 s during braked turns), over-steer, braking impulse,
the live and replay wall times. The report ranks the mitigations: per metric, the
paired difference against no mitigation (same surface, localizer, controller and users)
with a 95 % percentile bootstrap interval over users; figures plot each metric against
the surface's slip coefficient with 95 % bands.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from control.base import CONTROLLERS
from experiments.config import configure
from experiments.mitigations import check_calibration, resolve, set_name
from experiments.simulation import RunSpec
from experiments.studies import slip_report
from experiments.studies.runner import StudyResult, run_and_store, write_json
from experiments.studies.trial import run_trial
from hardware.errors import ConfigError
from hardware.sim.slip import surface_coefficient
from hardware.sim.user import UserProfile
from hardware.sim.world import load_world
from slam.base import LOCALIZERS

# (results.db column, where in the replay's metrics.json it is); the live run's own
# columns (collisions, route, wall time, braking) come from `run_trial`.
REPLAY_METRICS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("ate_rmse_m", ("ate_rmse_m",)),
    ("ate_rmse_unaligned_m", ("ate_rmse_unaligned_m",)),
    ("final_heading_error_deg", ("final_heading_error_deg",)),
    ("heading_error_braking_deg", ("heading_error_braking_deg",)),
    ("phantom_area_m2", ("phantom_area_m2",)),
    ("phantom_area_max_m2", ("phantom_area_over_time", "max_m2")),
    ("drag_mean_m", ("drag", "absolute", "all", "mean_m")),
    ("drag_added_braked_turn_m", ("drag", "local", "braked_turn", "mean_m")),
    ("drag_toward_turn_m", ("drag", "local", "braked_turn", "toward_turn_mean_m")),
    ("over_steer_deg", ("over_steer", "over_steer_mean_deg")),
    ("replay_realtime_factor", ("realtime_factor",)),
)
LIVE_METRICS = (
    "collisions_front",
    "collisions_side",
    "collisions_rear_wheel",
    "collisions_total",
    "finished_route",
    "sim_time_s",
    "distance_m",
    "braking_impulse_nms",
    "wall_time_s",
)
METRIC_COLUMNS = (*LIVE_METRICS, *(name for name, _ in REPLAY_METRICS))
COLUMNS = (
    "study",
    "cell",
    "surface",
    "slip_k",
    "localizer",
    "mitigation",
    "controller",
    "trial",
    "seed",
    *METRIC_COLUMNS,
    "user_profile",
    "localizer_config",
    "controller_config",
    "collisions",
    "log",
    "config",
)


@dataclass(frozen=True)
class SlipStudy:
    """What a slip study runs (module docstring). mitigations: the sets compared, each a
    tuple of mitigation names (() = none, the baseline of the ranking); settings:
    {controller or localizer name: {field: value}}; calibration: the file the
    'calibration' mitigation uses (the walker's software calibration in those runs)."""

    surfaces: tuple[str, ...] = ("clean", "dusty")
    localizers: tuple[str, ...] = ("dead-reckoning",)
    mitigations: tuple[tuple[str, ...], ...] = ((),)
    controllers: tuple[str, ...] = ("open-loop",)
    trials: int = 10
    seed: int = 0
    duration_s: float = 300.0
    course: str = "thesis-course"
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    keep_logs: bool = True
    calibration: str | None = None

    def validate(self) -> None:
        """Fail before any run: unknown names, mitigations that do not apply, numbers."""
        for names, what in (
            (self.surfaces, "surface"),
            (self.localizers, "localizer"),
            (self.controllers, "controller"),
            (self.mitigations, "mitigation set"),
        ):
            if not names:
                raise ConfigError(f"no {what}s given")
            dup = sorted({str(n) for n in names if names.count(n) > 1})
            if dup:
                raise ConfigError(f"repeated {what}s: {', '.join(dup)}")
        for s in self.surfaces:
            surface_coefficient(s)
        for c in self.controllers:
            configure(CONTROLLERS, c, None, self.settings.get(c, {}))
        for loc in self.localizers:
            for combo in self.mitigations:
                m = resolve(combo, loc)
                check_calibration(m, self.calibration)
                configure(
                    LOCALIZERS, loc, None, {**m.localizer_settings, **self.settings.get(loc, {})}
                )
        unknown = sorted(set(self.settings) - set(self.controllers) - set(self.localizers))
        if unknown:
            raise ConfigError(f"settings for names not in the study: {', '.join(unknown)}")
        if self.trials < 1:
            raise ConfigError(f"trials must be >= 1, got {self.trials}")
        if not self.duration_s > 0:
            raise ConfigError(f"duration must be > 0, got {self.duration_s}")
        load_world(self.course)

    def trial_seed(self, trial: int) -> int:
        return self.seed + trial

    def cells(self) -> list[tuple[str, str, tuple[str, ...], str]]:
        """(surface, localizer, mitigation set, controller) of every cell."""
        return [
            (s, loc, m, c)
            for loc in self.localizers
            for c in self.controllers
            for m in self.mitigations
            for s in self.surfaces
        ]


def cell_name(surface: str, localizer: str, combo: tuple[str, ...], controller: str) -> str:
    return f"{surface}_{localizer}_{set_name(combo)}_{controller}"


def plan(study: SlipStudy, out: Path) -> list[RunSpec]:
    """Every run of the study, cells in `cells` order, trial-major within a cell."""
    specs = []
    for surface, localizer, combo, controller in study.cells():
        cell = cell_name(surface, localizer, combo, controller)
        for i in range(study.trials):
            seed = study.trial_seed(i)
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
                    log_path=str(out / "runs" / cell / f"trial{i:03d}.mcap"),
                    labels={
                        "study": "slip",
                        "cell": cell,
                        "trial": i,
                        "keep_log": study.keep_logs,
                        "calibration": study.calibration if "calibration" in combo else None,
                    },
                    mitigations=combo,
                )
            )
    return specs


def run_slip_trial(spec: RunSpec) -> dict[str, Any]:
    """One run: the closed loop (`run_trial`), then its log replayed with the same
    localizer, settings and mitigations for the drag metrics (module docstring)."""
    from experiments.calibration_override import CalibrationOverride
    from experiments.run import replay_log

    calibration = CalibrationOverride.load(spec.labels.get("calibration"))
    res = run_trial(spec, calibration=calibration)
    log = Path(str(spec.log_path))
    over = dict(spec.localizer_overrides)
    if "seed" in res["config"]["localizer_config"] and "seed" not in over:
        over["seed"] = spec.seed  # as the live localizer had it
    replay_dir = log.with_suffix("")
    keep = spec.labels.get("keep_log", True)
    rep = replay_log(
        log,
        replay_dir,
        localizer=spec.localizer,
        localizer_overrides=over,
        mitigations=spec.mitigations,
        calibration=calibration,
        figures=False,
        map_figure=keep,  # (removed below otherwise)
    )
    for name, path in REPLAY_METRICS:
        res["metrics"][name] = _dig(rep.metrics, path)
    if not keep:
        log.unlink(missing_ok=True)
        shutil.rmtree(replay_dir, ignore_errors=True)
    return res


def _dig(d: Any, path: tuple[str, ...]) -> Any:
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return None if isinstance(d, float) and not math.isfinite(d) else d


def result_row(res: dict[str, Any]) -> dict[str, Any]:
    """One results-table row from a `run_slip_trial` result."""
    spec: RunSpec = res["spec"]
    m, cfg = res["metrics"], res["config"]
    row: dict[str, Any] = {
        "study": "slip",
        "cell": spec.labels.get("cell"),
        "surface": str(spec.surface),
        "slip_k": surface_coefficient(spec.surface),
        "localizer": spec.localizer,
        "mitigation": set_name(spec.mitigations),
        "controller": spec.controller,
        "trial": spec.labels.get("trial"),
        "seed": spec.seed,
    }
    row.update({k: m.get(k) for k in METRIC_COLUMNS})
    row.update(
        user_profile=asdict(spec.user_profile) if spec.user_profile else None,
        localizer_config=cfg["localizer_config"],
        controller_config=cfg["controller_config"],
        collisions=[list(c) for c in res["collisions"]],
        log=spec.log_path if spec.labels.get("keep_log", True) else None,
        config=cfg,
    )
    return row


def run_slip_study(
    study: SlipStudy,
    out_dir: str | Path,
    *,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> StudyResult:
    """Run every cell of `study` into out_dir: results.db/.csv, figures, report.md,
    study.json (module docstring)."""
    study.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    specs = plan(study, out)
    _, rows, files = run_and_store(
        specs,
        out,
        result_row,
        COLUMNS,
        engine=engine,
        workers=workers,
        address=address,
        progress=progress,
        run=run_slip_trial,
    )
    ranking = slip_report.ranking(rows)
    files.update(slip_report.figures(rows, out / "figures"))
    files["study"] = write_json(
        out / "study.json",
        {
            "command": "slip-study",
            **asdict(study),
            "mitigations": [set_name(c) for c in study.mitigations],
            "engine": engine,
            "runs": len(rows),
        },
    )
    files["report"] = slip_report.write_report(study, out, rows, ranking, files)
    return StudyResult(rows, ranking, files)
