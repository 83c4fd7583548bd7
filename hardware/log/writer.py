"""The trial-log writer: crash-safe (a chunk closed at least every half second) and
thread-safe."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from hardware.calibration import WalkerCalibration
from hardware.log.codec import TOPICS, dumps, encode_parts, message_ns
from hardware.log.schemas import ChannelSchema
from hardware.messages import Message

FLUSH_INTERVAL_S = 0.5
FORMAT = "walker-slam log v1"


def _best_compression() -> CompressionType:
    for kind, module in ((CompressionType.ZSTD, "zstandard"), (CompressionType.LZ4, "lz4")):
        try:
            __import__(module)
            return kind
        except ImportError:
            pass
    return CompressionType.NONE


def _metadata_record(name: str, d: dict[str, Any]) -> tuple[str, bytes]:
    """(name, strict JSON) of a metadata record; "calibration" is the writer's own."""
    if name == "calibration":
        raise ValueError("metadata name 'calibration' is reserved")
    try:
        return name, dumps(d)
    except (TypeError, ValueError) as e:
        raise ValueError(f"metadata {name!r} is not strict JSON: {e}") from None


class LogWriter:
    """Writes a trial log; crash-safe (see the `hardware.log` docstring) and thread-safe.

    `message_count` counts messages written, `flushed_count` those handed to the OS by the
    last flush (what survives if the process is killed now).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        calibration: WalkerCalibration,
        metadata: dict[str, dict[str, Any]] | None = None,
        attachments: dict[str, bytes] | None = None,
        *,
        flush_interval_s: float = FLUSH_INTERVAL_S,
        fsync: bool = False,
        background_flush: bool = True,
    ) -> None:
        self.path = Path(path)
        self.message_count = 0
        self.flushed_count = 0
        self._interval = flush_interval_s
        self._fsync = fsync
        records = [("calibration", dumps(calibration.to_dict()))]
        records += [_metadata_record(name, d) for name, d in (metadata or {}).items()]
        self._file = open(self.path, "wb")
        self._mcap = Writer(self._file, compression=_best_compression())
        self._mcap.start(profile="", library=f"{FORMAT} ({LIBRARY_IDENTIFIER})")
        for name, data in records:
            self._mcap.add_metadata(name, {"json": data.decode()})
        for name, blob in (attachments or {}).items():
            self._mcap.add_attachment(0, 0, name, "application/octet-stream", bytes(blob))
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._sequence: dict[int, int] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._last_flush = time.monotonic()
        self._unflushed_t0: float | None = None  # log time of the first unflushed message
        self._flush_locked()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background_flush:
            self._thread = threading.Thread(target=self._flush_loop, name="LogWriter", daemon=True)
            self._thread.start()

    def write(self, msg: Message, topic: str | None = None, log_time: float | None = None) -> None:
        """Log one message on `topic` (default: the type's topic, see TOPICS).

        log_time [s]: when the message was recorded, default its own time `t`. A live
        recorder gives the time it handed the message to the pipeline (never earlier
        than t), so a replay, which reads in log-time order, feeds the messages in the
        order the live run did."""
        if type(msg) not in TOPICS:
            raise TypeError(f"cannot log a {type(msg).__name__}")
        topic = topic or TOPICS[type(msg)]
        ns = message_ns(msg.t)
        log_ns = ns if log_time is None else message_ns(log_time)
        parts = encode_parts(msg, topic, ns)  # encode outside the lock
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path}: log writer is closed")
            channels = [self._channel(part_topic, schema, topic) for part_topic, schema, _ in parts]
            for channel, (_, _, data) in zip(channels, parts, strict=True):
                seq = self._sequence[channel] = (self._sequence[channel] + 1) & 0xFFFFFFFF
                self._mcap.add_message(channel, log_ns, data, ns, seq)
            self.message_count += 1
            t = float(msg.t)
            if self._unflushed_t0 is None:
                self._unflushed_t0 = t
            if (
                abs(t - self._unflushed_t0) >= self._interval
                or time.monotonic() - self._last_flush >= self._interval
            ):
                self._flush_locked()

    def add_metadata(self, name: str, d: dict[str, Any]) -> None:
        """Write one more metadata record now (what is known only at the end of a run,
        e.g. a simulation's true slip); a recorder killed before loses it."""
        record = _metadata_record(name, d)
        with self._lock:
            if self._closed:
                raise ValueError(f"{self.path}: log writer is closed")
            self._mcap.add_metadata(record[0], {"json": record[1].decode()})

    def flush(self) -> None:
        """Close the current chunk and hand everything written so far to the OS."""
        with self._lock:
            if not self._closed:
                self._flush_locked()

    def close(self) -> None:
        """Flush, write the summary and footer, and close the file. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._mcap.finish()
                self._file.flush()
                if self._fsync:
                    os.fsync(self._file.fileno())
                self.flushed_count = self.message_count
            finally:
                self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _channel(self, topic: str, schema: ChannelSchema, main_topic: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != schema.name:
                raise ValueError(f"topic {topic!r} holds {known[1]}, cannot write {schema.name}")
            return known[0]
        if schema.name not in self._schemas:
            self._schemas[schema.name] = self._mcap.register_schema(
                schema.name, schema.encoding, schema.data
            )
        meta = {} if topic == main_topic else {"main_topic": main_topic}
        channel = self._mcap.register_channel(
            topic, schema.message_encoding, self._schemas[schema.name], meta
        )
        self._channels[topic] = (channel, schema.name)
        self._sequence[channel] = 0
        return channel

    def _flush_locked(self) -> None:
        self._mcap.flush()  # finishes the chunk and flushes the Python file object
        if self._fsync:
            os.fsync(self._file.fileno())
        self.flushed_count = self.message_count
        self._last_flush = time.monotonic()
        self._unflushed_t0 = None

    def _flush_loop(self) -> None:
        while not self._stop.wait(self._interval / 5):
            with self._lock:
                if (
                    not self._closed
                    and self.flushed_count < self.message_count
                    and time.monotonic() - self._last_flush >= self._interval
                ):
                    self._flush_locked()
