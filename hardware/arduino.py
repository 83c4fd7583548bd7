"""The serial driver of the walker's encoder/brake board (an Arduino Uno, protocol v1).

`ArduinoBoard(port, calibration, clock)` is a live source and a command sink
(`hardware.source`):

    board = ArduinoBoard("/dev/ttyACM0", calibration, HostClock())
    board.open()                      # handshake; BoardError (one line) if it fails
    for msg in board.messages():      # EncoderTicks (100 Hz), GyroRate, DeviceEvents
        ...
    board.send(BrakeCommand(t, 1.2, 0.068))   # torques → PWM through the calibration
    board.close()                     # sends zero brake, ends messages()

What it does with the board's lines (`hardware/firmware/PROTOCOL.md`):

- **checksums**: every line's CRC-8 is checked; bad, malformed, partial and over-long
  lines are counted in `stats` and skipped, never acted on.
- **sequence gaps**: missing tick reports are counted (`stats.seq_gaps`).
- **counter wrap-around**: the board's int32 counts wrap modulo 2³²; the driver starts
  from the board's first report and accumulates the signed difference of each report,
  so its cumulative counts (int, unbounded) pass the wrap without a jump.
- **board time**: the board's µs clock (uint32, wraps after 71.6 min) is unwrapped and
  mapped onto the run's host clock by a `hardware.clock.ClockMap` (offset and drift
  estimated from the reports' arrival times); every EncoderTicks is stamped with it.
- **board reset** (a tick sequence number that goes backwards, or a handshake line the
  host did not ask for: the firmware sends one at boot): the counts restarted at zero;
  the driver re-bases them on the last counts it reported, so odometry continues
  without a jump (the motion while the board was restarting is lost), forgets the
  clock map, and emits DeviceEvent("board", "reset").
- **unplugging**: when the port disappears the driver emits DeviceEvent("board",
  "disconnected"), tries to reopen the same path every `reconnect_poll_s`, handshakes
  again and emits "reconnected" (the gap in the encoder stream is marked by the two
  events in a recorded log). Across the gap the counts are re-based, so the localizer
  sees no motion rather than a jump: if the board restarted (an Uno powered by the USB
  cable does) they restarted from zero; if it did not (an externally powered board, a
  USB hiccup), what the wheels turned meanwhile is kept in a DeviceEvent "rebased" —
  or, with `gap_motion="keep"`, integrated as one increment.
- **brake commands**: `send` turns torques into PWM (calibration.brake) and writes a `B`
  line at once; while the command is non-zero a background thread re-sends it every
  1/resend_hz s (default 20 Hz), so the board's 300 ms command timeout stays fed only
  while this process is alive. A zero command is sent once (the board releases anyway).
  `close()` sends zero before it lets go of the port.
- **DTR**: `reset_on_open` pulses DTR to reset an Uno (as its bootloader expects); a
  port where DTR cannot be set (a pseudo-terminal) is tolerated.
- **gyro**: a board with an IMU announces the scale of its gyro field in `H`; each tick
  report's gyro z rate becomes a GyroRate (rad/s, CCW positive with the IMU's z axis
  up; `gyro_sign` -1 for one mounted upside down), stamped as the report and yielded
  just before its EncoderTicks. A report without the field (no IMU, a failed read)
  gives none.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import Any

import serial

from hardware import board_protocol as bp
from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.clock import ClockMap, HostClock
from hardware.errors import DeviceError
from hardware.messages import BrakeCommand, DeviceEvent, EncoderTicks, GyroRate, Message


class BoardError(DeviceError):
    """The board cannot be used (port missing, no handshake, wrong firmware); one line."""


class GapMotion(Choice):
    """What the counts moved across a gap in the stream: dropped (rebased) or kept."""

    DROP = "drop"
    KEEP = "keep"


@dataclass(frozen=True)
class BoardConfig:
    """Serial driver settings.

    handshake_timeout_s: wait this long for the reply to one query; handshake_attempts
    queries before giving up. resend_hz: re-send rate of a non-zero brake command (the
    board releases after 300 ms without one). reconnect: reopen the port after it
    disappeared (else messages() ends with a "disconnected" event); reconnect_poll_s:
    how often to try. rate_hz: ask the board for this tick-report rate (None: its
    default). reset_on_open: pulse DTR on open (resets an Uno; ignored where DTR cannot
    be set). check_cpr: refuse firmware whose counts per revolution differ from the
    calibration's. gap_motion: what the counts moved across a gap in the stream (the
    port lost and back, the board still running): "drop" re-bases them, so the
    localizer sees no motion rather than a jump (the count difference is kept in a
    DeviceEvent "rebased"); "keep" integrates it as one increment (the wheels' turn, hence
    the heading change, is exact; the path between is not). gyro_sign: +1 when the
    board's IMU has its z axis up (a yaw rate CCW seen from above is positive), -1 when
    it is mounted upside down.
    """

    baud: int = bp.BAUD
    handshake_timeout_s: float = 1.0
    handshake_attempts: int = 3
    resend_hz: float = 20.0
    reconnect: bool = True
    reconnect_poll_s: float = 0.2
    read_timeout_s: float = 0.02
    rate_hz: int | None = None
    reset_on_open: bool = False
    check_cpr: bool = True
    gap_motion: GapMotion = GapMotion.DROP
    gyro_sign: int = 1

    def __post_init__(self) -> None:
        coerce(self, gap_motion=GapMotion)
        if self.gyro_sign not in (1, -1):
            raise ValueError(f"gyro_sign must be 1 or -1, got {self.gyro_sign}")
        if not self.resend_hz >= 1.0 / bp.COMMAND_TIMEOUT_S * 2:
            raise ValueError(
                f"resend_hz must be >= {2 / bp.COMMAND_TIMEOUT_S:.1f} (twice per board "
                f"timeout), got {self.resend_hz}"
            )


@dataclass
class BoardStats:
    """What the driver counted; `status` is the board's own last S line."""

    lines: int = 0  # valid lines received
    bad_crc: int = 0
    malformed: int = 0
    overflow: int = 0
    ticks: int = 0
    seq_gaps: int = 0  # tick reports missing between sequence numbers
    resets: int = 0
    disconnects: int = 0
    reconnects: int = 0
    commands_sent: int = 0
    write_errors: int = 0
    status: bp.Status | None = None
    last_tick: bp.Tick | None = None

    @property
    def bad_lines(self) -> int:
        return self.bad_crc + self.malformed + self.overflow

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["bad_lines"] = self.bad_lines
        return d


