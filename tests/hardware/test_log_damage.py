"""A damaged trial log loses only what is damaged.

A 20 s simulated trial (about 40 chunks of 0.5 s) is damaged in the ways files get damaged:
flipped bytes in one chunk, a zeroed 4 kB block, a cut summary, a cut in the middle,
damage before the first chunk, damage to the chunk that declares the channels. Which
messages must survive is worked out independently of the reader under test: mcap's own
stream reader lists the messages of every chunk of the intact file.
"""

from __future__ import annotations

import heapq
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

from hardware.log import TOPICS, LogError, LogRecoveryWarning, LogWriter, LostSpan, read_log
from hardware.messages import Collision
from tests.hardware.test_log import assert_same
from tests.hardware.test_log_compat import (
    V1_ATTACHMENTS,
    V1_LOG,
    V1_METADATA,
    expected_order,
    v1_messages,
)

MAIN_TOPICS = set(TOPICS.values())


@dataclass(frozen=True)
class ChunkInfo:
    """A chunk of the intact file: its record's bytes, log times, and the main messages
    in it as (topic, sequence number)."""

    start: int
    end: int  # end of the chunk record
    next_start: int  # where the next chunk (or the data end) starts
    t0: float
    t1: float
    messages: frozenset[tuple[str, int]]
    declares: frozenset[str]  # topics of the channels first declared in it


@dataclass(frozen=True)
class Trial:
    path: Path
    data: bytes
    chunks: list[ChunkInfo]
    messages: list[tuple[str, int, Any]]  # (topic, sequence, message) in replay order
    summary_start: int
    data_end: int  # offset of the data end record
    span: float  # first to last log time [s]


def read_chunks(path: Path, topics: set[str] = MAIN_TOPICS) -> tuple[list[ChunkInfo], int]:
    """The chunks of an intact log as mcap's stream reader sees them, and where its data
    end record is; messages on `topics` counted."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    names = {c.id: c.topic for c in summary.channels.values()}
    found: list[tuple[frozenset[tuple[str, int]], frozenset[str]]] = []
    with open(path, "rb") as f:
        records = list(StreamReader(f, emit_chunks=True).records)
    for record in records:
        if isinstance(record, Chunk):
            inside = breakup_chunk(record, validate_crc=True)
            msgs = frozenset(
                (names[r.channel_id], r.sequence)
                for r in inside
                if isinstance(r, McapMessage) and names[r.channel_id] in topics
            )
            found.append((msgs, frozenset(r.topic for r in inside if isinstance(r, Channel))))
    footer = next(r for r in records if isinstance(r, Footer))
    data_end = footer.summary_start - 13  # the data end record: opcode, length, CRC
    index = summary.chunk_indexes
    assert len(index) == len(found)
    starts = [c.chunk_start_offset for c in index] + [data_end]
    chunks = [
        ChunkInfo(
            c.chunk_start_offset,
            c.chunk_start_offset + c.chunk_length,
            starts[i + 1],
            c.message_start_time / 1e9,
            c.message_end_time / 1e9,
            *found[i],
        )
        for i, c in enumerate(index)
    ]
    return chunks, data_end


# The one collision of the trial (its channel is declared in the chunk it falls in, not
# in the first): written into the simulated trial so that the log always has a channel
# declared after the first chunk, whatever the simulated user did.
COLLISION = Collision(10.0, "side", "chair-a0", 0.5, 1.2)


@pytest.fixture(scope="module")
def trial(tmp_path_factory: pytest.TempPathFactory) -> Trial:
    from experiments.run import simulate_trial

    folder = tmp_path_factory.mktemp("damage")
    simulated, path = folder / "simulated.mcap", folder / "trial.mcap"
    simulate_trial("thesis-course", simulated, duration_s=20, seed=0)
    source = read_log(simulated)
    messages = [m for m in source.messages() if not isinstance(m, Collision)]
    metadata = {k: v for k, v in source.metadata.items() if k != "calibration"}
    with LogWriter(path, source.calibration, metadata=metadata) as log:
        for m in heapq.merge(messages, [COLLISION], key=lambda m: m.t):
            log.write(m)
    chunks, data_end = read_chunks(path)
    assert len(chunks) > 30
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean log: no warning
        log = read_log(path)
        replayed = list(log.messages())
    assert log.complete and log.lost == []
    # Each topic's messages were written in time order: the n-th one read is sequence n.
    seen: dict[str, int] = {}
    labelled = []
    for m in replayed:
        topic = TOPICS[type(m)]
        seen[topic] = seen.get(topic, 0) + 1
        labelled.append((topic, seen[topic], m))
    assert set(seen) >= {"/encoders", "/depth/image", "/groundtruth/pose", "/brakes/command"}
    assert labelled[-1][2].t >= 19.9
    t0, t1 = log.time_range  # type: ignore[misc]
    data = path.read_bytes()
    return Trial(path, data, chunks, labelled, data_end + 13, data_end, t1 - t0)


def damaged(trial: Trial, tmp: Path, name: str, edit: Any) -> Path:
    data = bytearray(trial.data)
    edit(data)
    path = tmp / name
    path.write_bytes(bytes(data))
    return path


def read_damaged(path: Path) -> tuple[Any, list[Any], str]:
    """(log, its messages, the one recovery warning)."""
    with pytest.warns(LogRecoveryWarning) as caught:
        log = read_log(path)
        got = list(log.messages())
    recovery = [w for w in caught if issubclass(w.category, LogRecoveryWarning)]
    assert len(recovery) == 1
    text = str(recovery[0].message)
    assert "\n" not in text and text.startswith(f"{path.name}: ")
    return log, got, text


def assert_survivors(trial: Trial, got: list[Any], lost_chunks: list[ChunkInfo]) -> None:
    """Exactly the messages outside the lost chunks, in replay order, none twice."""
    lost = frozenset().union(*(c.messages for c in lost_chunks))
    expected = [m for topic, seq, m in trial.messages if (topic, seq) not in lost]
    assert len(expected) == len(trial.messages) - len(lost)
    assert len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        assert_same(a, b)


def chunk_at(trial: Trial, offset: int) -> int:
    return next(i for i, c in enumerate(trial.chunks) if c.start <= offset < c.end)


def flip(start: int, n: int) -> Any:
    def edit(data: bytearray) -> None:
        for i in range(start, start + n):
            data[i] ^= 0xFF

    return edit


def test_a_clean_log_reads_without_warning(trial: Trial) -> None:
    """(The fixture reads it with warnings as errors.) Every message of the 20 s, as many as
    mcap's reader finds in the chunks."""
    log = read_log(trial.path)
    assert log.message_count == len(trial.messages) == sum(len(c.messages) for c in trial.chunks)
    assert log.time_range is not None and log.time_range[1] - log.time_range[0] > 19.9


