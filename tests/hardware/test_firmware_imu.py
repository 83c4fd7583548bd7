"""The board firmware with an MPU-6050 on its I²C bus, in simavr (the harness's IMU on the
AVR's TWI): it finds the chip, sets it up, announces the gyro in H and appends the z rate
to every T line; the driver turns it into GyroRate messages. Without the IMU the lines are
as before (the rest of tests/hardware/test_firmware.py runs without it)."""

from __future__ import annotations

import itertools
import threading
import time

import pytest

from hardware import board_protocol as bp
from hardware import firmware_sim as fs
from hardware.arduino import ArduinoBoard
from hardware.calibration import WalkerCalibration
from hardware.clock import HostClock
from hardware.messages import EncoderTicks, GyroRate
from tests.hardware.test_firmware import (
    WAIT_S,
    firmware_built,  # noqa: F401  (the fixture)
    is_tx,
    nth,
    parse,
    wait_tx,
)

pytestmark = pytest.mark.usefixtures("firmware_built")  # built once per session


@pytest.fixture
def imu_sim() -> fs.FirmwareSim:
    with fs.FirmwareSim(tx_events=True, timeout_s=WAIT_S, imu=True) as s:
        wait_tx(s, bp.Handshake)
        yield s


def ticks_from(sim: fs.FirmwareSim, n: int) -> list[bp.Tick]:
    """The n tick reports sent after now, the first one skipped (it may have been
    sampled before)."""
    m = sim.mark()
    nth(sim, is_tx(bp.Tick), n + 1, since=m)
    return [parse(e) for e in sim.events(m) if is_tx(bp.Tick)(e)][1 : n + 1]


def test_the_firmware_sets_up_the_imu_and_reports_its_z_rate(imu_sim):
    _, hs = wait_tx(imu_sim, bp.Handshake)
    assert hs == bp.Handshake(1, "1.0.0", 100, 256, 1, gyro_lsb_per_10dps=1310)
    regs = imu_sim.imu_registers()
    # awake on the PLL clock, 1 kHz, the 42 Hz filter, ±250 °/s
    assert (regs["pwr_mgmt_1"], regs["smplrt_div"], regs["config"], regs["gyro_config"]) == (
        1,
        0,
        3,
        0,
    )
    for raw in (-1234, 0, 32767, -32768, 17):
        imu_sim.set_gyro(raw)
        ticks = ticks_from(imu_sim, 3)
        assert [t.gyro_z for t in ticks] == [raw] * 3
    # one read per report, and the reports keep their period
    before = imu_sim.imu_registers()["gz_reads"]
    ticks = ticks_from(imu_sim, 20)
    reads = imu_sim.imu_registers()["gz_reads"] - before
    assert 20 <= reads <= 23
    assert all(abs(b.t_us - a.t_us - 10_000) <= 4 for a, b in itertools.pairwise(ticks))
    assert [b.seq - a.seq for a, b in itertools.pairwise(ticks)] == [1] * 19


def test_after_a_reset_the_firmware_finds_the_imu_again(imu_sim):
    imu_sim.set_gyro(-300)
    m = imu_sim.mark()
    imu_sim.reset()
    _, hs = wait_tx(imu_sim, bp.Handshake, since=m)
    assert hs.gyro_lsb_per_10dps == 1310 and hs.reset_flags == 2
    assert parse(nth(imu_sim, is_tx(bp.Tick), 2, since=m)).gyro_z == -300


def test_without_an_imu_the_lines_carry_no_gyro():
    with fs.FirmwareSim(tx_events=True, timeout_s=WAIT_S) as sim:
        ev, hs = wait_tx(sim, bp.Handshake)
        assert hs.gyro_lsb_per_10dps is None and ev.text.count(",") == 5
        tick_ev = nth(sim, is_tx(bp.Tick), 3)
        assert parse(tick_ev).gyro_z is None and tick_ev.text.split("*")[0].count(",") == 7
        sim.set_gyro(5)  # does not wait: its refusal comes with the next call that does
        with pytest.raises(fs.FirmwareSimError, match="refused an earlier command: no IMU"):
            sim.counts()
        assert len(sim.counts()) == 2  # said once; the board goes on answering


def test_the_driver_yields_gyro_rates_before_their_ticks(tmp_path):
    rate = 0.5  # rad/s: 28.6 °/s, 3753 LSB
    with fs.FirmwareSim(link=tmp_path / "tty", timeout_s=WAIT_S, imu=True) as sim:
        sim.set_gyro_rate(rate)
        board = ArduinoBoard(sim.port, WalkerCalibration(), HostClock())
        assert board.open().gyro_lsb_per_10dps == 1310
        assert board.metadata["board"]["gyro_lsb_per_10dps"] == 1310
        msgs: list = []
        reader = threading.Thread(target=lambda: msgs.extend(board.messages()), daemon=True)
        reader.start()
        deadline = time.monotonic() + WAIT_S
        while sum(isinstance(m, GyroRate) for m in msgs) < 30:
            assert time.monotonic() < deadline, "no gyro rates from the driver"
            time.sleep(0.01)
        board.close()
        reader.join(timeout=5)
    pairs = [(a, b) for a, b in itertools.pairwise(msgs) if isinstance(a, GyroRate)]
    assert len(pairs) >= 30
    for gyro, ticks in pairs:
        assert isinstance(ticks, EncoderTicks) and ticks.t == gyro.t
        assert gyro.rate_rad_s == pytest.approx(bp.gyro_rate(3753, 1310), abs=1e-12)
    assert abs(pairs[0][0].rate_rad_s - rate) < 0.5 * bp.gyro_rate(1, 1310)  # half an LSB
