"""Datasets as message sources: the `Dataset` type, the format registry and MCAP import.

A public dataset opens as a source like any other (a serial board, a trial log, the
simulator): `open_dataset(format, path, **options)` parses its files, checks them and
returns a `Dataset` whose `messages()` are `hardware.messages` in timestamp order (the
dataset's streams merged by `hardware.messages.merge`, a heap merge). At equal
timestamps the motion stream comes first, then ground truth, then observations, so a
localizer has integrated the motion up to t before it sees an observation taken at t.

Every dataset carries

    name          a short name, e.g. "mrclam_dataset7/robot1"
    calibration   a WalkerCalibration (the walker's defaults; a format sets what its
                  robot documents, e.g. the wheel track)
    metadata      {name: dict}, strict JSON, written to a trial log as its metadata
                  records; always "config" = {"format", "path", every option,
                  "initial_pose": [x, y, θ]} and "dataset" (counts, time base, notes);
                  per format "landmarks", "groundtruth", "skipped", "relations", "gps"
    arrays        format-specific numpy arrays that have no message type (documented
                  in each format module), e.g. Victoria Park's tree diameters

`import_to_log(dataset, out)` writes messages, calibration and metadata to an MCAP trial
log (`hardware.log.LogWriter`); `import_dataset(format, path, out, **options)` does both.

Bad input raises `DatasetError` (a ValueError) with one line naming the file and what is
wrong; an unknown format raises `hardware.registry.UnknownNameError` listing the valid
ones. Files may be plain text or gzip (detected from the content, not the name).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.errors import DatasetError
from hardware.geometry import wrap1
from hardware.messages import GroundTruthPose, Message, merge
from hardware.registry import Registry, UnknownNameError

__all__ = [
    "FORMATS",
    "Dataset",
    "DatasetError",
    "ImportSummary",
    "UnknownNameError",
    "available_formats",
    "import_dataset",
    "import_to_log",
    "open_dataset",
]


StreamFactory = Callable[[], Iterable[Message]]


@dataclass(eq=False)
class Dataset:
    """An opened dataset: a time-ordered message source with calibration and metadata
    (`hardware.source.Source`).

    `streams` maps each message type to a factory of that stream in time order (each
    call starts it afresh, so `messages()` can be iterated any number of times).
    """

    name: str
    calibration: WalkerCalibration
    metadata: dict[str, dict[str, Any]]
    streams: dict[type, StreamFactory]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def messages(self, types: Iterable[type] | None = None) -> Iterator[Message]:
        """All messages (or those of `types` only) merged in timestamp order."""
        wanted = None if types is None else set(types)
        sources = [f() for t, f in self.streams.items() if wanted is None or t in wanted]
        return merge(*sources)

    def close(self) -> None:
        """Nothing to release: the streams re-read the files on every `messages()`."""

    @property
    def initial_pose(self) -> tuple[float, float, float]:
        x, y, th = self.metadata["config"]["initial_pose"]
        return (float(x), float(y), float(th))

    def counts(self) -> dict[str, int]:
        """Messages per type name (from the metadata, without iterating)."""
        return dict(self.metadata["dataset"]["counts"])

    def __repr__(self) -> str:
        fmt = self.metadata.get("config", {}).get("format", "?")
        return f"Dataset({fmt} {self.name!r}, {self.counts()})"


# Members: the entry points of group "walker_slam.dataset_formats" (pyproject.toml).
FORMATS: Registry[Dataset] = Registry("dataset format", "walker_slam.dataset_formats")


def available_formats() -> list[str]:
    return FORMATS.names()


def open_dataset(format: str, path: str | Path, **options: Any) -> Dataset:
    """Open `path` as a dataset of `format` (see `available_formats()`).

    options are the fields of the format's options dataclass (e.g. robot=1 for mrclam);
    an unknown option is a DatasetError listing the valid ones.
    """
    spec = FORMATS.spec(format)
    valid = [f.name for f in fields(spec.config_type)]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise DatasetError(
            f"unknown option {', '.join(repr(u) for u in unknown)} for {format}; "
            f"valid: {', '.join(valid)}"
        )
    try:
        config = spec.config_type(**options)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{format}: {e}") from None
    return FORMATS.create(format, Path(path), config=config)


def options_dict(config: Any) -> dict[str, Any]:
    """The options dataclass as JSON values (paths as strings)."""
    out = {}
    for k, v in asdict(config).items():
        out[k] = str(v) if isinstance(v, Path) else v
    return out


def check_choice(name: str, value: str, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise ValueError(f"{name} must be one of {', '.join(valid)}; got {value!r}")


def as_int(name: str, value: Any) -> int:
    """An int option given as int or int-like string (e.g. from a command line)."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if isinstance(value, int):
        return value
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an integer, got {value!r}") from None
    if not f.is_integer():
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(f)