def test_flipped_bytes_lose_one_chunk(trial: Trial, tmp_path: Path) -> None:
    """64 flipped bytes at a quarter of the file (the reader used to stop there)."""
    at = len(trial.data) // 4
    k = chunk_at(trial, at)
    chunk = trial.chunks[k]
    path = damaged(trial, tmp_path, "flipped.mcap", flip(at, 64))
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, [chunk])
    assert log.lost == [
        LostSpan(
            chunk.start,
            chunk.next_start,
            "corrupt chunk record",
            (chunk.t0, chunk.t1),
            None,
            1,
        )
    ]
    assert (
        f"corrupt chunk record at byte {chunk.start}: skipped bytes {chunk.start}-"
        f"{chunk.next_start} ({chunk.next_start - chunk.start} bytes), lost log time "
        f"{chunk.t0:.3f}-{chunk.t1:.3f} s (1 chunk); recovered {len(got)} messages "
        f"(of {len(trial.messages)} in the summary) spanning {trial.span:.3f} s" in text
    )
    assert chunk.t1 - chunk.t0 <= 0.5 and not log.complete


@pytest.mark.parametrize(
    ("byte", "what"), [(7, "corrupt record length"), (0, "corrupt chunk record")]
)
def test_a_damaged_chunk_length_loses_that_chunk(
    trial: Trial, tmp_path: Path, byte: int, what: str
) -> None:
    """The length field of a chunk record: its top byte flipped runs past the end of the
    file (not a truncation: intact chunks follow), its low byte makes the sizes disagree."""
    k = len(trial.chunks) // 2
    chunk = trial.chunks[k]
    log, got, text = read_damaged(
        damaged(trial, tmp_path, "length.mcap", flip(chunk.start + 1 + byte, 1))
    )
    assert_survivors(trial, got, [chunk])
    assert [(s.start, s.end, s.what, s.log_time) for s in log.lost] == [
        (chunk.start, chunk.next_start, what, (chunk.t0, chunk.t1))
    ]
    assert f"{what} at byte {chunk.start}" in text


