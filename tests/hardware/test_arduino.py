"""The serial driver against the pure-Python board emulator on a real pseudo-terminal.
(The same driver against the compiled firmware in simavr: test_firmware_driver.py.)"""

from __future__ import annotations

import itertools
import os
import threading
import time
import tty

import pytest

from hardware.arduino import ArduinoBoard, BoardConfig, BoardError
from hardware.board_emulator import BoardEmulator
from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.messages import BrakeCommand, DeviceEvent, EncoderTicks, GyroRate

CAL = WalkerCalibration()


def wait_for(cond, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.005)
    raise AssertionError(f"timed out waiting for {what}")


class Running:
    """A board whose messages() is read by a thread into a list."""

    def __init__(self, port, **cfg):
        self.board = ArduinoBoard(port, CAL, HostClock(), BoardConfig(**cfg))
        self.handshake = self.board.open()
        self.msgs: list = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for m in self.board.messages():
            self.msgs.append(m)

    def ticks(self):
        return [m for m in self.msgs if isinstance(m, EncoderTicks)]

    def events(self, kind=None):
        return [m for m in self.msgs if isinstance(m, DeviceEvent) and kind in (None, m.event)]

    def close(self):
        self.board.close()
        self.thread.join(timeout=5.0)
        assert not self.thread.is_alive()


@pytest.fixture
def emulator(tmp_path):
    emu = BoardEmulator(tmp_path / "tty")
    yield emu
    emu.close()


def test_handshake_counts_and_wrap_arounds(tmp_path):
    emulator = BoardEmulator(tmp_path / "tty", t_us_start=2**32 - 300_000, count_offset=2**31 - 40)
    run = Running(emulator.port)
    assert run.handshake.firmware == "emu-1.0" and run.handshake.rate_hz == 100
    assert run.board.metadata["board"]["counts_per_rev"] == 256
    assert run.events("connected")
    # the board's int32 counts wrap (they start 40 below 2^31) and so does its µs clock
    # (0.3 s below 2^32): the driver's counts follow the wheels exactly
    off = 2**31 - 40
    for i in range(1, 61):
        emulator.set_counts(5 * i, -3 * i)
        wait_for(lambda i=i: run.ticks() and run.ticks()[-1].left == off + 5 * i, what=f"{i}")
    run.close()
    ticks = run.ticks()
    assert ticks[-1].left == off + 300 and ticks[-1].right == off - 180
    pairs = {(t.left - off, t.right - off) for t in ticks}
    assert pairs <= {(0, 0)} | {(5 * i, -3 * i) for i in range(1, 61)}
    assert all(b.t >= a.t for a, b in itertools.pairwise(ticks))
    st = run.board.stats
    assert st.bad_lines == 0 and st.seq_gaps == 0 and st.resets == 0
    assert st.last_tick.left < 0  # the raw counter did wrap
    assert st.last_tick.t_us < 2**31  # and so did the board's clock (from 0.3 s below 2^32)
    emulator.close()


def test_garbage_from_the_board_is_counted_and_skipped(emulator):
    run = Running(emulator.port)
    wait_for(lambda: len(run.ticks()) > 5)
    emulator.inject(b"\x00\xff garbage\n")  # malformed
    emulator.inject(b"T,1,2,3,4,0,0,0*00\n")  # bad checksum
    emulator.inject(b"Q" * 300 + b"\n")  # overflow
    emulator.inject(b"T,5,5,5")  # a partial line, completed by the next report
    n = len(run.ticks())
    wait_for(lambda: len(run.ticks()) > n + 20, what="ticks after the garbage")
    st = run.board.stats
    # the partial line swallowed the start of the next report: one more bad checksum,
    # and that report is missing from the sequence
    assert (st.bad_crc, st.overflow, st.malformed, st.seq_gaps) == (2, 1, 1, 1)
    run.close()


def test_board_reset_mid_run_rebases_the_counts(emulator):
    run = Running(emulator.port)
    emulator.set_counts(400, 380)
    wait_for(lambda: run.ticks() and run.ticks()[-1].left == 400)
    emulator.reset()  # counts, seq and clock restart at zero
    wait_for(lambda: run.events("reset"), what="reset event")
    emulator.set_counts(450, 420)  # the wheels roll on: +50, +40 since the reset
    wait_for(lambda: run.ticks()[-1].left == 450, what="counts after the reset")
    run.close()
    assert run.ticks()[-1].right == 420
    lefts = [t.left for t in run.ticks()]
    assert min(lefts[lefts.index(400) :]) == 400  # no jump back to zero
    assert run.board.stats.resets == 1
    ts = [t.t for t in run.ticks()]
    assert all(b >= a for a, b in itertools.pairwise(ts))


def test_unplug_marks_the_gap_and_reconnects(emulator):
    run = Running(emulator.port, reconnect_poll_s=0.05)
    emulator.set_counts(100, 100)
    wait_for(lambda: run.ticks() and run.ticks()[-1].left == 100)
    run.board.send(BrakeCommand(0.0, 2.0, 2.0))
    wait_for(lambda: emulator.brake_outputs()[1] > 0, what="brakes on")
    emulator.unplug()
    wait_for(lambda: run.events("disconnected"), what="disconnected event")
    # nobody can command the board now: its 300 ms timeout releases the brakes
    wait_for(lambda: emulator.brake_outputs()[1:] == (0, 0), what="brakes released")
    emulator.set_counts(130, 125)  # the walker moved while unplugged
    emulator.replug()
    wait_for(lambda: run.events("rebased"), what="the first report after the gap")
    # the host still wants braking: its re-sends apply it again after the reconnect
    wait_for(lambda: emulator.brake_outputs()[1] > 0, what="brakes applied again")
    st = run.board.stats
    assert st.disconnects == 1 and st.reconnects == 1 and st.resets == 0
    assert st.seq_gaps == 0  # reports lost while unplugged are the gap, not errors
    ev = [m.event for m in run.events()]
    assert ev == ["connected", "disconnected", "reconnected", "rebased"]
    # the counts are re-based across the gap: no motion, no jump; what the wheels turned
    # meanwhile is in the event
    assert run.ticks()[-1].left == 100 and run.ticks()[-1].right == 100
    assert "turned 30, 25 counts" in run.events("rebased")[0].detail
    emulator.set_counts(140, 130)
    wait_for(lambda: run.ticks()[-1].left == 110, what="counting on after the gap")
    assert run.ticks()[-1].right == 105
    run.close()