def as_float(name: str, value: Any, *, allow_none: bool = False) -> float | None:
    if value is None and allow_none:
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return f


def interpolate_pose(t: np.ndarray, poses: np.ndarray, at: float) -> tuple[float, float, float]:
    """Pose at time `at` from a time-sorted pose table (linear, θ unwrapped); clamps."""
    th = np.unwrap(poses[:, 2])
    x = float(np.interp(at, t, poses[:, 0]))
    y = float(np.interp(at, t, poses[:, 1]))
    return (x, y, math.remainder(float(np.interp(at, t, th)), 2.0 * math.pi))


def groundtruth_stream(t: np.ndarray, poses: np.ndarray) -> StreamFactory:
    """GroundTruthPose messages from a time-sorted table (θ wrapped to (−π, π])."""

    def gen() -> Iterator[GroundTruthPose]:
        for ti, (x, y, th) in zip(t.tolist(), poses.tolist(), strict=True):
            yield GroundTruthPose(ti, x, y, wrap1(th))

    return gen


@dataclass(frozen=True)
class ImportSummary:
    """What `import_to_log` wrote."""

    path: Path
    name: str
    messages: int
    counts: dict[str, int]
    t_first: float
    t_last: float

    @property
    def duration_s(self) -> float:
        return self.t_last - self.t_first if self.messages else 0.0

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["path"] = str(self.path)
        d["duration_s"] = self.duration_s
        return d


def import_to_log(
    dataset: Dataset,
    out_path: str | Path,
    *,
    progress: Callable[[float], None] | None = None,
) -> ImportSummary:
    """Write the dataset's messages, calibration and metadata to an MCAP trial log."""
    from hardware.log import LogWriter

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    counts: dict[str, int] = {}
    n = 0
    t_first = t_last = math.nan
    with LogWriter(out_path, dataset.calibration, metadata=dataset.metadata) as log:
        for msg in dataset.messages():
            log.write(msg)
            name = type(msg).__name__
            counts[name] = counts.get(name, 0) + 1
            if n == 0:
                t_first = msg.t
            t_last = msg.t
            n += 1
            if progress is not None and n % 10000 == 0:
                progress(msg.t)
    return ImportSummary(out_path, dataset.name, n, counts, t_first, t_last)


def import_dataset(
    format: str,
    path: str | Path,
    out: str | Path,
    *,
    progress: Callable[[float], None] | None = None,
    **options: Any,
) -> ImportSummary:
    """`open_dataset(format, path, **options)` then `import_to_log` into `out`."""
    return import_to_log(open_dataset(format, path, **options), out, progress=progress)


def sorted_stream_order(t: np.ndarray) -> tuple[np.ndarray | None, int]:
    """(stable sort order or None when already non-decreasing, number of back-steps)."""
    if len(t) < 2:
        return None, 0
    back = int(np.count_nonzero(np.diff(t) < 0))
    if back == 0:
        return None, 0
    return np.argsort(t, kind="stable"), back