@dataclass
class _Wheels:
    """Cumulative counts the host reports, from the board's wrapping int32 counts."""

    raw: tuple[int, int] | None = None
    total: list[int] | None = None

    def update(self, left: int, right: int) -> tuple[int, int]:
        if self.total is None:
            self.total = [left, right]  # the board's own counts to begin with
        elif self.raw is not None:
            for i, (new, old) in enumerate(zip((left, right), self.raw, strict=True)):
                self.total[i] += ((new - old + (1 << 31)) % bp.UINT32) - (1 << 31)
        self.raw = (left, right)
        return self.total[0], self.total[1]

    def rebase(self) -> None:
        """The next report continues from the current totals (no motion in between)."""
        self.raw = None


class ArduinoBoard:
    """The encoder/brake board on a serial port; see the module docstring."""

    device = "board"

    def __init__(
        self,
        port: str,
        calibration: WalkerCalibration,
        clock: HostClock | None = None,
        config: BoardConfig | None = None,
    ) -> None:
        self.port = str(port)
        self.calibration = calibration
        self.clock = clock or HostClock()
        self.config = config or BoardConfig()
        self.stats = BoardStats()
        self.handshake: bp.Handshake | None = None
        self.clock_map = ClockMap()
        self._serial: serial.Serial | None = None
        self._splitter = bp.LineSplitter()
        self._wheels = _Wheels()
        self._pending: deque[Message] = deque()
        self._write_lock = threading.Lock()
        self._closed = threading.Event()
        self._lost = threading.Event()  # the port failed (read or write)
        self._cmd_seq = 0
        self._pwm = (0, 0)
        self._resend: threading.Thread | None = None
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
        self._t_epochs = 0  # wraps of the board's µs counter
        self._queried_at = -math.inf
        self._handshake_seen = threading.Event()
        self._reset_pending = False
        self._after_gap = False  # the next tick follows a disconnection
        self._lost_at: float | None = None  # when the port was lost (a gap is open)

    # -- Source ---------------------------------------------------------------------
    @property
    def metadata(self) -> dict[str, Any]:
        h = self.handshake
        info: dict[str, Any] = {"port": self.port}
        if h is not None:
            info.update(
                protocol=h.proto,
                firmware=h.firmware,
                rate_hz=h.rate_hz,
                counts_per_rev=h.cpr,
                reset_cause=h.reset_cause,
                gyro_lsb_per_10dps=h.gyro_lsb_per_10dps,
            )
        return {"board": info}

    def open(self) -> bp.Handshake:
        """Open the port and handshake; BoardError if the board does not answer."""
        try:
            self._open_port()
        except (serial.SerialException, OSError) as e:
            raise BoardError(f"{self.port}: cannot open the serial port: {_reason(e)}") from None
        try:
            hs = self._handshake()
        except BoardError:
            self._close_port()
            raise
        if self.config.check_cpr and hs.cpr != self.calibration.counts_per_rev:
            self._close_port()
            raise BoardError(
                f"{self.port}: the firmware counts {hs.cpr} per wheel revolution, the "
                f"calibration {self.calibration.counts_per_rev} (rebuild the firmware with "
                f"CPR={self.calibration.counts_per_rev} or fix the calibration)"
            )
        self._pending.append(
            DeviceEvent(self._now_stamp(), self.device, "connected", self._describe(hs))
        )
        if self._resend is None:
            self._resend = threading.Thread(target=self._resend_loop, name="board-resend")
            self._resend.daemon = True
            self._resend.start()
        return hs

    def messages(self) -> Iterator[Message]:
        """EncoderTicks and DeviceEvents as they arrive; ends after close() (or when the
        port is lost and reconnect is off)."""
        if self._serial is None and not self._closed.is_set():
            self.open()
        while not self._closed.is_set():
            while self._pending:
                yield self._pending.popleft()
            if self._lost.is_set() or self._serial is None:
                if self._lost_at is None:
                    self._mark_lost()  # its event is yielded before reconnecting
                elif not self.config.reconnect:
                    break
                elif not self._try_reconnect():
                    self._closed.wait(self.config.reconnect_poll_s)
                continue
            self._read_once()
        while self._pending:
            yield self._pending.popleft()

    def close(self) -> None:
        """Release the brakes (zero command), stop re-sending, close the port; idempotent."""
        if self._closed.is_set():
            return
        self._pwm = (0, 0)
        self._write(bp.Brake(self._next_seq(), 0, 0).line())
        self._closed.set()
        if self._resend is not None and self._resend is not threading.current_thread():
            self._resend.join(timeout=1.0)
        self._close_port()

    # -- CommandSink ----------------------------------------------------------------
    def send(self, cmd: BrakeCommand) -> None:
        """Command brake torques [N·m] (through the calibration's PWM map)."""
        brake = self.calibration.brake
        self.send_pwm(brake.pwm(cmd.left_nm), brake.pwm(cmd.right_nm))

    def send_pwm(self, left: int, right: int) -> None:
        """Command PWM duties (0–255) directly."""
        for v in (left, right):
            if not 0 <= int(v) <= 255:
                raise ValueError(f"PWM duty must be 0..255, got {v}")
        self._pwm = (int(left), int(right))
        self._write(bp.Brake(self._next_seq(), *self._pwm).line())

    @property
    def commanded_pwm(self) -> tuple[int, int]:
        return self._pwm

    # -- internals ------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._cmd_seq = (self._cmd_seq + 1) % bp.UINT32
        return self._cmd_seq

    def _now_stamp(self) -> float:
        return self.clock.now()

    def _describe(self, hs: bp.Handshake) -> str:
        gyro = "no gyro" if hs.gyro_lsb_per_10dps is None else "a gyro"
        return (
            f"firmware {hs.firmware}, protocol {hs.proto}, {hs.rate_hz} Hz, "
            f"{hs.cpr} counts/rev, {gyro}, reset cause {hs.reset_cause}"
        )

    def _open_port(self) -> None:
        s = serial.Serial(self.port, self.config.baud, timeout=self.config.read_timeout_s)
        if self.config.reset_on_open:
            try:
                s.dtr = False
                time.sleep(0.05)
                s.dtr = True
                time.sleep(1.5)  # the Uno's bootloader waits before starting the sketch
            except OSError:
                pass  # a pseudo-terminal has no DTR line
        self._serial = s
        self._splitter = bp.LineSplitter()
        self._lost.clear()

    def _close_port(self) -> None:
        with self._write_lock:  # not while another thread writes to it
            s, self._serial = self._serial, None
        if s is not None:
            try:
                s.close()
            except (serial.SerialException, OSError):
                pass

    def _write(self, data: bytes) -> bool:
        with self._write_lock:
            s = self._serial
            if s is None:
                return False
            try:
                s.write(data)
                if data.startswith(b"B"):
                    self.stats.commands_sent += 1
                return True
            except (serial.SerialException, OSError, TypeError):
                # TypeError: pyserial on a port the reader thread just found dead
                self.stats.write_errors += 1
                self._lost.set()
                return False

    def _resend_loop(self) -> None:
        period = 1.0 / self.config.resend_hz
        while not self._closed.wait(period):
            if self._pwm != (0, 0):
                self._write(bp.Brake(self._next_seq(), *self._pwm).line())

    def _handshake(self) -> bp.Handshake:
        """Query until an H line comes back (ticks read meanwhile are kept)."""
        cfg = self.config
        for _ in range(cfg.handshake_attempts):
            self._handshake_seen.clear()
            self._queried_at = time.monotonic()
            if cfg.rate_hz is not None:
                self._write(bp.Configure(cfg.rate_hz).line())
            self._write(bp.Query().line())
            deadline = time.monotonic() + cfg.handshake_timeout_s
            while time.monotonic() < deadline and not self._lost.is_set():
                self._read_once()
                if self._handshake_seen.is_set() and self.handshake is not None:
                    return self.handshake
        raise BoardError(
            f"{self.port}: no handshake from the board after {cfg.handshake_attempts} "
            f"queries ({cfg.handshake_timeout_s:.1f} s each): is it the walker board's "
            f"firmware at {cfg.baud} baud?"
        )

    def _mark_lost(self) -> None:
        """The port failed: close it and mark the start of the gap."""
        self._lost_at = self._now_stamp()
        self._close_port()
        self._after_gap = True
        self.stats.disconnects += 1
        self._pending.append(DeviceEvent(self._lost_at, self.device, "disconnected", "port lost"))

    def _try_reconnect(self) -> bool:
        """Reopen the port and handshake again; mark the end of the gap."""
        before, t_open = len(self._pending), self._now_stamp()
        try:
            self._open_port()
            hs = self._handshake()
        except (serial.SerialException, OSError, BoardError):
            self._close_port()
            return False
        self.stats.reconnects += 1
        gap = t_open - (self._lost_at or 0.0)
        self._lost_at = None
        # before what the handshake read meanwhile (the first reports after the gap)
        self._pending.insert(
            before,
            DeviceEvent(
                t_open,
                self.device,
                "reconnected",
                f"after {gap:.2f} s (last tick seq {self._last_seq}; a 'reset' event "
                f"follows if the board restarted meanwhile); " + self._describe(hs),
            ),
        )
        return True

    def _read_once(self) -> None:
        s = self._serial
        if s is None:
            self._lost.set()
            return
        try:
            data = s.read(max(1, s.in_waiting or 1))
        except (serial.SerialException, OSError, TypeError):
            # TypeError: pyserial's read on a port closed by another thread
            self._lost.set()
            return
        if not data:
            return
        arrival = self._now_stamp()
        for item in self._splitter.feed(data):
            if isinstance(item, bp.LineError):
                self._count_bad(item)
                continue
            try:
                msg = bp.parse_board_line(item)
            except bp.LineError as e:
                self._count_bad(e)
                continue
            self.stats.lines += 1
            self._handle(msg, arrival)

    def _count_bad(self, e: bp.LineError) -> None:
        if e.kind == "crc":
            self.stats.bad_crc += 1
        elif e.kind == "overflow":
            self.stats.overflow += 1
        else:
            self.stats.malformed += 1

    def _handle(self, msg: bp.BoardMessage, arrival: float) -> None:
        if isinstance(msg, bp.Tick):
            self._on_tick(msg, arrival)
        elif isinstance(msg, bp.Status):
            self.stats.status = msg
        else:
            asked = time.monotonic() - self._queried_at < self.config.handshake_timeout_s
            if not asked and self.handshake is not None:
                self._on_reset(arrival, f"boot announced (reset cause {msg.reset_cause})")
            self.handshake = msg
            self._handshake_seen.set()

    def _on_reset(self, arrival: float, why: str) -> None:
        if self._reset_pending:
            return
        self._reset_pending = True
        self.stats.resets += 1
        self._wheels.rebase()
        self.clock_map.reset()
        self._last_seq = self._last_t_us = None
        self._t_epochs = 0
        self._pending.append(DeviceEvent(arrival, self.device, "reset", why))

    def _on_tick(self, tick: bp.Tick, arrival: float) -> None:
        if self._last_seq is not None:
            ahead = (tick.seq - self._last_seq) % bp.UINT32
            if ahead == 0 or ahead >= 1 << 31:
                self._on_reset(arrival, f"tick sequence went back ({self._last_seq} → {tick.seq})")
            elif ahead > 1 and not self._after_gap:
                self.stats.seq_gaps += ahead - 1  # (reports lost while unplugged are not)
        if self._after_gap and not self._reset_pending:
            self._across_gap(tick, arrival)
        if self._last_t_us is not None and tick.t_us < self._last_t_us:
            self._t_epochs += 1  # the µs counter wrapped
        self._reset_pending = self._after_gap = False
        self._last_seq, self._last_t_us = tick.seq, tick.t_us
        board_t = (self._t_epochs * bp.UINT32 + tick.t_us) * 1e-6
        self.clock_map.observe(board_t, arrival)
        left, right = self._wheels.update(tick.left, tick.right)
        self.stats.ticks += 1
        self.stats.last_tick = tick
        t = self.clock_map.to_host(board_t, not_after=arrival)
        scale = self.handshake.gyro_lsb_per_10dps if self.handshake is not None else None
        if tick.gyro_z is not None and scale:
            rate = self.config.gyro_sign * bp.gyro_rate(tick.gyro_z, scale)
            self._pending.append(GyroRate(t, rate))
        self._pending.append(EncoderTicks(t, left, right))

    def _across_gap(self, tick: bp.Tick, arrival: float) -> None:
        """The first report after a reconnection of a board that did not restart: its
        clock may have wrapped unseen (the map starts afresh), and its counts moved by
        what the wheels turned while nobody listened."""
        self.clock_map.reset()
        self._last_t_us, self._t_epochs = None, 0
        raw = self._wheels.raw
        if raw is None:
            return
        moved = [
            ((new - old + (1 << 31)) % bp.UINT32) - (1 << 31)
            for new, old in zip((tick.left, tick.right), raw, strict=True)
        ]
        if self.config.gap_motion == "drop":
            self._wheels.rebase()
            what = "not integrated: the localizer sees no motion across the gap"
        else:
            what = "integrated as one increment (gap_motion='keep')"
        self._pending.append(
            DeviceEvent(
                arrival,
                self.device,
                "rebased" if self.config.gap_motion == "drop" else "gap-motion",
                f"the wheels turned {moved[0]}, {moved[1]} counts during the gap; {what}",
            )
        )


def _reason(e: BaseException) -> str:
    """What went wrong opening a port, without pyserial's repetition of its name."""
    errno = getattr(e, "errno", None)
    if isinstance(errno, int) and errno > 0:
        return os.strerror(errno)
    return str(e).splitlines()[0] if str(e) else type(e).__name__
