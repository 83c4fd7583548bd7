"""Reading dataset text files: plain or gzip, located by name, parsed with line numbers.

Gzip is recognised by its magic bytes, so `X.dat` and `X.dat.gz` both work whatever
their content. Every failure is a `DatasetError` whose one-line message names the file
(and the line, for malformed content).
"""

from __future__ import annotations

import gzip
import io
import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hardware.datasets.base import DatasetError

GZIP_MAGIC = b"\x1f\x8b"


def find_file(folder: Path, name: str) -> Path:
    """`folder/name` or `folder/name.gz`, whichever exists; else a DatasetError."""
    for candidate in (folder / name, folder / (name + ".gz")):
        if candidate.is_file():
            return candidate
    raise DatasetError(f"{folder / name}: missing file (also looked for {name}.gz)")


def find_optional(folder: Path, name: str) -> Path | None:
    try:
        return find_file(folder, name)
    except DatasetError:
        return None


class FolderFiles:
    """The files of a dataset folder, found by name (`find_file`) and remembered as found:
    `found` {name: path} is what metadata "dataset" "files" records."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.found: dict[str, str] = {}

    def find(self, name: str) -> Path:
        path = find_file(self.folder, name)
        self.found[name] = str(path)
        return path

    def has(self, name: str) -> bool:
        return find_optional(self.folder, name) is not None


def _text(raw: io.BufferedReader) -> io.TextIOWrapper:
    """The text of an open binary file, gunzipped when its first bytes say gzip."""
    magic = raw.read(2)
    raw.seek(0)
    stream = gzip.GzipFile(fileobj=raw) if magic == GZIP_MAGIC else raw
    return io.TextIOWrapper(stream, encoding="utf-8-sig", newline=None)


def iter_lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number from 1, line without its end) of a plain or gzipped text file."""
    try:
        raw = path.open("rb")
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing file") from None
    except IsADirectoryError:
        raise DatasetError(f"{path}: is a folder, expected a file") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
    lineno = 0
    with raw:
        text = _text(raw)
        try:
            for lineno, line in enumerate(text, 1):
                yield lineno, line.rstrip("\n")
        except (EOFError, gzip.BadGzipFile, zlib.error) as e:
            raise DatasetError(
                f"{path}: truncated or corrupt gzip after line {lineno} ({e})"
            ) from None
        except UnicodeDecodeError as e:
            # decoding runs ahead of the lines, so the position is approximate
            raise DatasetError(
                f"{path}: not a text file ({e.reason} after line {lineno})"
            ) from None


def read_lines(path: Path) -> list[str]:
    """The lines of a plain or gzipped text file without their ends: iter_lines' lines,
    read in one piece. A file iter_lines would fail on is read by it, for its error."""
    try:
        with path.open("rb") as raw:
            text = _text(raw).read()
    except (OSError, EOFError, zlib.error, UnicodeDecodeError):  # BadGzipFile is an OSError
        return [line for _, line in iter_lines(path)]  # raises the one-line error
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()  # the end of the last line, or an empty file
    return lines


@dataclass(frozen=True, eq=False)
class Table:
    """A numeric table read from `path`: data (rows × columns) and each row's line number."""

    path: Path
    data: np.ndarray
    lines: np.ndarray

    def __len__(self) -> int:
        return len(self.data)

    def integer_column(self, col: int, name: str) -> np.ndarray:
        """Column `col` as int64; a DatasetError naming the line if a value is not integral."""
        v = self.data[:, col]
        bad = np.nonzero(v != np.round(v))[0]
        if len(bad):
            i = bad[0]
            raise DatasetError(
                f"{self.path}: line {self.lines[i]}: {name} must be an integer, got {v[i]!r}"
            )
        return v.astype(np.int64)


def read_table(
    path: Path,
    columns: int,
    *,
    delimiter: str | None = None,
    skip_header: int = 0,
    comments: tuple[str, ...] = ("#",),
) -> Table:
    """Numeric table (rows × columns, float64) of a text file, with line numbers.

    Blank lines and lines starting with one of `comments` ('#') are skipped;
    `skip_header` further lines at the top of the file are skipped whatever they hold.
    Fields are separated by whitespace (delimiter None) or by `delimiter` (surrounding
    spaces ignored, trailing empty fields dropped). Every row must have exactly
    `columns` finite numbers.

    The data lines are parsed in one compiled pass (numpy's loadtxt, which reads a
    number as Python's float does: the same bits); only when that pass fails are they
    parsed line by line, to name the first bad line.
    """
    numbered = [
        (lineno, s)
        for lineno, line in enumerate(read_lines(path)[skip_header:], skip_header + 1)
        if (s := line.strip()) and not s.startswith(comments)
    ]
    if not numbered:
        raise DatasetError(f"{path}: no data rows")
    linenos = np.array([n for n, _ in numbered], dtype=np.int64)
    data = _parse_block([s for _, s in numbered], columns, delimiter)
    if data is None:
        data = np.array(
            [parse_floats(path, n, _fields(path, n, s, columns, delimiter)) for n, s in numbered],
            dtype=np.float64,
        )
    return Table(path, data, linenos)


def _parse_block(lines: list[str], columns: int, delimiter: str | None) -> np.ndarray | None:
    """The lines as a (rows × columns) array of finite numbers, or None if any line is
    not `columns` numbers (the caller then finds which)."""
    try:
        data = np.loadtxt(lines, dtype=np.float64, delimiter=delimiter, comments=None, ndmin=2)
    except ValueError:
        return None
    if data.shape != (len(lines), columns) or not np.isfinite(data).all():
        return None
    return data


def _fields(path: Path, lineno: int, s: str, columns: int, delimiter: str | None) -> list[str]:
    """The fields of one stripped data line; a DatasetError if they are not `columns`."""
    if delimiter is None:
        parts = s.split()
    else:
        parts = [p.strip() for p in s.split(delimiter)]
        while parts and parts[-1] == "":
            parts.pop()
    if len(parts) != columns:
        raise DatasetError(f"{path}: line {lineno}: expected {columns} columns, got {len(parts)}")
    return parts


def parse_floats(path: Path, lineno: int, parts: list[str]) -> list[float]:
    """Floats of `parts`; a DatasetError naming the line if one is not a finite number."""
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        bad = next(p for p in parts if not _is_float(p))
        raise DatasetError(f"{path}: line {lineno}: not a number: {bad!r}") from None
    for p, v in zip(parts, vals, strict=True):
        if not math.isfinite(v):
            raise DatasetError(f"{path}: line {lineno}: not a finite number: {p!r}")
    return vals


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