def test_a_zeroed_block_loses_the_chunks_it_touches(trial: Trial, tmp_path: Path) -> None:
    """4 kB of zeros in the middle (the reader used to stop there), and 4 kB across the
    end of one chunk, its message indexes and the start of the next."""
    k = chunk_at(trial, len(trial.data) // 2)
    middle = (trial.chunks[k].start + trial.chunks[k].end) // 2 - 2048
    for name, at, n_lost in (
        ("middle.mcap", middle, 1),
        ("boundary.mcap", trial.chunks[k + 2].end - 1000, 2),
    ):
        lost = [c for c in trial.chunks if c.start < at + 4096 and at < c.end]
        assert len(lost) == n_lost

        def zero(data: bytearray, at: int = at) -> None:
            data[at : at + 4096] = bytes(4096)

        log, got, text = read_damaged(damaged(trial, tmp_path, name, zero))
        assert_survivors(trial, got, lost)
        first, last = lost[0], lost[-1]
        span = (first.start, last.next_start)
        assert [(s.start, s.end, s.chunks, s.log_time) for s in log.lost] == [
            (*span, n_lost, (first.t0, last.t1))
        ]
        assert f"skipped bytes {span[0]}-{span[1]}" in text
        assert f"lost log time {first.t0:.3f}-{last.t1:.3f} s ({n_lost} chunk" in text


@pytest.mark.parametrize("where", ["summary", "footer"])
def test_a_cut_summary_loses_nothing(trial: Trial, tmp_path: Path, where: str) -> None:
    """The reader needs no summary: all messages, no warning; the data section ended."""
    cut = trial.summary_start + 100 if where == "summary" else len(trial.data) - 20
    path = tmp_path / f"cut-{where}.mcap"
    path.write_bytes(trial.data[:cut])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = read_log(path)
        got = list(log.messages())
    assert_survivors(trial, got, [])
    assert log.complete and log.lost == []


def test_a_cut_in_the_middle_keeps_the_chunks_before_it(trial: Trial, tmp_path: Path) -> None:
    cut = len(trial.data) // 2
    k = chunk_at(trial, cut)
    path = tmp_path / "cut.mcap"
    path.write_bytes(trial.data[:cut])
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, trial.chunks[k:])
    start = trial.chunks[k].start
    assert log.lost == [
        LostSpan(start, cut, "truncated", None, (trial.chunks[k - 1].t1, None), None)
    ]
    assert f"truncated at byte {start} (writer killed or still writing?)" in text
    assert f"recovered {len(got)} messages spanning" in text  # no summary to count from
    assert not log.complete


def test_without_a_summary_the_span_is_bounded_by_its_neighbours(
    trial: Trial, tmp_path: Path
) -> None:
    """A recorder killed after the last chunk (no data end, no summary), one chunk damaged:
    the lost messages lie between the intact chunks either side."""
    k = len(trial.chunks) // 3
    chunk = trial.chunks[k]
    data = bytearray(trial.data[: trial.data_end])
    flip(chunk.start + 200, 64)(data)
    path = tmp_path / "killed.mcap"
    path.write_bytes(bytes(data))
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, [chunk])
    before, after = trial.chunks[k - 1].t1, trial.chunks[k + 1].t0
    end = max(c.t1 for c in trial.chunks)
    assert log.lost == [
        LostSpan(
            chunk.start, chunk.next_start, "corrupt chunk record", None, (before, after), None
        ),
        LostSpan(trial.data_end, trial.data_end, "truncated", None, (end, None), None),
    ]
    assert (
        "lost what lay between the intact chunks either side "
        f"(log time {before:.3f} and {after:.3f} s)" in text
    )


def test_the_first_chunk_lost_with_its_declarations(trial: Trial, tmp_path: Path) -> None:
    """The first chunk declares the channels used in it; with the summary intact they are
    learned from it, without one the later messages on those channels are skipped."""
    first = trial.chunks[0]
    assert {"/encoders", "/depth/image", "/groundtruth/pose"} <= first.declares
    path = damaged(trial, tmp_path, "first.mcap", flip(first.start + 500, 64))
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, [first])
    assert "lost log time 0.000-0.500 s (1 chunk)" in text

    # a recorder killed after its last chunk: no summary to learn the channels from
    path = tmp_path / "first-killed.mcap"
    path.write_bytes(path.parent.joinpath("first.mcap").read_bytes()[: trial.data_end])
    declared_later = [(t, s, m) for t, s, m in trial.messages if t not in first.declares]
    assert {t for t, _, _ in declared_later} == {"/collisions"}  # the one collision (10 s)
    log, got, text = read_damaged(path)
    assert log.topics.keys() == {"/collisions"}
    assert len(got) == len(declared_later) == 1
    assert_same(got[0], declared_later[0][2])
    assert re.search(
        r"; \d+ records on channels \d+(, \d+){7} skipped: their declarations were in the "
        r"lost bytes and the log has no intact summary; recovered 1 messages",
        text,
    )


