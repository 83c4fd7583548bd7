"""The replayer: a trial log opened as a message source, its damage reported."""

from __future__ import annotations

import heapq
import io
import itertools
import os
import struct
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from hardware.calibration import WalkerCalibration
from hardware.errors import LogError
from hardware.log.codec import READERS, Companions, SchemaReader, Skip
from hardware.log.records import Record, block_records
from hardware.log.scan import Block, Contents, Damage, scan
from hardware.messages import Message


class LogRecoveryWarning(UserWarning):
    """A truncated or damaged log was read past its damage: what was lost and kept."""


class UnsupportedChannelWarning(UserWarning):
    """A channel (or its messages) that the replayer cannot turn into messages is skipped."""


@dataclass(frozen=True)
class LostSpan:
    """Bytes [start, end) of a log that could not be read, and what they held."""

    start: int
    end: int
    what: str  # "truncated", "corrupt chunk record", "unreadable bytes", ...
    #: (first, last) log time [s] of the lost chunks, from the summary's chunk index;
    #: None when the summary says no chunk was lost, or when there is no summary
    log_time: tuple[float, float] | None
    #: without a summary: where the intact chunks before the span end and those after it
    #: begin, in log time (None: there is none); a recorder writes its chunks in time
    #: order, so its lost messages lie between the two
    between: tuple[float | None, float | None] | None
    chunks: int | None  # chunks lost, when the summary says
    names: tuple[str, ...] = ()  # metadata and attachments lost, when the summary says

    def describe(self) -> str:
        """One clause for the recovery warning."""
        if self.what == "truncated":
            return f"truncated at byte {self.start} (writer killed or still writing?)"
        text = (
            f"{self.what} at byte {self.start}: skipped bytes {self.start}-{self.end} "
            f"({self.end - self.start} bytes)"
        )
        if self.log_time is not None:
            n = self.chunks or 0
            t0, t1 = self.log_time
            text += f", lost log time {t0:.3f}-{t1:.3f} s ({n} chunk{'s' if n != 1 else ''})"
        elif self.chunks == 0:
            text += ", no chunk lost"
        elif self.between is not None:  # in file order; a recorder's chunks are in time order
            t0, t1 = self.between
            if t0 is None:
                text += f", lost what came before the intact chunk at log time {t1:.3f} s"
            elif t1 is None:
                text += f", lost what came after the intact chunk ending at log time {t0:.3f} s"
            else:
                text += (
                    ", lost what lay between the intact chunks either side "
                    f"(log time {t0:.3f} and {t1:.3f} s)"
                )
        return text + "".join(f", lost {name}" for name in self.names)


def _lost_span(damage: Damage, contents: Contents) -> LostSpan:
    """What a damaged span held: from the summary's indexes when the log has an intact
    summary, else bounded by the blocks read either side of it."""
    inside = range(damage.start, damage.end)
    summary = contents.summary
    if summary is not None:
        chunks = [c for c in summary.chunks if c.chunk_start_offset in inside]
        names = tuple(
            [f"metadata {m.name!r}" for m in summary.metadata if m.offset in inside]
            + [f"attachment {a.name!r}" for a in summary.attachments if a.offset in inside]
        )
        times = None
        if chunks:
            first = min(c.message_start_time for c in chunks)
            times = (first / 1e9, max(c.message_end_time for c in chunks) / 1e9)
        return LostSpan(damage.start, damage.end, damage.what, times, None, len(chunks), names)
    before = [b.end_ns / 1e9 for b in contents.blocks if b.offset < damage.start]
    after = [b.start_ns / 1e9 for b in contents.blocks if b.offset >= damage.end]
    between = (max(before, default=None), min(after, default=None))
    return LostSpan(
        damage.start, damage.end, damage.what, None, between if before or after else None, None
    )


@dataclass
class _Role:
    main_topic: str
    reader: SchemaReader


