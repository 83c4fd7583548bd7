"""The corner tests (thesis §6, Figs 6.5–6.8): controller parameter sweeps on `corner`.

The walker approaches a 90° room corner (wall ahead, wall on the right); the user
pushes straight ahead with constant, nearly equal handle forces and does not steer, so
any turn is the controller's braking. Thesis settings: pushed at 0.9–1.2 m/s with 15 lb
(6.8 kg) on each handle; D ∈ 9–30 N·s/m (Dφ 9.75, d_max 1.25 m); Dφ ∈ 4.25–12.5
N·m·s/rad (D 16, d_max 1.75 m); d_max 0.75–2.25 m for both controllers. D and Dφ here
are the closed-loop controller's model parameters; the simulated walker keeps its own
(`WalkerParams`: D 16, Dφ 9). The user's weight on the handles is part of the
simulated walker's 31.5 kg, so the 6.8 kg per handle enters as mass, not as a setting.

Run j of every setting is the same user (seed SEED + j, `Pusher.sample`): a push speed
U(0.9, 1.2) m/s, turned into the constant total handle force D·v + the brakes' residual
drag (so that speed is the unbraked steady state, and the walker starts at it), split
between the handles with an imbalance N(0, 2 %) (clipped at ±5 %); and a start pose
shifted U(−0.2, 0.2) m along and U(−0.1, 0.1) m across the approach, turned N(0, 1°)
(clipped at ±2°).

A sweep is `CONTROLLER.FIELD=V1,V2,...` over that controller's registered config; the
default sweeps (`DEFAULT_SWEEPS`) are the thesis's four and need `closed-loop`
registered. Outputs: `results.db` / `results.csv` (one row per run), `table.md` (per
setting: collisions, closest approach of the walker's footprint to a wall, final
heading, braking), `figures/corner_<controller>_<field>.png` (one per sweep: individual
and averaged paths, walls), `report.md`, `study.json`, trial logs under `runs/`.
"""

from __future__ import annotations

import math
import typing
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from control.base import CONTROLLERS
from experiments.config import configure, convert, field_type, parse_assignment
from experiments.simulation import RunSpec
from experiments.studies import figures, tables
from experiments.studies.runner import StudyResult, run_and_store, write_json
from hardware.errors import ConfigError
from hardware.registry import UnknownNameError
from hardware.sim.dynamics import WalkerParams
from hardware.sim.slip import surface_coefficient
from hardware.sim.world import load_world
from slam.base import LOCALIZERS

PUSH_STREAM = 0xC0E4  # seed-sequence stream of the pusher draw


