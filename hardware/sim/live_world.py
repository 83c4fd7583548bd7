"""The simulated walker as a machine of its own, for `walkerslam live --sim`.

    python -m hardware.sim.live_world --dir DIR [--course NAME] [--seed N] [--surface S]
        [--duration S] [--depth-size WxH] [--depth-rate HZ] [--board emulator|firmware]
        [--gyro]

Runs the simulator in real time and exposes it as the real walker is exposed: its board
on a serial port (`DIR/tty`: the pure-Python board emulator, or the compiled firmware
running in simavr with `--board firmware`), whose encoder counts are the simulated
wheels' and whose brake outputs set the simulated brakes; and its cameras and truth on
a stream socket (`DIR/sensors.sock`, `hardware.sim.stream`). `walkerslam live` then
drives it with exactly the drivers and loop it uses on the walker. With `--gyro` the
simulated walker carries its yaw-rate gyro (`hardware.sim.gyro`) as an MPU-6050 on the
board's I²C bus: the board (emulator or firmware) reports the gyro's latest rate with
every tick.

It talks to whoever started it through JSON lines on stdout:

    {"event": "ready", "port": ..., "socket": ..., "physics_rate_hz": ...}
    {"event": "connected"}                      the live process connected to the socket
    {"event": "brakes", "t": mono, "sim_t": s, "board_t": s, "left": duty, "right": duty,
     "last_command_t": s, "last_command_pwm": [l, r]}
                                                every change of the board's brake outputs,
                                                and the last valid command it had received
                                                (board_t, last_command_t: the board's own
                                                clock — simavr's simulated time with the
                                                firmware)
    {"event": "done", "finished": bool, "sim_t": s, "sent": {type: n}, "dropped": {type: n}}
                                                the user finished (or the duration); the
                                                records sent to the live process and the
                                                camera records dropped because it lagged

and it ends on SIGTERM, on a line "quit" or at the end of its standard input — not when
the simulated trial ends, so that the board still answers (and releases the brakes)
while the live process shuts down. Other lines on its standard input inject faults:
"unplug" / "replug" (the board's pty goes away / comes back at the same path), "reset"
(the board restarts), "garble" (noise and bad lines from the board), "stall S" (the
cameras deliver nothing for S seconds).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import select
import signal
import socket
import sys
import threading
import time
from collections import deque
from pathlib import Path

from hardware.messages import (
    BrakeCommand,
    Collision,
    DepthFrame,
    GroundTruthPose,
    GyroRate,
    TagDetections,
)
from hardware.sim import stream
from hardware.sim.gyro import GyroSimConfig
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import load_world

STREAMED = (DepthFrame, TagDetections, GroundTruthPose, Collision)
# what "garble" sends to the host: noise, a line with a bad checksum, an over-long line
GARBAGE = b"\x00\xff\x13noise\nT,1,2,3,4,0,0,0*00\n" + b"#" * 120 + b"\n"


def physics_rate(*rates: int, minimum: int = 200) -> int:
    """The smallest multiple of every sensor rate that is at least `minimum` Hz."""
    lcm = math.lcm(*rates)
    return lcm * math.ceil(minimum / lcm)


def _say(**event) -> None:
    sys.stdout.write(json.dumps(event) + "\n")
    sys.stdout.flush()


def _open_board(kind: str, link: Path, cpr: int, imu: bool = False):
    if kind == "emulator":
        from hardware.board_emulator import BoardEmulator

        return BoardEmulator(link, cpr=cpr, imu=imu)
    if kind == "firmware":
        from hardware.firmware_sim import FirmwareSim

        return FirmwareSim(link=link, imu=imu)
    raise ValueError(f"unknown board {kind!r}; valid: emulator, firmware")


def _parse_size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    sim = Simulator(load_world(args.course), _sim_config(args))
    folder = Path(args.dir)
    folder.mkdir(parents=True, exist_ok=True)
    sock_path = folder / "sensors.sock"
    server = _listen(sock_path)
    board = _open_board(args.board, folder / "tty", sim.calibration.counts_per_rev, args.gyro)
    if sim.gyro is not None:  # at rest until the walk starts, the gyro reads its bias
        board.set_gyro_rate(sim.gyro.bias)
    stop = {"now": False}

    def on_term(*_: object) -> None:
        stop["now"] = True

    signal.signal(signal.SIGTERM, on_term)
    _say(
        event="ready",
        port=str(board.port),
        socket=str(sock_path),
        physics_rate_hz=sim.config.physics_rate_hz,
    )
    try:
        _serve(server, sim, board, stop, args.accept_timeout)
    except (TimeoutError, BrokenPipeError, ConnectionResetError) as e:
        _say(event="error", error=str(e) or type(e).__name__)
    finally:
        # the board stays up until we are told to go (the live process releases the
        # brakes through it, and the firmware's timeout must still run)
        _wait_for_quit(board, stop)
        board.close()
        server.close()
        sock_path.unlink(missing_ok=True)
    return 0


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (see the module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m hardware.sim.live_world", description=__doc__)
    ap.add_argument("--dir", required=True, help="folder for the tty link and the socket")
    ap.add_argument("--course", default="thesis-course")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--surface", default="dusty")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--depth-size", default="160x120")
    ap.add_argument("--depth-rate", type=int, default=10)
    ap.add_argument("--board", default="emulator", choices=("emulator", "firmware"))
    ap.add_argument("--gyro", action="store_true", help="the walker's gyro, on the board")
    ap.add_argument("--accept-timeout", type=float, default=60.0)
    return ap.parse_args(argv)


def _sim_config(args: argparse.Namespace) -> SimConfig:
    """The simulation the command line asks for: a surface name or friction number, the
    depth camera's size and rate, and a physics rate that is a multiple of every sensor's."""
    surface: str | float = args.surface
    with contextlib.suppress(ValueError):
        surface = float(args.surface)
    width, height = _parse_size(args.depth_size)
    base = SimConfig()
    rate = physics_rate(
        base.encoder_rate_hz, args.depth_rate, base.tag_rate_hz, base.groundtruth_rate_hz
    )
    return SimConfig(
        surface=surface,
        seed=args.seed,
        duration_s=args.duration,
        physics_rate_hz=rate,
        depth_rate_hz=args.depth_rate,
        depth_width=width,
        depth_height=height,
        gyro=GyroSimConfig(enabled=args.gyro),
    )


def _listen(sock_path: Path) -> socket.socket:
    """A stream socket listening at sock_path (replacing a stale one) for one client."""
    sock_path.unlink(missing_ok=True)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock_path))
    server.listen(1)
    return server


def _serve(server: socket.socket, sim: Simulator, board, stop: dict, timeout_s: float) -> None:
    """Accept the live process, send it the hello record (calibration and metadata), wait
    for its "go" and run the simulated walker for it until the trial ends or stop."""
    server.settimeout(timeout_s)
    conn, _ = server.accept()
    conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    _say(event="connected")
    hello = {"type": "hello", "calibration": sim.calibration.to_dict(), "metadata": sim.metadata}
    conn.sendall(stream.record(hello))
    # the walker starts when the live process starts reading (it says so)
    conn.settimeout(timeout_s)
    if conn.recv(3) != b"go\n":
        raise ConnectionResetError("the live process did not start reading")
    conn.settimeout(None)
    _run(sim, board, Sender(conn), stop)


class Sender:
    """Sends records from a thread of its own, so that the simulated walker never waits
    for its reader (a real camera does not stop the world either): when the live process
    falls behind by more than `max_frames` camera records, the oldest are dropped
    (counted); truth and collisions are always sent. `ok` turns False when the reader
    went away."""

    def __init__(self, conn: socket.socket, max_frames: int = 8) -> None:
        self.conn = conn
        self.max_frames = max_frames
        self.dropped: dict[str, int] = {}  # per message type
        self.sent: dict[str, int] = {}
        self.ok = True
        self._q: deque[tuple[bool, str, bytes]] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="sensor-sender", daemon=True)
        self._thread.start()

    def send(self, data: bytes, kind: str, frame: bool) -> None:
        with self._cond:
            if frame and sum(f for f, _, _ in self._q) >= self.max_frames:
                oldest = next(i for i, (f, _, _) in enumerate(self._q) if f)
                gone = self._q[oldest][1]
                del self._q[oldest]
                self.dropped[gone] = self.dropped.get(gone, 0) + 1
            self._q.append((frame, kind, data))
            self._cond.notify()

    def close(self) -> None:
        """Send what is queued, then stop."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._q and not self._closed:
                    self._cond.wait()
                if not self._q:
                    return
                _, kind, data = self._q.popleft()
            try:
                self.conn.sendall(data)
            except OSError:
                self.ok = False
                return
            self.sent[kind] = self.sent.get(kind, 0) + 1


