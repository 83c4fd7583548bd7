"""A pure-Python walker board on a pseudo-terminal, speaking the firmware's protocol.

`BoardEmulator` opens a pty (and a symlink to it at a path of your choice), and from a
thread behaves like the firmware in `hardware/firmware/` does on the UART: tick reports
at a fixed rate with its own microsecond clock, a sequence number and the cumulative
counts it was given (`set_counts`), status lines every second, a handshake on `Q`, the
brake duties of valid `B` lines (`brake_outputs`), released 300 ms after the last valid
command, and counters of the bad lines it received. The serial driver
(`hardware.arduino.ArduinoBoard`) opens the pty as it would `/dev/ttyACM0`.

It serves `walkerslam live --sim` (the simulator's wheels turn its counts, its duties
set the simulated brakes) and quick tests of the driver; the protocol itself is tested
against the real firmware in simavr (`hardware.firmware_sim`), which has the same
`port`, `set_counts` and `brake_outputs`.

With `imu=True` it also emulates the firmware with an MPU-6050 on its I²C bus: the
handshake announces the gyro's scale and every tick report carries the rate last given to
`set_gyro_rate` as the IMU's int16 output (131 LSB per °/s).

For fault tests: `reset()` restarts it (counts, sequence and clock from zero, brakes
released, a boot handshake line), `unplug()` / `replug()` close the pty and make a new
one at the same path, `inject(data)` sends raw bytes to the host; `clock_drift_ppm`,
`t_us_start` and `count_offset` exercise the driver's clock mapping and wrap-around.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from pathlib import Path

from hardware import board_protocol as bp

EMULATOR_VERSION = "emu-1.0"


class BoardEmulator:
    """See the module docstring. Times are the host's monotonic clock."""

    def __init__(
        self,
        link: str | os.PathLike[str] | None = None,
        *,
        rate_hz: int = 100,
        cpr: int = 256,
        clock_drift_ppm: float = 0.0,
        t_us_start: int = 0,
        count_offset: int = 0,
        imu: bool = False,
    ) -> None:
        self.link = Path(link) if link is not None else None
        self.rate_hz = rate_hz
        self.cpr = cpr
        self.drift = clock_drift_ppm * 1e-6
        self.t_us_start = t_us_start
        self.count_offset = count_offset
        self.imu = imu
        self._gyro_raw = 0
        self.rx = {"lines": 0, "bad_crc": 0, "malformed": 0, "overflow": 0}
        self.cmd_timeouts = 0
        self.cmd_seq_gaps = 0
        self.commands: list[tuple[float, bp.Brake]] = []  # every valid B line, with its time
        self._lock = threading.Lock()
        self._counts = (0, 0)
        self._base = (0, 0)  # counts at the last reset: reports restart from zero
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self.port = ""
        self._boot(reset_flags=1)
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="board-emulator", daemon=True)
        self._thread.start()

    # -- what the simulated world does ------------------------------------------------
    def set_counts(self, left: int, right: int) -> None:
        """The wheels' cumulative encoder counts now (e.g. the simulator's)."""
        with self._lock:
            self._counts = (int(left), int(right))

    def set_gyro_rate(self, rate_rad_s: float) -> None:
        """The yaw rate the emulated IMU measures now [rad/s] (with `imu=True`)."""
        with self._lock:
            self._gyro_raw = bp.gyro_raw(rate_rad_s)

    def brake_outputs(self) -> tuple[float, int, int]:
        """(time, left duty, right duty) applied now (0 while the command timed out)."""
        with self._lock:
            self._check_timeout(time.monotonic())
            return time.monotonic(), self._pwm[0], self._pwm[1]

    def last_command(self) -> tuple[float, int, int] | None:
        """(time, left duty, right duty) of the last valid brake command (None: none)."""
        with self._lock:
            if not self.commands:
                return None
            t, cmd = self.commands[-1]
            return t, cmd.pwm_left, cmd.pwm_right

    # -- faults -----------------------------------------------------------------------
    def reset(self) -> None:
        """Restart like the MCU after a reset: counts, seq and clock from zero, brakes
        released until the next valid command, a boot handshake line."""
        with self._lock:
            self._boot(reset_flags=2)
            self._base = self._counts
            self._send(self._handshake().line())

    def unplug(self) -> None:
        """Close the pty (the host sees the port disappear); the board keeps running."""
        with self._lock:
            self._close_pty()

    def replug(self) -> None:
        """A new pty at the same path."""
        with self._lock:
            if self._master is None:
                self._open_pty()

    def inject(self, data: bytes) -> None:
        """Raw bytes to the host (garbage, partial lines)."""
        with self._lock:
            self._send(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            self._close_pty()

    def __enter__(self) -> BoardEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals --------------------------------------------------------------------
    def _boot(self, reset_flags: int) -> None:
        self._t0 = time.monotonic()
        self._seq = 0
        self._pwm = (0, 0)
        self._last_cmd = -float("inf")
        self._timed_out = True
        self._last_cmd_seq = 0
        self._reset_flags = reset_flags
        self._next_tick = self._t0
        self._next_status = self._t0 + 1.0
        self._splitter = bp.LineSplitter()

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(self.port)
            tmp.replace(self.link)
            self.port = str(self.link)

    def _close_pty(self) -> None:
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    def _send(self, data: bytes) -> None:
        if self._master is None:
            return
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._master, data)  # nobody listening: dropped, as on a UART

    def _board_us(self, now: float) -> int:
        return (self.t_us_start + round((now - self._t0) * (1.0 + self.drift) * 1e6)) % bp.UINT32

    def _handshake(self) -> bp.Handshake:
        return bp.Handshake(
            bp.PROTOCOL_VERSION,
            EMULATOR_VERSION,
            self.rate_hz,
            self.cpr,
            self._reset_flags,
            bp.GYRO_LSB_PER_10DPS if self.imu else None,
        )

    def _status(self) -> bp.Status:
        return bp.Status(
            self.rx["lines"],
            self.rx["bad_crc"],
            self.rx["malformed"],
            self.rx["overflow"],
            self.cmd_timeouts,
            self.cmd_seq_gaps,
            0,
            self._last_cmd_seq,
        )

    def _check_timeout(self, now: float) -> None:
        # checked every few ms: a little early, so that it releases within the 300 ms
        if not self._timed_out and now - self._last_cmd > bp.COMMAND_TIMEOUT_S - 0.005:
            self._timed_out = True
            self._pwm = (0, 0)
            self.cmd_timeouts += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                now = time.monotonic()
                self._receive(now)
                self._check_timeout(now)
                while now >= self._next_tick:
                    self._tick(self._next_tick)
                    self._next_tick += 1.0 / self.rate_hz
                if now >= self._next_status:
                    self._send(self._status().line())
                    self._next_status += 1.0
                wait = max(0.0, min(self._next_tick, self._next_status) - time.monotonic())
                master = self._master
            if master is None:
                self._stop.wait(min(wait, 0.005))
                continue
            with contextlib.suppress(OSError, ValueError):
                select.select([master], [], [], min(wait, 0.005))

    def _tick(self, at: float) -> None:
        left = (self._counts[0] - self._base[0] + self.count_offset) % bp.UINT32
        right = (self._counts[1] - self._base[1] + self.count_offset) % bp.UINT32
        flags = bp.TICK_TIMEOUT_FLAG if self._timed_out else 0
        tick = bp.Tick(
            self._seq,
            self._board_us(at),
            _int32(left),
            _int32(right),
            self._pwm[0],
            self._pwm[1],
            flags,
            self._gyro_raw if self.imu else None,
        )
        self._send(tick.line())
        self._seq = (self._seq + 1) % bp.UINT32

    def _receive(self, now: float) -> None:
        if self._master is None:
            return
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return
        for item in self._splitter.feed(data):
            if isinstance(item, bp.LineError):
                self.rx[_counter(item)] += 1
                continue
            try:
                msg = bp.parse_host_line(item)
            except bp.LineError as e:
                self.rx[_counter(e)] += 1
                continue
            self.rx["lines"] += 1
            if isinstance(msg, bp.Brake):
                gap = (msg.seq - self._last_cmd_seq - 1) % bp.UINT32
                if self._last_cmd_seq and gap < 1 << 31:
                    self.cmd_seq_gaps += gap
                self._last_cmd_seq = msg.seq
                self._pwm = (msg.pwm_left, msg.pwm_right)
                self._last_cmd, self._timed_out = now, False
                self.commands.append((now, msg))
            elif isinstance(msg, bp.Configure):
                self.rate_hz = msg.rate_hz
                self._send(self._handshake().line())
            else:
                self._send(self._handshake().line())
                self._send(self._status().line())


def _int32(v: int) -> int:
    return v - bp.UINT32 if v >= 1 << 31 else v


def _counter(e: bp.LineError) -> str:
    return {"crc": "bad_crc", "overflow": "overflow"}.get(e.kind, "malformed")
