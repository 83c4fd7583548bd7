"""The walker board's real firmware on a simulated ATmega328P (simavr), behind a pty.

`FirmwareSim` starts `hardware/firmware/build/board_sim` (the C harness in
`hardware/firmware/simavr/board_sim.c`) on `walker_board.elf`. The firmware's UART is
bridged to a pseudo-terminal whose slave is symlinked at `.port`, so a serial driver
(`hardware.arduino`, or pyserial directly) opens it as it would `/dev/ttyACM0`; the
harness drives the encoder pins and watches the brake outputs, and the wrapper talks to
it over its control channel (its syntax is documented at the top of board_sim.c):

    with FirmwareSim() as sim:                   # builds the firmware if needed
        port = serial.Serial(sim.port, 115200, timeout=1.0)
        sim.steps("L", 1000, period_us=100, wait=True)   # 1000 edges, forward
        sim.set_counts(1200, -40)                # the live simulation's true counts
        t, left, right = sim.brake_outputs()     # simulated time (s), duties 0-255

Times are the simulated MCU's (nanoseconds since power-on in events, seconds in
`sim_time()` and `brake_outputs()`): assert timing in those, never in wall-clock time.
The harness runs paced to the wall clock (`speed` 1.0 by default), slower when the host
cannot keep up. Events (`SimEvent`) arrive asynchronously and are kept in order; wait
for one with `wait_for(predicate, timeout, since=mark)`, where `mark()` taken before
the action makes sure an event that arrives early is not missed:

    m = sim.mark()
    port.write(Brake(1, 120, 0).line())
    ev = sim.wait_for(lambda e: e.kind == "brake" and e.args[0] == "120", since=m)
    sim.wait_until(ev.t_ns + 300_000_000)     # an alarm in simulated time, not a sleep

Event kinds (args are strings): "rx-nl" (n) each newline handed to the AVR's UART,
"brake" (ocr1a, ocr1b, com1a, com1b) each change of the brake outputs, "tx" (the line)
each line the AVR transmitted while `tx_events` is on, "reset" (MCUSR flags),
"done" (wheel, position) the end of a `steps`, "plug" (0/1, slave), "alarm" (id),
"halt" (simavr state) and "ready".

Wheel positions (`counts()`, `set_counts`) are the edges the harness generated since it
started, the encoders' "true" counts; the board counts from 0 again after a reset.

With `imu=True` the harness puts an MPU-6050 on the AVR's I²C bus (TWI); `set_gyro` /
`set_gyro_rate` set the z rate it outputs, `imu_registers()` what the firmware wrote.

`build()` runs `make -C hardware/firmware` when an output is missing or older than its
sources; it raises FirmwareSimError with one line naming the Debian package to install
when avr-gcc or the simavr headers are missing.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hardware import board_protocol as bp

FIRMWARE_DIR = Path(__file__).resolve().parent / "firmware"
BUILD_DIR = FIRMWARE_DIR / "build"
HARNESS = BUILD_DIR / "board_sim"
FIRMWARE_ELF = BUILD_DIR / "walker_board.elf"
FIRMWARE_HEX = BUILD_DIR / "walker_board.hex"
# the same firmware plus the test-only `X,1` line that hangs the MCU (watchdog tests)
TEST_FIRMWARE_ELF = BUILD_DIR / "walker_board_test.elf"
_SOURCES = (
    FIRMWARE_DIR / "walker_board.c",
    FIRMWARE_DIR / "simavr" / "board_sim.c",
    FIRMWARE_DIR / "Makefile",
)
_OUTPUTS = (HARNESS, FIRMWARE_ELF, FIRMWARE_HEX, TEST_FIRMWARE_ELF)
_MAX_EVENTS = 200_000  # kept; the oldest half is dropped beyond that


class FirmwareSimError(RuntimeError):
    """The harness cannot be built, started or talked to (one line)."""


def _stale() -> bool:
    newest = max(p.stat().st_mtime for p in _SOURCES)
    return any(not p.exists() or p.stat().st_mtime < newest for p in _OUTPUTS)


def build(force: bool = False) -> None:
    """Build the firmware and the harness (make -C hardware/firmware) if they are
    missing or older than their sources."""
    if not force and not _stale():
        return
    if shutil.which("make") is None:
        raise FirmwareSimError("make not found: install the Debian package make")
    if shutil.which("avr-gcc") is None:
        raise FirmwareSimError(
            "avr-gcc not found: install the Debian packages gcc-avr avr-libc binutils-avr "
            "(make system-deps)"
        )
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    with open(BUILD_DIR / ".lock", "w") as lock:  # several test processes may build
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not force and not _stale():
            return
        r = subprocess.run(
            ["make", "-C", str(FIRMWARE_DIR)], capture_output=True, text=True, check=False
        )
    if r.returncode != 0:
        lines = (r.stdout + r.stderr).splitlines()
        errors = [ln for ln in lines if ln.startswith("error:")]
        why = errors[0] if errors else " | ".join(lines[-3:])
        raise FirmwareSimError(f"building the firmware failed: {why}")


@dataclass(frozen=True, slots=True)
class SimEvent:
    """An asynchronous line of the harness: 'E <t_ns> <kind> <args...>'."""

    t_ns: int
    kind: str
    args: tuple[str, ...]
    text: str  # everything after the kind (a "tx" event's whole line)

    @property
    def t(self) -> float:
        """Simulated time in seconds."""
        return self.t_ns * 1e-9


@dataclass(frozen=True, slots=True)
class BrakeState:
    """The brake outputs now: Timer1's compare registers, its compare output modes
    (COM1x: 0 disconnected, 2 non-inverting PWM), the duty measured on the pins PB1/PB2
    over the last PWM period (fraction high, 0-1; the level while the pin is still),
    their levels and PWM frequencies (0 while still)."""

    t_ns: int
    ocr_left: int
    ocr_right: int
    com_left: int
    com_right: int
    pin_duty_left: float
    pin_duty_right: float
    pin_left: int
    pin_right: int
    pin_hz_left: float
    pin_hz_right: float

    @property
    def left(self) -> int:
        """The duty the left brake gets (0-255): OCR1A while its output is connected."""
        return self.ocr_left if self.com_left else 0

    @property
    def right(self) -> int:
        return self.ocr_right if self.com_right else 0


class _Reply:
    __slots__ = ("done", "text")

    def __init__(self) -> None:
        self.done = threading.Event()
        self.text = ""


class FirmwareSim:
    """See the module docstring.

    link: where the pty's symlink goes (a temporary folder if None). elf: the firmware
    (FIRMWARE_ELF; TEST_FIRMWARE_ELF has the watchdog-test hang). speed: simulated per
    wall-clock time (0: as fast as possible). tx_events: report every line the AVR sends
    as a "tx" event. edge_rate_hz: the fastest `set_counts` moves a wheel. timeout_s:
    the wall-clock limit of every wait for the harness (generous: a loaded machine).
    imu: an MPU-6050 on the I²C bus (without it nobody answers there)."""

    def __init__(
        self,
        link: str | os.PathLike[str] | None = None,
        *,
        elf: str | os.PathLike[str] | None = None,
        speed: float = 1.0,
        tx_events: bool = False,
        edge_rate_hz: float = 10_000.0,
        build_if_needed: bool = True,
        timeout_s: float = 30.0,
        imu: bool = False,
    ) -> None:
        if build_if_needed:
            build()
        if not HARNESS.exists():
            raise FirmwareSimError(f"{HARNESS} is missing: run make -C {FIRMWARE_DIR}")
        self.elf = Path(elf) if elf is not None else FIRMWARE_ELF
        self.timeout_s = timeout_s
        self._tmp: tempfile.TemporaryDirectory | None = None
        if link is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="walker-board-")
            link = Path(self._tmp.name) / "tty"
        self.link = Path(link)
        self.port = str(self.link)
        self._events: list[SimEvent] = []
        self._events_base = 0  # absolute index of self._events[0]
        self._cond = threading.Condition()
        self._pending: deque[_Reply | None] = deque()
        self._write_lock = threading.Lock()
        self._async_error: str | None = None
        self._dead: str | None = None
        self._stderr: deque[str] = deque(maxlen=20)
        args = [str(HARNESS), "-s", str(speed), "-r", str(edge_rate_hz), "-l", self.port]
        if tx_events:
            args.append("-t")
        if imu:
            args.append("-i")
        args.append(str(self.elf))
        self._proc = subprocess.Popen(
            args,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self._reader = threading.Thread(target=self._read, name="board-sim-out", daemon=True)
        self._reader.start()
        self._errs = threading.Thread(target=self._read_err, name="board-sim-err", daemon=True)
        self._errs.start()
        try:
            self.wait_for(lambda e: e.kind == "ready", timeout=timeout_s)
        except BaseException:
            self.close()
            raise

    # -- the control channel ---------------------------------------------------------
    def _read(self) -> None:
        assert self._proc.stdout is not None
        for raw in self._proc.stdout:
            line = raw.rstrip("\n")
            if line.startswith("E "):
                self._add_event(line)
            elif line.startswith(("OK", "ERR")):
                with self._cond:
                    slot = self._pending.popleft() if self._pending else None
                if slot is None:
                    if line.startswith("ERR"):
                        self._async_error = line[4:]
                else:
                    slot.text = line
                    slot.done.set()
        with self._cond:
            self._dead = self._dead or "the harness exited"
            for slot in self._pending:
                if slot is not None:
                    slot.done.set()
            self._pending.clear()
            self._cond.notify_all()

    def _read_err(self) -> None:
        assert self._proc.stderr is not None
        for line in self._proc.stderr:
            self._stderr.append(line.rstrip())

    def _add_event(self, line: str) -> None:
        parts = line.split(" ", 3)
        if len(parts) < 3:
            return
        text = parts[3] if len(parts) > 3 else ""
        ev = SimEvent(int(parts[1]), parts[2], tuple(text.split()), text)
        with self._cond:
            self._events.append(ev)
            if len(self._events) > _MAX_EVENTS:
                drop = _MAX_EVENTS // 2
                del self._events[:drop]
                self._events_base += drop
            self._cond.notify_all()

    def _why_dead(self) -> str:
        if self._proc.poll() is not None:
            self._errs.join(timeout=1.0)  # its last words
        tail = " | ".join(self._stderr)
        return f"{self._dead}" + (f" ({tail})" if tail else "")

    def _send(self, line: str, wait: bool) -> _Reply | None:
        slot = _Reply() if wait else None
        with self._write_lock:
            if self._dead:
                raise FirmwareSimError(f"board_sim is not running: {self._why_dead()}")
            with self._cond:
                self._pending.append(slot)
            try:
                assert self._proc.stdin is not None
                self._proc.stdin.write(line + "\n")
                self._proc.stdin.flush()
            except (BrokenPipeError, OSError, ValueError) as e:
                raise FirmwareSimError(f"board_sim is not running: {e}") from None
        return slot

    def _request(self, line: str) -> list[str]:
        """Send a command, wait for its reply; the reply's fields after OK.

        A refusal of an earlier command that did not wait is raised here, after the
        reply: board_sim answers in order, so by then it has always been read."""
        slot = self._send(line, wait=True)
        assert slot is not None
        if not slot.done.wait(self.timeout_s):
            raise FirmwareSimError(f"board_sim did not answer {line!r} in {self.timeout_s} s")
        if self._async_error:
            err, self._async_error = self._async_error, None
            raise FirmwareSimError(f"board_sim refused an earlier command: {err}")
        if not slot.text:
            raise FirmwareSimError(f"board_sim is not running: {self._why_dead()}")
        if slot.text.startswith("ERR"):
            raise FirmwareSimError(f"board_sim: {slot.text[4:]}")
        return slot.text.split()[1:]

    # -- events ----------------------------------------------------------------------
    def mark(self) -> int:
        """The index the next event will have (for `since=`)."""
        with self._cond:
            return self._events_base + len(self._events)

    def events(self, since: int = 0, kind: str | None = None) -> list[SimEvent]:
        """The events kept from index `since` on (optionally of one kind)."""
        with self._cond:
            start = max(0, since - self._events_base)
            evs = self._events[start:]
        return [e for e in evs if kind is None or e.kind == kind]

    def wait_for(
        self,
        predicate: Callable[[SimEvent], bool],
        timeout: float | None = None,
        since: int = 0,
    ) -> SimEvent:
        """The first event from index `since` on that satisfies `predicate`; waits for
        it at most `timeout` wall-clock seconds (default `timeout_s`)."""
        deadline = time.monotonic() + (self.timeout_s if timeout is None else timeout)
        i = since
        with self._cond:
            while True:
                start = max(i, self._events_base)
                for j in range(start - self._events_base, len(self._events)):
                    if predicate(self._events[j]):
                        return self._events[j]
                i = self._events_base + len(self._events)
                if self._dead:
                    raise FirmwareSimError(f"board_sim is not running: {self._why_dead()}")
                left = deadline - time.monotonic()
                if left <= 0:
                    last = "; ".join(f"{e.t_ns} {e.kind} {e.text}" for e in self._events[-4:])
                    raise TimeoutError(f"the awaited harness event did not come (last: {last})")
                self._cond.wait(left)

    def wait_sim(self, seconds: float, timeout: float | None = None) -> int:
        """Wait until `seconds` more of simulated time have passed; the sim time (ns)."""
        return self.wait_until(self.sim_time_ns() + round(seconds * 1e9), timeout)

    def wait_until(self, t_ns: int, timeout: float | None = None) -> int:
        """Wait until the simulated time reaches t_ns (an alarm in the harness)."""
        m = self.mark()
        (alarm_id,) = self._request(f"alarm {int(t_ns)}")
        ev = self.wait_for(
            lambda e: e.kind == "alarm" and e.args[0] == alarm_id, timeout=timeout, since=m
        )
        return ev.t_ns

    # -- time, encoders, brakes ------------------------------------------------------
    def sim_time_ns(self) -> int:
        return int(self._request("time")[0])

    def sim_time(self) -> float:
        """Simulated time since power-on, seconds."""
        return self.sim_time_ns() * 1e-9

    def steps(self, wheel: str, n: int, period_us: float, wait: bool = False) -> SimEvent | None:
        """|n| quadrature edges on wheel "L" or "R" (forward if n > 0), one every
        period_us of simulated time, after those already queued. wait: until the last
        edge is out (the "done" event)."""
        m = self.mark()
        self._request(f"steps {_wheel(wheel)} {int(n)} {float(period_us)}")
        if not wait:
            return None
        w = _wheel(wheel)
        return self.wait_for(lambda e: e.kind == "done" and e.args[0] == w, since=m)

    def set_counts(self, left: int, right: int, max_rate_hz: float | None = None) -> None:
        """Move the wheels to these positions (edges at up to max_rate_hz, default the
        constructor's edge_rate_hz). Does not wait for the harness: cheap at 100-200 Hz;
        a refusal is raised by the next call that waits."""
        rate = "" if max_rate_hz is None else f" {float(max_rate_hz)}"
        self._send(f"goto {int(left)} {int(right)}{rate}", wait=False)

    def counts(self) -> tuple[int, int]:
        """The wheels' positions now (edges generated so far)."""
        f = self._request("counts")
        return int(f[0]), int(f[1])

    def glitch(self, wheel: str) -> int:
        """Flip both lines of a wheel at once (a quadrature error for the board)."""
        return int(self._request(f"glitch {_wheel(wheel)}")[0])

    def brake_state(self) -> BrakeState:
        f = self._request("brakes")
        return BrakeState(
            int(f[0]),
            int(f[1]),
            int(f[2]),
            int(f[3]),
            int(f[4]),
            float(f[5]),
            float(f[6]),
            int(f[7]),
            int(f[8]),
            float(f[9]),
            float(f[10]),
        )

    def brake_outputs(self) -> tuple[float, int, int]:
        """(simulated time in s since when, left duty, right duty) applied now (0 while a
        compare output is disconnected): the time is that of the change to these duties,
        not of this call, however late the host asks."""
        s = self.brake_state()
        changes = self.events(kind="brake")  # all read by now: the harness answers in order
        t_ns = s.t_ns
        if changes:
            a, b, com_a, com_b = (int(v) for v in changes[-1].args[:4])
            if ((a if com_a else 0), (b if com_b else 0)) == (s.left, s.right):
                t_ns = changes[-1].t_ns
        return t_ns * 1e-9, s.left, s.right

    def uart_config(self) -> tuple[int, bool, float, int]:
        """The firmware's UART0 setting: (UBRR0, U2X0, baud, simavr cycles per byte)."""
        f = self._request("uart")
        return int(f[0]), f[1] == "1", float(f[2]), int(f[3])

    def stats(self) -> dict[str, int]:
        """sim_ns, wall_ns (since the harness started), rx_bytes, tx_bytes, rx_dropped,
        tx_dropped."""
        names = ("sim_ns", "wall_ns", "rx_bytes", "tx_bytes", "rx_dropped", "tx_dropped")
        return dict(zip(names, (int(v) for v in self._request("stats")), strict=True))

    def set_tx_events(self, on: bool) -> None:
        self._request("tx on" if on else "tx off")

    def last_command(self) -> tuple[float, int, int] | None:
        """The last line the board received (time its newline reached the UART, in
        simulated s) and the duties right after it (the firmware applies a brake command
        0.26 ms after its newline); None before any."""
        received = self.events(kind="rx-nl")
        if not received:
            return None
        t_ns = received[-1].t_ns
        left = right = 0
        for e in self.events(kind="brake"):
            if e.t_ns > t_ns + 1_000_000:
                break
            a, b, com_a, com_b = (int(v) for v in e.args[:4])
            left, right = (a if com_a else 0), (b if com_b else 0)
        return t_ns * 1e-9, left, right

    # -- the IMU (imu=True) ----------------------------------------------------------
    def set_gyro(self, raw: int) -> None:
        """The IMU's z-rate output from now on, in LSB (int16). Does not wait for the
        harness (as set_counts); a refusal is raised by the next call that waits."""
        self._send(f"gyro {int(raw)}", wait=False)

    def set_gyro_rate(self, rate_rad_s: float) -> None:
        """The yaw rate the IMU measures now [rad/s] (131 LSB per °/s, as configured)."""
        self.set_gyro(bp.gyro_raw(rate_rad_s))

    def imu_registers(self) -> dict[str, int]:
        """What the firmware set in the IMU (pwr_mgmt_1, smplrt_div, config, gyro_config)
        and how often it read GYRO_ZOUT_H (gz_reads)."""
        names = ("pwr_mgmt_1", "smplrt_div", "config", "gyro_config", "gz_reads")
        return dict(zip(names, (int(v) for v in self._request("imu")), strict=True))

    # -- faults ----------------------------------------------------------------------
    def inject(self, data: bytes) -> None:
        """Bytes to the host as if the board had sent them (garbage on the line)."""
        self._request(f"inject {bytes(data).hex()}")

    def reset(self) -> int:
        """An external reset of the MCU (the pins keep their levels); its sim time (ns)."""
        return int(self._request("reset")[0])

    def unplug(self) -> None:
        """Close the pty: the driver's port fails and the symlink disappears; the MCU
        keeps running."""
        self._request("unplug")

    def replug(self) -> str:
        """A new pty at the same symlink; the new slave's path."""
        return self._request("replug")[0]

    # -- life ------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the harness (quit, then SIGTERM, then SIGKILL)."""
        proc = self._proc
        if proc.poll() is None:
            with contextlib.suppress(Exception):
                self._send("quit", wait=False)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        for thread in (self._reader, self._errs):
            thread.join(timeout=5)
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            with contextlib.suppress(Exception):
                if stream is not None:
                    stream.close()
        self._dead = self._dead or "closed"
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> FirmwareSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _wheel(wheel: str) -> str:
    w = wheel.upper()[:1]
    if w not in ("L", "R"):
        raise ValueError(f"wheel must be 'L' or 'R', not {wheel!r}")
    return w
