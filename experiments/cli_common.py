"""What every `walkerslam` command shares: the consoles, the error rule, size parsing and
the progress bar (experiments.cli and the command modules import it; it imports none of
them).

The error rule: a `hardware.errors.WalkerSlamError` (bad input: a log, a dataset, a
config value, a name, a device) and an `OSError` about a file the user named print one
line `error: …` and exit with code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import functools
import sys
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from hardware.errors import ConfigError, WalkerSlamError


def _width(stream) -> int | None:
    """Rich wraps and truncates at 80 columns when output is not a terminal (a pipe, a
    file); keep tables and lines whole there."""
    return None if stream.isatty() else 200


console = Console(width=_width(sys.stdout))
err_console = Console(stderr=True, width=_width(sys.stderr))


def user_error_message(exc: BaseException) -> str | None:
    """The one line to show for a user's error, None for a bug."""
    if isinstance(exc, WalkerSlamError):
        text = str(exc)
    elif isinstance(exc, OSError) and exc.filename is not None:
        why = exc.strerror or type(exc).__name__
        text = f"{exc.filename}: {why}"
    else:
        return None
    return text.splitlines()[0] if text else type(exc).__name__


def print_error(text: str) -> None:
    err_console.print(f"[bold red]error:[/] {text}", highlight=False, soft_wrap=True)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings (e.g. a recovered log) as one line, without Python's source context."""
    text = str(message).splitlines()[0]
    err_console.print(f"[bold yellow]warning:[/] {text}", highlight=False, soft_wrap=True)


def friendly(fn: Callable) -> Callable:
    """A command under the error rule (module docstring); warnings as one line."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _show_warning
                return fn(*args, **kwargs)
        except Exception as exc:
            msg = user_error_message(exc)
            if msg is None:
                raise
            print_error(msg)
            raise typer.Exit(2) from None

    return wrapper


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' → (W, H), within the Kinect's 640×480."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"image size must look like 160x120, got '{text}'") from None
    if not (8 <= w <= 640 and 6 <= h <= 480):
        raise ConfigError(f"image size {w}x{h} is outside 8x6 .. 640x480")
    return w, h


@contextmanager
def progress_bar(label: str, total: float | None):
    """A bar over a run's message time; `update(t)` moves it, `update.phase(text)` says
    what happens once the messages are done (metrics, figures)."""
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:>6.1f} s"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=total)
        last = [0.0]

        def update(t: float) -> None:
            if t - last[0] >= 0.5:
                last[0] = t
                bar.update(task, completed=t)

        def phase(text: str) -> None:
            bar.update(task, description=f"{label}: {text}", completed=bar.tasks[0].total)

        update.phase = phase  # type: ignore[attr-defined]
        yield update


MitigationOpt = Annotated[
    str | None,
    typer.Option(
        help="encoder-slip mitigations NAME[,NAME...] (walkerslam list mitigations): they "
        "set the localizer's fields they need (before --set) and the map's hygiene"
    ),
]


def parse_mitigations(text: str | None, localizer: str, calibration: Path | None):
    """(names, their combined effect on `localizer`) of --mitigation; one-line errors
    for an unknown name, one that does not apply, or a missing --calibration."""
    from experiments.mitigations import check_calibration, parse, resolve

    names = parse(text)
    mitigated = resolve(names, localizer)
    check_calibration(mitigated, calibration)
    return names, mitigated