def test_damage_before_the_first_chunk(trial: Trial, tmp_path: Path) -> None:
    """The header record, a metadata record, the calibration record. (Metadata records
    have no CRC: damage is found when it breaks their structure, UTF-8 or JSON.)"""
    clean = read_log(trial.path)
    header_end = 8 + 9 + int.from_bytes(trial.data[9:17], "little")
    path = damaged(trial, tmp_path, "header.mcap", flip(8 + 9 + 8 + 2, 8))  # "lker-sla"
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, [])
    assert log.lost == [LostSpan(8, header_end, "corrupt header record", None, None, 0)]
    assert f"corrupt header record at byte 8: skipped bytes 8-{header_end}" in text
    assert "no chunk lost" in text
    assert log.metadata == clean.metadata and log.calibration == clean.calibration

    with open(trial.path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    meta = {m.name: m for m in summary.metadata_indexes}
    config = meta["config"]
    map_size = config.offset + 9 + 4 + len("config")  # the size of its key-value map
    path = damaged(trial, tmp_path, "config.mcap", flip(map_size, 1))
    log, got, text = read_damaged(path)
    assert_survivors(trial, got, [])
    assert set(clean.metadata) - set(log.metadata) == {"config"}
    assert log.calibration == clean.calibration
    assert (
        f"corrupt metadata record at byte {config.offset}: skipped bytes {config.offset}-"
        f"{config.offset + config.length} ({config.length} bytes), no chunk lost, "
        "lost metadata 'config'" in text
    )

    cal = meta["calibration"]
    path = damaged(trial, tmp_path, "calibration.mcap", flip(cal.offset + 9 + 4 + 11, 1))
    with pytest.raises(LogError, match=r"no readable calibration record \(corrupt metadata"):
        read_log(path)

    def zero_header(data: bytearray) -> None:
        data[8 : header_end + 40] = bytes(header_end + 32)

    path = damaged(trial, tmp_path, "zeroed.mcap", zero_header)
    with pytest.raises(
        LogError,
        match=r"calibration record \(corrupt header record at byte 8: .*"
        r"lost metadata 'calibration'\)",
    ):
        read_log(path)


def test_a_damaged_log_of_the_v1_writer_without_its_summary(tmp_path: Path) -> None:
    """The v1 fixture (written before the reader resynchronised): its middle chunk damaged
    and its tail cut as a killed recorder leaves it. Its last chunk overlaps the middle
    one in time (a late collision and a live log time), so the replay merges them."""
    written = v1_messages()
    topics = {topic or TOPICS[type(m)] for m, topic, _ in written}
    chunks, data_end = read_chunks(V1_LOG, topics)
    assert len(chunks) == 3 and chunks[2].t0 < chunks[1].t1
    data = bytearray(V1_LOG.read_bytes()[:data_end])
    flip(chunks[1].start + 100, 8)(data)
    path = tmp_path / "v1.mcap"
    path.write_bytes(bytes(data))
    log, got, text = read_damaged(path)
    seen: dict[str, int] = {}
    kept = []
    for m, topic, log_time in written:
        topic = topic or TOPICS[type(m)]
        seen[topic] = seen.get(topic, 0) + 1
        if (topic, seen[topic]) not in chunks[1].messages:
            kept.append((m, topic, log_time))
    expected = expected_order(kept)
    assert 0 < len(expected) < len(written) and len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        assert_same(a, b)
    assert [(s.start, s.end, s.what, s.between) for s in log.lost] == [
        (
            chunks[1].start,
            chunks[1].next_start,
            "corrupt chunk record",
            (chunks[0].t1, chunks[2].t0),
        ),
        (data_end, data_end, "truncated", (chunks[2].t1, None)),
    ]
    assert log.metadata == V1_METADATA and log.attachments == V1_ATTACHMENTS
    assert f"recovered {len(got)} messages" in text