def _run(sim: Simulator, board, conn: Sender, stop: dict) -> None:
    cal = sim.calibration.brake
    t0 = time.monotonic()
    step = 1.0 / sim.config.physics_rate_hz
    duties = (-1, -1)
    stalled_until = -math.inf
    while not stop["now"] and not sim.done:
        command = _command()
        if command == "quit":
            stop["now"] = True
            break
        if command.startswith("stall"):
            stalled_until = time.monotonic() + float(command.split()[1])
        elif command in ("unplug", "replug", "reset"):
            getattr(board, command)()
        elif command == "garble":
            board.inject(GARBAGE)
        if command:
            _say(event="injected", what=command, t=time.monotonic())
        target = time.monotonic() - t0
        msgs = sim.poll(min(target, sim.t + 0.02)) if target > sim.t else []
        board.set_counts(*sim.encoders.counts())
        rates = [m.rate_rad_s for m in msgs if isinstance(m, GyroRate)]
        if rates:  # the board reports the latest with its ticks
            board.set_gyro_rate(rates[-1])
        camera_on = time.monotonic() >= stalled_until
        for m in msgs:
            frame = isinstance(m, DepthFrame | TagDetections)
            if frame and not camera_on:
                continue
            if conn.ok and isinstance(m, STREAMED):  # (if the live process went away,
                conn.send(stream.encode(m, t0 + m.t), type(m).__name__, frame)  # it walks on)
        board_t, left, right = board.brake_outputs()
        if (left, right) != duties:
            duties = (left, right)
            sim.send(BrakeCommand(sim.t, cal.torque(left), cal.torque(right), "board"))
            _say_brakes(board, board_t, left, right, sim_t=sim.t)
        ahead = sim.t - (time.monotonic() - t0)
        if ahead > 0:
            time.sleep(min(ahead, step))
    conn.send(stream.record({"type": "end", "finished": bool(sim.user.finished)}), "end", False)
    conn.close()
    _say(
        event="done",
        finished=bool(sim.user.finished),
        sim_t=sim.t,
        sent=conn.sent,
        dropped=conn.dropped,
    )