def _value_label(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class Pusher:
    """A user who pushes straight at constant force, from a slightly varied start."""

    speed_mps: float = 1.05
    imbalance: float = 0.0  # (F_R − F_L) / (F_R + F_L)
    start_ahead_m: float = 0.0
    start_left_m: float = 0.0
    start_turn_rad: float = 0.0

    @classmethod
    def sample(cls, seed: int) -> Pusher:
        """Drawn from `seed` (deterministic); distributions in the module docstring."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), PUSH_STREAM]))
        return cls(
            speed_mps=round(float(rng.uniform(0.9, 1.2)), 4),
            imbalance=round(float(np.clip(rng.normal(0.0, 0.02), -0.05, 0.05)), 5),
            start_ahead_m=round(float(rng.uniform(-0.2, 0.2)), 4),
            start_left_m=round(float(rng.uniform(-0.1, 0.1)), 4),
            start_turn_rad=round(
                float(np.clip(rng.normal(0.0, math.radians(1.0)), -0.035, 0.035)), 5
            ),
        )

    def forces(self, walker: WalkerParams | None = None) -> tuple[float, float]:
        """(left, right) handle forces [N] whose unbraked steady speed is speed_mps on
        `walker` (default: the simulated thesis walker)."""
        walker = walker or WalkerParams()
        drag = 2.0 * walker.brake_torque_off_nm / walker.wheel_radius_m
        total = walker.damping * self.speed_mps + drag
        return (
            round(0.5 * total * (1.0 - self.imbalance), 5),
            round(0.5 * total * (1.0 + self.imbalance), 5),
        )


@dataclass(frozen=True)
class Sweep:
    """Values of one config field of one controller; `base` fixes other fields."""

    controller: str
    field: str
    values: tuple[Any, ...]
    base: tuple[tuple[str, Any], ...] = ()

    @property
    def name(self) -> str:
        return f"{self.controller}.{self.field}"

    @property
    def slug(self) -> str:
        return f"{self.controller}_{self.field}"

    def describe(self) -> str:
        base = ", ".join(f"{k}={_value_label(v)}" for k, v in self.base)
        return f"{self.name} ∈ {{{', '.join(_value_label(v) for v in self.values)}}}" + (
            f" ({base})" if base else ""
        )


DEFAULT_SWEEPS = (
    Sweep("closed-loop", "D", (9.0, 16.0, 23.0, 30.0), (("D_phi", 9.75), ("d_max_m", 1.25))),
    Sweep("closed-loop", "D_phi", (4.25, 7.0, 9.75, 12.5), (("D", 16.0), ("d_max_m", 1.75))),
    Sweep("closed-loop", "d_max_m", (0.75, 1.25, 1.75, 2.25), (("D", 16.0), ("D_phi", 9.75))),
    Sweep("open-loop", "d_max_m", (0.75, 1.25, 1.75, 2.25)),
)


def parse_sweep(text: str) -> Sweep:
    """'open-loop.d_max_m=0.75,1.25' → a Sweep (values typed by the config field; a
    field that takes several numbers itself cannot be swept this way)."""
    controller, fld, raw = parse_assignment(text)
    typ = field_type(CONTROLLERS, controller, fld)
    if typing.get_origin(typ) is tuple:
        raise ConfigError(f"--sweep {text}: {controller}.{fld} takes several values; sweep "
                          "a field of one value")  # fmt: skip
    values = [v.strip() for v in raw.split(",") if v.strip()]
    return Sweep(controller, fld, tuple(convert(v, typ, f"{controller}.{fld}") for v in values))


@dataclass(frozen=True)
class CornerStudy:
    """What a corner study runs; settings: {controller: {field: value}} applied to every
    sweep of that controller (after the sweep's base, before the swept value)."""

    sweeps: tuple[Sweep, ...] = DEFAULT_SWEEPS
    runs: int = 5
    seed: int = 0
    duration_s: float = 7.0
    localizer: str = "dead-reckoning"
    surface: str = "dusty"
    course: str = "corner"
    settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    keep_logs: bool = True

    def overrides(self, sweep: Sweep, value: Any) -> tuple[tuple[str, Any], ...]:
        over = dict(sweep.base)
        over.update(self.settings.get(sweep.controller, {}))
        over[sweep.field] = value
        return tuple(over.items())

    def validate(self) -> None:
        if not self.sweeps:
            raise ConfigError("no sweeps given")
        names = [s.name for s in self.sweeps]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"repeated sweeps: {', '.join(dup)}")
        for s in self.sweeps:
            try:
                CONTROLLERS.spec(s.controller)
            except UnknownNameError as e:
                raise ConfigError(f"sweep {s.name}: {e} (choose sweeps with --sweep)") from None
            if not s.values:
                raise ConfigError(f"sweep {s.name} has no values")
            for v in s.values:
                configure(CONTROLLERS, s.controller, None, self.overrides(s, v))
        unknown = sorted(set(self.settings) - {s.controller for s in self.sweeps})
        if unknown:
            raise ConfigError(f"settings for controllers not swept: {', '.join(unknown)}")
        LOCALIZERS.spec(self.localizer)
        surface_coefficient(self.surface)
        if self.runs < 1:
            raise ConfigError(f"runs must be >= 1, got {self.runs}")
        if not self.duration_s > 0:
            raise ConfigError(f"duration must be > 0, got {self.duration_s}")
        load_world(self.course)

    def run_seed(self, run: int) -> int:
        return self.seed + run


def plan(study: CornerStudy, out: Path) -> list[RunSpec]:
    specs = []
    for sweep in study.sweeps:
        for value in sweep.values:
            setting = f"{sweep.slug}={_value_label(value)}"
            for j in range(study.runs):
                seed = study.run_seed(j)
                pusher = Pusher.sample(seed)
                log = out / "runs" / sweep.slug / _value_label(value) / f"run{j:03d}.mcap"
                specs.append(
                    RunSpec(
                        course=study.course,
                        controller=sweep.controller,
                        localizer=study.localizer,
                        surface=study.surface,
                        seed=seed,
                        duration_s=study.duration_s,
                        controller_overrides=study.overrides(sweep, value),
                        push_n=pusher.forces(),
                        start_offset=(
                            pusher.start_ahead_m,
                            pusher.start_left_m,
                            pusher.start_turn_rad,
                        ),
                        initial_speed_mps=pusher.speed_mps,
                        log_path=str(log) if study.keep_logs else None,
                        labels={
                            "study": "corner",
                            "sweep": sweep.name,
                            "parameter": sweep.field,
                            "value": value,
                            "setting": setting,
                            "run": j,
                            "pusher": asdict(pusher),
                        },
                    )
                )
    return specs


METRIC_COLUMNS = (
    "collisions_front",
    "collisions_side",
    "collisions_rear_wheel",
    "collisions_total",
    "min_clearance_m",
    "final_heading_deg",
    "distance_m",
    "braking_impulse_nms",
    "ate_rmse_m",
    "phantom_area_m2",
    "sim_time_s",
    "wall_time_s",
)
COLUMNS = (
    "study",
    "sweep",
    "controller",
    "parameter",
    "value",
    "run",
    "seed",
    "push_speed_mps",
    "push_left_n",
    "push_right_n",
    "start_pose",
    *METRIC_COLUMNS,
    "pusher",
    "controller_config",
    "localizer",
    "surface",
    "collisions",
    "log",
    "config",
)


def result_row(res: dict[str, Any]) -> dict[str, Any]:
    spec: RunSpec = res["spec"]
    m, cfg, lab = res["metrics"], res["config"], spec.labels
    row: dict[str, Any] = {
        "study": "corner",
        "sweep": lab["sweep"],
        "controller": spec.controller,
        "parameter": lab["parameter"],
        "value": lab["value"],
        "run": lab["run"],
        "seed": spec.seed,
        "push_speed_mps": spec.initial_speed_mps,
        "push_left_n": spec.push_n[0],
        "push_right_n": spec.push_n[1],
        "start_pose": cfg["initial_pose"],
    }
    for k in METRIC_COLUMNS:
        row[k] = m.get(k)
    row.update(
        pusher=lab["pusher"],
        controller_config=cfg["controller_config"],
        localizer=spec.localizer,
        surface=str(spec.surface),
        collisions=[list(c) for c in res["collisions"]],
        log=spec.log_path,
        config=cfg,
    )
    return row


def setting_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (sweep, value): runs, collisions (sums by kind), runs with any collision,
    closest approach (mean and minimum), final heading (mean ± std), braking impulse."""
    groups: dict[tuple[str, Any], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["sweep"], r["value"]), []).append(r)
    out = []
    for (sweep, value), rs in groups.items():
        heading = np.array([r["final_heading_deg"] or 0.0 for r in rs])
        clear = [r["min_clearance_m"] for r in rs if r["min_clearance_m"] is not None]
        out.append(
            {
                "sweep": sweep,
                "value": value,
                "runs": len(rs),
                **{
                    k: int(sum(r[f"collisions_{k}"] for r in rs))
                    for k in ("front", "side", "rear_wheel", "total")
                },
                "runs_with_collision": int(sum(r["collisions_total"] > 0 for r in rs)),
                "clearance_mean_m": float(np.mean(clear)) if clear else math.nan,
                "clearance_min_m": float(np.min(clear)) if clear else math.nan,
                "heading_mean_deg": float(heading.mean()),
                "heading_std_deg": float(heading.std()),
                "braking_nms": tables.mean_of(rs, "braking_impulse_nms"),
            }
        )
    return out


TABLE_HEADERS = (
    "sweep",
    "value",
    "runs",
    "collisions F / S / R",
    "runs with a collision",
    "closest approach m (mean, min)",
    "final heading deg",
    "braking N·m·s",
)


def table_rows(table: Sequence[dict[str, Any]]) -> list[list[str]]:
    return [
        [
            e["sweep"],
            _value_label(e["value"]),
            str(e["runs"]),
            f"{e['front']} / {e['side']} / {e['rear_wheel']}",
            f"{e['runs_with_collision']}",
            f"{e['clearance_mean_m']:.3f}, {e['clearance_min_m']:.3f}",
            f"{e['heading_mean_deg']:.1f} ± {e['heading_std_deg']:.1f}",
            f"{e['braking_nms']:.2f}",
        ]
        for e in table
    ]


def run_corner_study(
    study: CornerStudy,
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
    table = setting_table(rows)
    files["table"] = out / "table.md"
    files["table"].write_text(tables.markdown(TABLE_HEADERS, table_rows(table)) + "\n")
    files.update(_figures(study, out, rows, results))
    files["study"] = write_json(
        out / "study.json",
        {
            "command": "corner-study",
            **asdict(study),
            "engine": engine,
            "runs_total": len(rows),
            "pushers": [asdict(Pusher.sample(study.run_seed(j))) for j in range(study.runs)],
        },
    )
    files["report"] = _report(study, out, table, files)
    return StudyResult(rows, table, files)


def _figures(study: CornerStudy, out: Path, rows, results) -> dict[str, Path]:
    world = load_world(study.course)
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    files: dict[str, Path] = {}
    for sweep in study.sweeps:
        settings = []
        for value in sweep.values:
            runs = [
                {"path": res["path"], "collisions": res["collisions"]}
                for row, res in zip(rows, results, strict=True)
                if row["sweep"] == sweep.name and row["value"] == value
            ]
            settings.append((f"{sweep.field} = {_value_label(value)}", runs))
        title = (
            f"corner: {sweep.describe()}; {study.runs} runs per setting "
            f"(thin), average by arc length (thick)"
        )
        path = fig_dir / f"corner_{sweep.slug}.png"
        files[f"corner_{sweep.slug}"] = figures.corner_sweep(world, settings, title, path)
    return files


def _report(study: CornerStudy, out: Path, table, files) -> Path:
    settings = "; ".join(f"{n}: {v}" for n, v in study.settings.items()) or "none"
    lines = [
        "# Corner study (thesis Figs 6.5–6.8)",
        "",
        f"Course `{study.course}`, surface {study.surface}, localizer {study.localizer}, "
        f"{study.runs} runs per setting of {study.duration_s:g} s, seeds {study.seed}–"
        f"{study.run_seed(study.runs - 1)} (run j is the same pusher in every setting); "
        f"extra settings: {settings}.",
        "",
        "The user pushes straight at a constant force for 0.9–1.2 m/s and does not steer; "
        "paths are the true rear-axle centre. Closest approach: smallest distance from a "
        "corner of the walker's footprint (frame and rear wheels) to a wall. Final heading: "
        "turn from the start heading at the end (+ = left, toward the open side).",
        "",
        "Sweeps:",
        "",
        *[f"- {s.describe()}" for s in study.sweeps],
        "",
        tables.markdown(TABLE_HEADERS, table_rows(table)),
        "",
    ]
    for s in study.sweeps:
        lines += [f"## {s.name}", "", f"![{s.name}](figures/{files[f'corner_{s.slug}'].name})", ""]
    lines.append(
        "Files: `results.db` (tables `runs`, `paths`), `results.csv`, `table.md`, `study.json`"
        + (", trial logs in `runs/`." if study.keep_logs else ".")
    )
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