class TrialLog:
    """A trial log opened for replay: calibration, metadata, attachments and messages; a
    message source (`hardware.source.Source`).

    Opening scans the whole file once (without needing its summary), so problems are
    reported here: `LogError` for files that cannot be used, `LogRecoveryWarning` for a
    truncated or damaged file (read past the damage, see `lost`),
    `UnsupportedChannelWarning` for channels it skips.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        with self._open() as f:
            contents = scan(f, self.path)
        self.metadata: dict[str, dict[str, Any]] = dict(contents.metadata)
        self.attachments: dict[str, bytes] = contents.attachments
        #: False: truncated or damaged (read past the damage), or not closed by its writer
        self.complete = contents.ended and not contents.damage
        #: what could not be read, in file order
        self.lost = [_lost_span(d, contents) for d in contents.damage]
        self._blocks: list[Block] = contents.blocks
        self._channels = contents.channels
        raw_cal = self.metadata.pop("calibration", None)
        if raw_cal is None:
            self._fail(self._no_calibration())
        try:
            self.calibration = WalkerCalibration.from_dict(raw_cal)
        except (TypeError, ValueError) as e:
            self._fail(f"invalid calibration record: {e}")
        self._roles: dict[int, _Role] = {}
        #: readable topics -> message type
        self.topics: dict[str, type] = {}
        self._classify(contents)
        counts = [
            contents.counts[c]
            for c, r in self._roles.items()
            if r.reader.build and c in contents.counts
        ]
        #: number of messages (companions not counted)
        self.message_count = sum(c[0] for c in counts)
        #: per readable topic: (messages, first log time [s], last log time [s])
        self.topic_counts: dict[str, tuple[int, float, float]] = {
            r.main_topic: (n, t0 / 1e9, t1 / 1e9)
            for c, r in self._roles.items()
            if r.reader.build and c in contents.counts
            for n, t0, t1 in [contents.counts[c]]
        }
        #: (first, last) log time [s], None if there are no messages
        self.time_range = (
            (min(c[1] for c in counts) / 1e9, max(c[2] for c in counts) / 1e9) if counts else None
        )
        if self.lost:
            self._report(contents)

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[Message]:
        """Messages on `topics` (default all readable ones) in log-time order."""
        wanted = None if topics is None else set(topics)
        channels = {c for c, r in self._roles.items() if wanted is None or r.main_topic in wanted}
        state: dict[str, Companions] = {}
        skipped: set[str] = set()
        for ns, channel, data in self._records(channels):
            role = self._roles[channel]
            if role.main_topic in skipped:
                continue
            comp = state.setdefault(role.main_topic, {})
            try:
                payload = role.reader.parse(data)
                if role.reader.build is None:
                    comp[role.reader.schema.name] = (ns, payload)
                    continue
                msg = role.reader.build(payload, ns, comp)
            except Skip as e:
                skipped.add(role.main_topic)
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping {role.main_topic!r}: {e}"
                    ),
                    stacklevel=2,
                )
                continue
            except Exception as e:
                topic = self._channels[channel].topic
                self._fail(f"cannot decode the message on {topic!r} at {ns} ns: {e!r}")
            yield msg

    def __iter__(self) -> Iterator[Message]:
        return self.messages()

    def close(self) -> None:
        """Nothing to release: every `messages()` iteration opens the file itself."""

    # -- opening

    def _fail(self, what: str) -> NoReturn:
        raise LogError(f"{self.path}: {what}")

    def _open(self) -> io.BufferedReader:
        try:
            return open(self.path, "rb")
        except FileNotFoundError:
            self._fail("no such file")
        except IsADirectoryError:
            self._fail("is a directory, not a log file")
        except PermissionError:
            self._fail("permission denied")
        except OSError as e:
            self._fail(f"cannot open: {e.strerror}")

    def _no_calibration(self) -> str:
        if not self.lost:
            return "no calibration record"
        first = self.lost[0]
        if first.what == "truncated":
            return f"truncated at byte {first.start} before the calibration record"
        return f"no readable calibration record ({first.describe()})"

    def _classify(self, contents: Contents) -> None:
        for cid, channel in sorted(self._channels.items()):
            schema = contents.schemas.get(channel.schema_id)
            reader = READERS.get(schema.name) if schema else None
            main = channel.topic if reader and reader.build else channel.metadata.get("main_topic")
            if (
                reader is None
                or schema is None
                or (schema.encoding, channel.message_encoding)
                != (reader.schema.encoding, reader.schema.message_encoding)
                or not main
            ):
                name = schema.name if schema else "(none)"
                warnings.warn(
                    UnsupportedChannelWarning(
                        f"{self.path.name}: skipping channel {channel.topic!r} with unsupported "
                        f"schema {name!r} ({channel.message_encoding})"
                    ),
                    stacklevel=4,
                )
                continue
            self._roles[cid] = _Role(main, reader)
            if reader.cls is not None:
                self.topics[main] = reader.cls

    def _report(self, contents: Contents) -> None:
        """LogError if nothing could be recovered, else the one-line LogRecoveryWarning:
        each lost span, the channels that could not be read, what was recovered."""
        undeclared = contents.undeclared
        lost_records = sum(contents.counts[c][0] for c in undeclared)
        unreadable = (
            f"{lost_records} records on channels {', '.join(map(str, undeclared))} skipped: "
            "their declarations were in the lost bytes and the log has no intact summary"
            if undeclared
            else ""
        )
        if self.message_count == 0:
            first = self.lost[0]
            self._fail(
                f"{first.what} at byte {first.start} before any message"
                + (f"; {unreadable}" if unreadable else "")
            )
        first, last = self.time_range or (0.0, 0.0)
        expected = ""
        summary = contents.summary
        if summary is not None and summary.statistics is not None:
            counts = summary.statistics.channel_message_counts
            total = sum(
                n for c, n in counts.items() if c in self._roles and self._roles[c].reader.build
            )
            expected = f" (of {total} in the summary)"
        clauses = [span.describe() for span in self.lost] + ([unreadable] if unreadable else [])
        warnings.warn(
            LogRecoveryWarning(
                f"{self.path.name}: {'; '.join(clauses)}; recovered {self.message_count} "
                f"messages{expected} spanning {last - first:.3f} s "
                f"(log time {first:.3f} to {last:.3f} s)"
            ),
            stacklevel=4,
        )

    # -- reading

    def _records(self, channels: set[int]) -> Iterator[Record]:
        """(log time, channel, data) of the messages on `channels`, in log-time order
        (ties in file order)."""
        blocks = [b for b in self._blocks if b.channels & channels]
        disjoint = all(a.end_ns <= b.start_ns for a, b in itertools.pairwise(blocks))
        with self._open() as f:
            if disjoint:
                # Blocks follow each other in time (a recorder writes them so): a stable
                # sort within each block is the global order.
                for block in blocks:
                    recs = [r for r in self._read_block(f, block) if r[1] in channels]
                    recs.sort(key=_log_time)
                    yield from recs
                return
            heap: list[tuple[int, int, int, Any]] = [(b.start_ns, b.offset, -1, b) for b in blocks]
            heapq.heapify(heap)
            while heap:
                _, offset, index, item = heapq.heappop(heap)
                if index >= 0:
                    yield item
                    continue
                for i, rec in enumerate(self._read_block(f, item)):
                    if rec[1] in channels:
                        heapq.heappush(heap, (rec[0], offset, i, rec))

    def _read_block(self, f: io.BufferedReader, block: Block) -> list[Record]:
        try:
            f.seek(block.offset)
            opcode, length = struct.unpack("<BQ", f.read(9))
            return block_records(opcode, f.read(length))[0]
        except Exception as e:
            self._fail(f"changed or unreadable while replaying (byte {block.offset}): {e!r}")


def _log_time(record: Record) -> int:
    return record[0]


def read_log(path: str | os.PathLike[str]) -> TrialLog:
    """Open a trial log for replay (see TrialLog)."""
    return TrialLog(path)


LogReader = TrialLog  # alias


def replay(path: str | os.PathLike[str], topics: Iterable[str] | None = None) -> Iterator[Message]:
    """All messages of a trial log (or those on `topics`) in log-time order."""
    yield from read_log(path).messages(topics)
