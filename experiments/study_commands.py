"""`walkerslam course-study`, `corner-study` and `slip-study`: the simulated user studies
(`experiments.studies`). `register(app)` adds them to the CLI; errors follow the CLI's
rule (one line `error: …`, exit 2)."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich import box
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from experiments.cli_common import console, err_console, friendly
from hardware.errors import ConfigError

EngineOpt = Annotated[str, typer.Option(help="local (a process per core) or ray (a Ray cluster)")]
AddressOpt = Annotated[
    str | None,
    typer.Option(help="ray: address of an existing cluster (default: start a local Ray)"),
]
WorkersOpt = Annotated[
    int | None,
    typer.Option(help="parallel runs (local processes / local Ray CPUs) [default: all cores]"),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="NAME.FIELD=VALUE: a field of a controller's or localizer's config, e.g. "
        "open-loop.d_max_m=1.75 (repeatable)",
    ),
]
LogsOpt = Annotated[
    bool, typer.Option(help="keep every run's trial log under OUT/runs/ (replayable)")
]


def _split(text: str) -> tuple[str, ...]:
    return tuple(dict.fromkeys(v.strip() for v in text.split(",") if v.strip()))


@contextmanager
def runs_bar(label: str):
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("runs"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update


def print_files(files: dict[str, Path]) -> None:
    shown = [p for k, p in files.items() if not k.startswith(("paths_", "corner_"))]
    console.print("files: " + ", ".join(str(p) for p in shown), highlight=False)


def course_study(
    controllers: Annotated[
        str, typer.Option(help="controllers, separated by commas")
    ] = "none,open-loop",
    localizers: Annotated[
        str, typer.Option(help="localizers the controllers use, separated by commas")
    ] = "dead-reckoning",
    surface: Annotated[
        str, typer.Option(help="surfaces (clean, dusty or a slip coefficient), by commas")
    ] = "dusty",
    trials: Annotated[int, typer.Option(help="simulated users per cell")] = 10,
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/course-study"),
    engine: EngineOpt = "local",
    address: AddressOpt = None,
    workers: WorkersOpt = None,
    duration: Annotated[float, typer.Option(help="longest simulated trial [s]")] = 300.0,
    seed: Annotated[int, typer.Option(help="user i has seed SEED + i")] = 0,
    course: Annotated[
        str, typer.Option(help="built-in course name or a course JSON file")
    ] = "thesis-course",
    set_: SetOpt = None,
    logs: LogsOpt = True,
) -> None:
    """Thesis Table 6.3 with simulated users: N users (seeded user profiles, the same
    users in every cell) walk the course for every controller × localizer × surface;
    writes the collision table with the change against `none` (95 % CI), path
    figures, results.db, results.csv and report.md.

    (Long for its option list: typer reads the options from this signature.)"""
    from control.base import CONTROLLERS
    from experiments.config import parse_sets
    from experiments.studies.course import CourseStudy, run_course_study
    from experiments.studies.engine import check
    from experiments.studies.tables import collision_rows
    from slam.base import LOCALIZERS

    ctl, locs = _split(controllers), _split(localizers)
    registries = {**{c: CONTROLLERS for c in ctl}, **{n: LOCALIZERS for n in locs}}
    for c in ctl:
        CONTROLLERS.spec(c)
    for n in locs:
        LOCALIZERS.spec(n)
    study = CourseStudy(
        controllers=ctl,
        localizers=locs,
        surfaces=_split(surface),
        trials=trials,
        seed=seed,
        duration_s=duration,
        course=course,
        settings=parse_sets(set_ or [], registries, registries),
        keep_logs=logs,
    )
    study.validate()
    check(engine, workers, address)
    with runs_bar(f"course study ({engine})") as update:
        res = run_course_study(
            study, out, engine=engine, workers=workers, address=address, progress=update
        )
    rows = collision_rows(res.table, study.baseline)
    for group in dict.fromkeys(tuple(r[:2]) for r in rows):
        table = Table(
            title=f"{group[0]} · {group[1]}, {study.trials} user"
            f"{'s' if study.trials != 1 else ''}: collisions per trial "
            "(mean) front / side / rear-wheel / total, totals, change of the total",
            title_justify="left",
            box=box.SIMPLE_HEAD,
        )
        for h in ("controller", "F", "S", "R", "all", "Σ F/S/R"):
            table.add_column(h, no_wrap=True)
        table.add_column(f"vs {study.baseline} (95% CI)", no_wrap=True)
        for r in rows:
            if tuple(r[:2]) == group:
                table.add_row(r[2], *r[4:10])
        console.print(table)
    print_files(res.files)


def corner_study(
    sweep: Annotated[
        list[str] | None,
        typer.Option(
            help="CONTROLLER.FIELD=V1,V2,... to sweep (repeatable) [default: the thesis "
            "sweeps closed-loop.D, closed-loop.D_phi, closed-loop.d_max_m, "
            "open-loop.d_max_m]"
        ),
    ] = None,
    runs: Annotated[int, typer.Option(help="runs per setting")] = 5,
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/corner-study"),
    engine: EngineOpt = "local",
    address: AddressOpt = None,
    workers: WorkersOpt = None,
    duration: Annotated[float, typer.Option(help="simulated time per run [s]")] = 7.0,
    seed: Annotated[int, typer.Option(help="run j has seed SEED + j")] = 0,
    localizer: Annotated[
        str, typer.Option(help="localizer the controller uses")
    ] = "dead-reckoning",
    surface: Annotated[str, typer.Option(help="clean, dusty or a slip coefficient")] = "dusty",
    set_: SetOpt = None,
    logs: LogsOpt = True,
) -> None:
    """Thesis Figs 6.5–6.8: sweep controller parameters on the `corner` course, the
    user pushing straight at 0.9–1.2 m/s; one figure per sweep with the individual
    and averaged paths, a table per setting, results.db, results.csv, report.md.

    (Long for its option list: typer reads the options from this signature.)"""
    from control.base import CONTROLLERS
    from experiments.config import parse_sets
    from experiments.studies.corner import (
        DEFAULT_SWEEPS,
        CornerStudy,
        parse_sweep,
        run_corner_study,
        table_rows,
    )
    from experiments.studies.engine import check

    sweeps = tuple(parse_sweep(s) for s in sweep) if sweep else DEFAULT_SWEEPS
    names = list(dict.fromkeys(s.controller for s in sweeps))
    for n in names:
        try:
            CONTROLLERS.spec(n)
        except ValueError as e:
            raise ConfigError(f"sweep of {n}: {e} (choose sweeps with --sweep)") from None
    study = CornerStudy(
        sweeps=sweeps,
        runs=runs,
        seed=seed,
        duration_s=duration,
        localizer=localizer,
        surface=surface,
        settings=parse_sets(set_ or [], {n: CONTROLLERS for n in names}, names),
        keep_logs=logs,
    )
    study.validate()
    check(engine, workers, address)
    with runs_bar(f"corner study ({engine})") as update:
        res = run_corner_study(
            study, out, engine=engine, workers=workers, address=address, progress=update
        )
    rows = table_rows(res.table)
    for s in study.sweeps:
        table = Table(
            title=f"{s.describe()}, {study.runs} runs per value",
            title_justify="left",
            box=box.SIMPLE_HEAD,
        )
        for h in ("value", "collisions F/S/R", "runs hit", "closest m (mean, min)"):
            table.add_column(h, no_wrap=True)
        for h in ("heading °", "N·m·s"):
            table.add_column(h, no_wrap=True)
        for r in rows:
            if r[0] == s.name:
                table.add_row(r[1], *r[3:])
        console.print(table)
    print_files(res.files)


def slip_study(
    surface: Annotated[
        str, typer.Option(help="surfaces: clean, dusty or slip coefficients, by commas")
    ] = "clean,dusty,0.2",
    localizers: Annotated[
        str, typer.Option(help="localizers, separated by commas")
    ] = "dead-reckoning",
    mitigations: Annotated[
        str,
        typer.Option(
            help="mitigation sets, separated by commas; a set joins names with + (e.g. "
            "none,gyro,gyro+map-hygiene); 'none' is the baseline of the ranking"
        ),
    ] = "none,gyro,map-hygiene",
    controllers: Annotated[
        str, typer.Option(help="controllers, separated by commas")
    ] = "open-loop",
    trials: Annotated[int, typer.Option(help="simulated users per cell")] = 10,
    out: Annotated[Path, typer.Option(help="output folder")] = Path("out/slip-study"),
    engine: EngineOpt = "local",
    address: AddressOpt = None,
    workers: WorkersOpt = None,
    duration: Annotated[float, typer.Option(help="longest simulated trial [s]")] = 300.0,
    seed: Annotated[int, typer.Option(help="user i has seed SEED + i")] = 0,
    course: Annotated[
        str, typer.Option(help="built-in course name or a course JSON file")
    ] = "thesis-course",
    calibration: Annotated[
        Path | None,
        typer.Option(help="the calibration file of the 'calibration' mitigation"),
    ] = None,
    set_: SetOpt = None,
    logs: LogsOpt = True,
) -> None:
    """Encoder-slip mitigations against slip severity: N paired users per cell surface ×
    localizer × mitigation set × controller; per run collisions, ATE, heading error
    while braking, phantom area, obstacle drag, over-steer, braking, runtime
    (results.db); figures of each metric against slip with 95 % bands; report.md ranks
    the mitigations (paired differences against none, 95 % intervals).

    (Long for its option list: typer reads the options from this signature.)"""
    from control.base import CONTROLLERS
    from experiments.config import parse_sets
    from experiments.mitigations import parse
    from experiments.studies.engine import check
    from experiments.studies.slip_report import ranking_table
    from experiments.studies.slip_study import SlipStudy, run_slip_study
    from slam.base import LOCALIZERS

    ctl, locs = _split(controllers), _split(localizers)
    registries = {**{c: CONTROLLERS for c in ctl}, **{n: LOCALIZERS for n in locs}}
    for c in ctl:
        CONTROLLERS.spec(c)
    for n in locs:
        LOCALIZERS.spec(n)
    study = SlipStudy(
        surfaces=_split(surface),
        localizers=locs,
        mitigations=tuple(dict.fromkeys(parse(m) for m in _split(mitigations))),
        controllers=ctl,
        trials=trials,
        seed=seed,
        duration_s=duration,
        course=course,
        settings=parse_sets(set_ or [], registries, registries),
        keep_logs=logs,
        calibration=str(calibration) if calibration else None,
    )
    study.validate()
    check(engine, workers, address)
    with runs_bar(f"slip study ({engine})") as update:
        res = run_slip_study(
            study, out, engine=engine, workers=workers, address=address, progress=update
        )
    if res.table:
        console.print(ranking_table(res.table), highlight=False, soft_wrap=True, markup=False)
    print_files({k: p for k, p in res.files.items() if not k.startswith("figure_")})


def register(app: typer.Typer) -> None:
    """Add the study commands to `app` (the `walkerslam` CLI)."""
    app.command(name="course-study")(friendly(course_study))
    app.command(name="corner-study")(friendly(corner_study))
    app.command(name="slip-study")(friendly(slip_study))
