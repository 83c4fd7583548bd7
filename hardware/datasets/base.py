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

The steps the importers share are here too: `require_folder`, `sorted_by_time`, the
stream factories (`velocity_stream`, `range_bearing_stream`, `groundtruth_stream`) put
in the tie order above by `tie_ordered_streams`, and the metadata's `config_metadata`
and `span_and_counts`.

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
from hardware.messages import GroundTruthPose, Message, RangeBearing, VelocityOdometry, merge
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


def coerce_option(options: Any, name: str, convert: Callable[..., Any], **kwargs: Any) -> None:
    """Replace field `name` of a frozen options dataclass by `convert(name, value, **kwargs)`
    (in `__post_init__`, e.g. `coerce_option(self, "robot", as_int)`)."""
    object.__setattr__(options, name, convert(name, getattr(options, name), **kwargs))


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


def interpolate_poses(t: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Poses (N, 3) at the times `at` from a time-sorted pose table (x, y linear, θ linear
    in its unwrapped form and left unwrapped); clamps at the table's ends."""
    th = np.unwrap(poses[:, 2])
    return np.column_stack(
        [np.interp(at, t, poses[:, 0]), np.interp(at, t, poses[:, 1]), np.interp(at, t, th)]
    )


def interpolate_pose(t: np.ndarray, poses: np.ndarray, at: float) -> tuple[float, float, float]:
    """Pose at time `at` from a time-sorted pose table (linear, θ unwrapped); clamps."""
    x, y, th = interpolate_poses(t, poses, np.array([at]))[0].tolist()
    return (x, y, math.remainder(th, 2.0 * math.pi))


# ---------------------------------------------------------------------------------------
# the steps every importer shares: its folder, time order, streams, metadata


def require_folder(path: str | Path, format: str) -> Path:
    """`path` as a dataset folder; a DatasetError when it is missing or not a folder."""
    folder = Path(path)
    if not folder.is_dir():
        what = "missing folder" if not folder.exists() else "not a folder"
        raise DatasetError(f"{folder}: {what} ({format} takes the dataset folder)")
    return folder


def time_order(t: np.ndarray, name: str, notes: list[str]) -> np.ndarray | None:
    """The stable order that sorts the times `t`, or None when they never step back; a
    sort is noted in `notes` (metadata "dataset" "notes") under `name`."""
    order, back = sorted_stream_order(t)
    if order is not None:
        notes.append(f"{name}: {back} timestamps step back; rows stably sorted by time")
    return order


def sorted_by_time(data: np.ndarray, name: str, notes: list[str], col: int = 0) -> np.ndarray:
    """The rows of `data` stably sorted by their time column `col` (`data` itself when in
    order; see `time_order`)."""
    order = time_order(data[:, col], name, notes)
    return data if order is None else data[order]


def velocity_stream(t: np.ndarray, v: np.ndarray, w: np.ndarray) -> StreamFactory:
    """VelocityOdometry messages from columns of times, speeds and yaw rates."""

    def gen() -> Iterator[VelocityOdometry]:
        for ti, vi, wi in zip(t.tolist(), v.tolist(), w.tolist(), strict=True):
            yield VelocityOdometry(ti, vi, wi)

    return gen


def range_bearing_stream(
    t: np.ndarray, ids: np.ndarray, r: np.ndarray, b: np.ndarray
) -> StreamFactory:
    """RangeBearing messages from columns of times, landmark IDs, ranges and bearings."""

    def gen() -> Iterator[RangeBearing]:
        for ti, i, ri, bi in zip(t.tolist(), ids.tolist(), r.tolist(), b.tolist(), strict=True):
            yield RangeBearing(ti, i, ri, bi)

    return gen


def groundtruth_stream(t: np.ndarray, poses: np.ndarray) -> StreamFactory:
    """GroundTruthPose messages from a time-sorted table (θ wrapped to (−π, π])."""

    def gen() -> Iterator[GroundTruthPose]:
        for ti, (x, y, th) in zip(t.tolist(), poses.tolist(), strict=True):
            yield GroundTruthPose(ti, x, y, wrap1(th))

    return gen


def tie_ordered_streams(
    motion: tuple[type, StreamFactory],
    observations: tuple[type, StreamFactory],
    truth: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[type, StreamFactory]:
    """`Dataset.streams` in the order `merge` keeps at equal timestamps (module
    docstring): the motion stream, the ground truth (times, poses) if there is any, then
    the observations."""
    streams = dict([motion])
    if truth is not None:
        streams[GroundTruthPose] = groundtruth_stream(*truth)
    streams.update([observations])
    return streams


def config_metadata(
    format: str,
    path: Path,
    options: Any,
    initial_pose: tuple[float, float, float],
    **extra: Any,
) -> dict[str, Any]:
    """Metadata "config": the format, the resolved path, every option, the initial pose,
    then the format's `extra` entries."""
    return {
        "format": format,
        "path": str(path.resolve()),
        **options_dict(options),
        "initial_pose": list(initial_pose),
        **extra,
    }


def span_and_counts(counts: dict[str, int], *times: np.ndarray) -> dict[str, Any]:
    """Metadata "dataset" "t_first" and "t_last" (over every time in `times`, empty arrays
    ignored) and "counts" (messages per type name)."""
    present = [t for t in times if len(t)]
    return {
        "t_first": float(min(t.min() for t in present)),
        "t_last": float(max(t.max() for t in present)),
        "counts": counts,
    }


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