def _say_brakes(board, board_t: float, left: int, right: int, sim_t: float | None = None) -> None:
    """Tell of new brake outputs of the board (with the simulation's time while it runs)
    and of the last valid command the board had received."""
    times = {"t": time.monotonic()} if sim_t is None else {"t": time.monotonic(), "sim_t": sim_t}
    _say(event="brakes", **times, board_t=board_t, **_last_command(board), left=left, right=right)


def _last_command(board) -> dict:
    """The board's last valid brake command: its time on the board's clock and duties."""
    last = board.last_command()
    if last is None:
        return {"last_command_t": None, "last_command_pwm": None}
    return {"last_command_t": last[0], "last_command_pwm": [last[1], last[2]]}


def _command(timeout: float = 0.0) -> str:
    """The next line of standard input ('' if none is waiting); 'quit' at its end."""
    try:
        ready, _, _ = select.select([sys.stdin], [], [], timeout)
    except (OSError, ValueError):
        return "quit"
    if not ready:
        return ""
    line = sys.stdin.readline()
    return "quit" if line == "" else line.strip()


def _wait_for_quit(board, stop: dict) -> None:
    last = (-1, -1)
    while not stop["now"] and _command(0.02) != "quit":
        board_t, left, right = board.brake_outputs()
        if (left, right) != last:
            last = (left, right)
            _say_brakes(board, board_t, left, right)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
