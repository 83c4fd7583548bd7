"""`walkerslam calibrate`: the wheel diameters and track from UMBmark logs
(`experiments.calibrate`). `register(app)` adds it to the CLI; errors follow the CLI's
rule (one line `error: …`, exit 2; a bug keeps its traceback)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from experiments.cli_common import console

_SideOpt = Annotated[
    float | None,
    typer.Option(
        help="side of the taped square [m] (the scale; without it the mean wheel diameter "
        "is kept by the UMBmark method)"
    ),
]
_BaseOpt = Annotated[
    Path | None,
    typer.Option(help="calibration JSON to write the estimate into (default: the first log's)"),
]
_MethodOpt = Annotated[
    str,
    typer.Option(
        help="umbmark (closed form from the laps, no ground truth needed), ground-truth "
        "(least squares against the log's true poses), or auto (ground truth when every "
        "log has it)"
    ),
]


def calibrate(
    logs: Annotated[
        list[Path], typer.Argument(help="UMBmark logs (.mcap): laps of a square, both ways")
    ],
    output: Annotated[
        Path, typer.Option("-o", "--output", help="walker calibration JSON to write")
    ] = Path("calibration.json"),
    side: _SideOpt = None,
    base: _BaseOpt = None,
    method: _MethodOpt = "auto",
) -> None:
    """Estimate the wheel diameters and the track from a UMBmark run (a taped square
    pushed both ways), print the estimate and the laps' return errors before and after,
    and write a calibration file that `--calibration FILE` of the other commands reads."""
    from experiments.calibrate import calibrate as run_calibrate

    res = run_calibrate(logs, output, side_m=side, base=base, method=method)
    console.print(_how(res), highlight=False, soft_wrap=True)
    console.print(_geometry_table(res))
    console.print(
        "return errors, mean of the laps (x along the side, y to the left, in the frame "
        "of the lap's start):",
        highlight=False,
        soft_wrap=True,
    )
    console.print(_errors_table(res))
    console.print(f"wrote {res.path}", highlight=False, soft_wrap=True)


def _how(res) -> str:
    """What the estimate was made from and how, and what the assumed geometry did wrong."""
    from slam.umbmark import systematic_errors

    laps = f"{res.before[1].laps} counter-clockwise and {res.before[-1].laps} clockwise laps"
    if res.umbmark is None:
        how = "least squares against the ground truth"
    else:
        side = f"a {res.side_m:g} m square" if res.side_m else "no --side: mean diameter kept"
        how = f"UMBmark closed form ({side}), iterated {res.umbmark.iterations}×"
    e = systematic_errors(res.assumed, res.estimate, 1.0)
    turn, drift = math.degrees(e.alpha_rad), math.degrees(e.beta_rad)
    short = 100 * (1 - 1 / e.scale)
    return (
        f"{laps}; {how}. With the assumed wheels and track the odometry "
        f"{'over' if turn >= 0 else 'under'}-rotates every 90° turn by {abs(turn):.2f}° "
        f"(track, E_b), turns {abs(drift):.3f}° {'left' if drift >= 0 else 'right'} per metre "
        f"(wheel ratio, E_d) and measures distances {abs(short):.2f} % "
        f"{'short' if short >= 0 else 'long'} (mean diameter)"
    )


def _geometry_table(res) -> Table:
    heads = ("", "left wheel [mm]", "right wheel [mm]", "mean [mm]", "ratio R/L", "track [m]")
    table = Table(*map(escape, heads))
    for name, g in (("assumed", res.assumed), ("estimate", res.estimate)):
        table.add_row(
            name,
            f"{1e3 * g.left_diameter_m:.2f}",
            f"{1e3 * g.right_diameter_m:.2f}",
            f"{1e3 * g.mean_diameter_m:.2f}",
            f"{g.diameter_ratio:.5f}",
            f"{g.track_m:.4f}",
        )
    return table


def _errors_table(res) -> Table:
    heads = ("direction", "laps", "before x ± sd, y [m]", "heading [°]", "after x ± sd, y [m]")
    table = Table(*map(escape, (*heads, "heading [°]")))
    for d, name in ((1, "counter-clockwise"), (-1, "clockwise")):
        cells = [name, str(res.before[d].laps)]
        for e in (res.before[d], res.after[d]):
            x, y, heading = e.mean
            cells += [f"{x:+.3f} ± {e.std[0]:.3f}, {y:+.3f}", f"{math.degrees(heading):+.2f}"]
        table.add_row(*cells)
    return table


def register(app: typer.Typer) -> None:
    """Add `calibrate` to `app` (the `walkerslam` CLI)."""
    from experiments.cli_common import friendly

    app.command()(friendly(calibrate))