def test_gap_motion_keep_integrates_what_the_wheels_turned(emulator):
    run = Running(emulator.port, reconnect_poll_s=0.05, gap_motion="keep")
    emulator.set_counts(100, 100)
    wait_for(lambda: run.ticks() and run.ticks()[-1].left == 100)
    emulator.unplug()
    wait_for(lambda: run.events("disconnected"))
    emulator.set_counts(130, 125)
    emulator.replug()
    wait_for(lambda: run.ticks()[-1].left == 130, what="counts after the gap")
    assert run.ticks()[-1].right == 125
    assert "turned 30, 25 counts" in run.events("gap-motion")[0].detail
    run.close()


def test_brake_commands_are_resent_while_non_zero_and_zero_on_close(emulator):
    run = Running(emulator.port, resend_hz=20.0)
    brake = CAL.brake
    run.board.send(BrakeCommand(0.0, 1.5, 0.068))
    wait_for(lambda: len(emulator.commands) >= 15, what="re-sent commands")
    applied = {(c.pwm_left, c.pwm_right) for _, c in emulator.commands}
    assert applied == {(brake.pwm(1.5), 0)}
    # re-sent at least every 0.1 s of the board's own time (it reports 100 ticks per s)
    n0, t0 = len(emulator.commands), run.board.stats.ticks
    wait_for(lambda: run.board.stats.ticks >= t0 + 100, what="a second of ticks")
    assert len(emulator.commands) - n0 >= 10
    # a zero command is sent once and not repeated
    run.board.send(BrakeCommand(0.0, 0.068, 0.068))
    wait_for(lambda: emulator.commands[-1][1].pwm_left == 0)
    n = len(emulator.commands)
    t1 = run.board.stats.ticks
    wait_for(lambda: run.board.stats.ticks >= t1 + 30)
    assert len(emulator.commands) == n
    run.board.send(BrakeCommand(0.0, 3.0, 3.0))
    wait_for(lambda: emulator.brake_outputs()[1] == brake.pwm(3.0))
    run.close()
    wait_for(lambda: emulator.brake_outputs()[1:] == (0, 0), what="zero on close")
    assert emulator.commands[-1][1].pwm_left == 0
    seqs = [c.seq for _, c in emulator.commands]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


def test_bad_ports_give_one_line_errors(tmp_path):
    with pytest.raises(BoardError, match="cannot open the serial port") as e:
        ArduinoBoard(str(tmp_path / "nothing"), CAL).open()
    assert "\n" not in str(e.value)
    # a port where nobody speaks the protocol
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        cfg = BoardConfig(handshake_timeout_s=0.2, handshake_attempts=2)
        with pytest.raises(BoardError, match="no handshake"):
            ArduinoBoard(os.ttyname(slave), CAL, config=cfg).open()
    finally:
        os.close(master)
        os.close(slave)


def test_firmware_with_other_counts_per_revolution_is_refused(tmp_path):
    with BoardEmulator(tmp_path / "tty", cpr=1024) as emu:
        with pytest.raises(BoardError, match="1024 per wheel revolution"):
            ArduinoBoard(emu.port, CAL).open()
        b = ArduinoBoard(emu.port, CAL, config=BoardConfig(check_cpr=False))
        assert b.open().cpr == 1024
        b.close()


def test_resend_rate_must_feed_the_board_timeout():
    with pytest.raises(ValueError, match="resend_hz"):
        BoardConfig(resend_hz=3.0)


def test_an_emulated_imu_gives_gyro_rates_before_their_ticks(tmp_path):
    with BoardEmulator(tmp_path / "tty", imu=True) as emu:
        emu.set_gyro_rate(-0.75)
        run = Running(emu.port, gyro_sign=-1)  # an IMU mounted upside down
        assert run.handshake.gyro_lsb_per_10dps == 1310
        wait_for(lambda: sum(isinstance(m, GyroRate) for m in run.msgs) >= 20, what="gyro")
        run.close()
    msgs = run.msgs
    pairs = [(a, b) for a, b in itertools.pairwise(msgs) if isinstance(a, GyroRate)]
    assert len(pairs) >= 20
    for gyro, ticks in pairs:
        assert isinstance(ticks, EncoderTicks) and gyro.t == ticks.t
        assert gyro.rate_rad_s == pytest.approx(0.75, abs=1.4e-4)  # sign flipped, 1 LSB
    connected = run.events("connected")[0].detail
    assert "a gyro" in connected


def test_a_board_without_an_imu_gives_no_gyro_rates(emulator):
    run = Running(emulator.port)
    assert run.handshake.gyro_lsb_per_10dps is None
    wait_for(lambda: len(run.ticks()) >= 10, what="ticks")
    run.close()
    assert not any(isinstance(m, GyroRate) for m in run.msgs)
    with pytest.raises(ValueError, match="gyro_sign"):
        BoardConfig(gyro_sign=0)
