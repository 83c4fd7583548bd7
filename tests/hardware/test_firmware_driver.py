"""The serial driver (hardware/arduino.py) against the compiled firmware running in simavr,
on the harness's pty as it would open /dev/ttyACM0. Timing is asserted in simulated time
(the harness's clock), never in wall time."""

from __future__ import annotations

import itertools
import threading
import time

import pytest

from hardware import firmware_sim as fs
from hardware.arduino import ArduinoBoard, BoardConfig
from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.messages import BrakeCommand, DeviceEvent, EncoderTicks

CAL = WalkerCalibration()
WAIT_S = 60.0


@pytest.fixture(scope="module")
def firmware_built():
    try:
        fs.build()
    except fs.FirmwareSimError as e:
        pytest.fail(f"cannot build the board firmware and its simavr harness: {e}")


@pytest.fixture
def sim(firmware_built, tmp_path):
    with fs.FirmwareSim(link=tmp_path / "ttyACM0", timeout_s=WAIT_S) as s:
        s.wait_for(lambda e: e.kind == "tx" or e.kind == "ready")
        yield s


class Driver:
    def __init__(self, port, **cfg):
        self.board = ArduinoBoard(port, CAL, HostClock(), BoardConfig(**cfg))
        self.handshake = self.board.open()
        self.msgs = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for m in self.board.messages():
            self.msgs.append(m)

    def last(self):
        ticks = [m for m in self.msgs if isinstance(m, EncoderTicks)]
        return ticks[-1] if ticks else None

    def wait(self, cond, what):
        deadline = time.monotonic() + WAIT_S
        while not cond():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            time.sleep(0.005)

    def events(self, kind):
        return [m for m in self.msgs if isinstance(m, DeviceEvent) and m.event == kind]

    def close(self):
        self.board.close()
        self.thread.join(10.0)


def test_driver_handshakes_and_counts_exact_edges(sim):
    d = Driver(sim.port)
    assert (d.handshake.proto, d.handshake.rate_hz, d.handshake.cpr) == (1, 100, 256)
    assert d.handshake.reset_cause == "power-on"
    d.wait(lambda: d.last() is not None, "a tick")
    sim.steps("L", 700, 50, wait=True)
    sim.steps("R", -313, 50, wait=True)
    sim.steps("L", -45, 50, wait=True)
    d.wait(lambda: (d.last().left, d.last().right) == (655, -313), "the counts")
    d.close()
    st = d.board.stats
    # (at most the line the board was sending when the port opened: its tail is a bad line)
    assert st.bad_lines <= 1 and st.seq_gaps == 0 and st.resets == 0
    assert d.board.metadata["board"]["firmware"] == d.handshake.firmware


def test_driver_commands_are_applied_held_and_released_on_close(sim):
    d = Driver(sim.port)
    brake = CAL.brake
    m = sim.mark()
    d.board.send(BrakeCommand(0.0, 2.5, 1.0))
    ev = sim.wait_for(lambda e: e.kind == "brake", since=m)
    assert (int(ev.args[0]), int(ev.args[1])) == (brake.pwm(2.5), brake.pwm(1.0))
    # the driver's re-sends keep the brakes on for 1.5 s of simulated time (the board
    # alone would release them after 0.3 s)
    t_on = ev.t_ns
    sim.wait_until(t_on + 1_500_000_000)
    assert sim.brake_outputs()[1:] == (brake.pwm(2.5), brake.pwm(1.0))
    assert not [e for e in sim.events(since=m, kind="brake") if e.t_ns > t_on]
    m = sim.mark()
    d.close()
    off = sim.wait_for(lambda e: e.kind == "brake", since=m)
    assert off.args[2:4] == ("0", "0")  # zero on close: outputs disconnected
    # and it was the driver's command, not the board's timeout
    nl = sim.events(since=m, kind="rx-nl")
    assert nl and off.t_ns - nl[-1].t_ns < 5_000_000


def test_board_reset_mid_run_no_odometry_jump(sim):
    d = Driver(sim.port)
    sim.steps("L", 400, 40, wait=True)
    sim.steps("R", 380, 40, wait=True)
    d.wait(lambda: d.last() is not None and d.last().right == 380, "counts before")
    sim.reset()  # counts and sequence restart in the firmware
    d.wait(lambda: d.events("reset"), "the reset detected")
    sim.steps("L", 30, 40, wait=True)  # the wheels roll on after the restart
    d.wait(lambda: d.last().left == 430, "counts after")
    d.close()
    ticks = [m for m in d.msgs if isinstance(m, EncoderTicks)]
    lefts = [t.left for t in ticks]
    assert min(lefts[lefts.index(400) :]) == 400  # never back towards zero
    assert ticks[-1].right == 380
    assert all(b.t >= a.t for a, b in itertools.pairwise(ticks))
    assert d.board.stats.resets == 1


def test_unplugged_board_releases_and_the_driver_reconnects(sim):
    d = Driver(sim.port, reconnect_poll_s=0.05)
    d.wait(lambda: d.last() is not None, "a tick")
    m = sim.mark()
    d.board.send(BrakeCommand(0.0, 3.0, 3.0))
    on = sim.wait_for(lambda e: e.kind == "brake", since=m)
    sim.unplug()
    d.wait(lambda: d.events("disconnected"), "disconnected")
    # nobody can reach the board: its own timeout releases both brakes 300 ms (of
    # simulated time) after the last command line reached it
    off = sim.wait_for(lambda e: e.kind == "brake" and e.args[2:4] == ("0", "0"), since=m)
    last_nl = [e for e in sim.events(since=m, kind="rx-nl") if e.t_ns < off.t_ns][-1]
    assert 298e6 <= off.t_ns - last_nl.t_ns <= 300e6  # within 300 ms of simulated time
    assert off.t_ns > on.t_ns
    sim.steps("L", 50, 40, wait=True)  # the walker moves while unplugged
    m = sim.mark()
    sim.replug()
    d.wait(lambda: d.events("rebased"), "the first report after the gap")
    assert "turned 50, 0 counts" in d.events("rebased")[0].detail
    # the driver still wants braking: its re-sends apply it again
    again = sim.wait_for(lambda e: e.kind == "brake" and e.args[2] != "0", since=m)
    assert again.t_ns > off.t_ns
    d.close()
    assert d.board.stats.reconnects == 1 and d.board.stats.resets == 0


def test_garbage_from_the_board_is_counted_by_the_driver(sim):
    d = Driver(sim.port)
    d.wait(lambda: d.board.stats.ticks > 5, "ticks")
    sim.inject(b"\x00\xffnoise\nT,1,2,3,4,0,0,0*00\n" + b"#" * 150 + b"\n")
    n = d.board.stats.ticks
    d.wait(lambda: d.board.stats.ticks > n + 50, "ticks after the garbage")
    st = d.board.stats
    assert st.bad_crc >= 1 and st.overflow >= 1 and st.malformed >= 1
    d.close()
