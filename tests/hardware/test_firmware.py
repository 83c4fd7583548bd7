"""The board firmware (hardware/firmware/walker_board.c) running on a simulated
ATmega328P (simavr, through hardware/firmware_sim.py), talked to over its pty with
pyserial and the protocol codec (hardware/board_protocol.py).

Every timing assertion is in simulated time: the harness stamps its events (each
newline handed to the AVR's UART, each brake-output change, each line the AVR sends,
resets) with the MCU's clock. Wall-clock limits are only timeouts, and generous.
The firmware and the harness are built once per session; if avr-gcc or simavr are
missing the tests fail (`make test` installs them).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import statistics
import subprocess
from collections.abc import Callable

import pytest
import serial

from hardware import board_protocol as bp
from hardware import firmware_sim as fs

WAIT_S = 30.0  # wall-clock limit of any single wait (a loaded 2-core machine)
MS = 1_000_000  # ns


@pytest.fixture(scope="session")
def firmware_built() -> None:
    try:
        fs.build()
    except fs.FirmwareSimError as e:
        pytest.fail(f"cannot build the board firmware and its simavr harness: {e}")


@pytest.fixture
def sim(firmware_built) -> fs.FirmwareSim:
    with fs.FirmwareSim(tx_events=True, timeout_s=WAIT_S) as s:
        wait_tx(s, bp.Handshake)  # booted
        yield s


class Host:
    """The test's end of the serial line: pyserial on the harness's pty."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, bp.BAUD, timeout=0.05)
        self.split = bp.LineSplitter()
        self.pending: list[bp.BoardMessage] = []
        self.bad: list[bp.LineError] = []

    def send(self, *lines: bytes | bp.HostMessage) -> None:
        for line in lines:
            self.ser.write(line if isinstance(line, bytes) else line.line())
        self.ser.flush()

    def next(self, timeout: float = WAIT_S) -> bp.BoardMessage:
        """The next good line the board sent (a partial first line is set aside)."""
        with self.ser_timeout(timeout):
            while not self.pending:
                data = self.ser.read(256)
                if not data:
                    raise TimeoutError("no line from the board")
                for item in self.split.feed(data):
                    if isinstance(item, bp.LineError):
                        self.bad.append(item)
                        continue
                    try:
                        self.pending.append(bp.parse_board_line(item))
                    except bp.LineError as e:
                        self.bad.append(e)
        return self.pending.pop(0)

    @contextlib.contextmanager
    def ser_timeout(self, timeout: float):
        # one read blocks at most `timeout`; a stream of T lines keeps it short
        old = self.ser.timeout
        self.ser.timeout = min(timeout, 2.0)
        try:
            yield
        finally:
            self.ser.timeout = old

    def expect(self, kind: type, pred: Callable = lambda m: True, skip: int = 1000):
        """The first line of type `kind` satisfying pred, within `skip` lines."""
        for _ in range(skip):
            msg = self.next()
            if isinstance(msg, kind) and pred(msg):
                return msg
        raise AssertionError(f"no {kind.__name__} line among {skip}")

    def query(self) -> tuple[bp.Handshake, bp.Status]:
        """Q -> the reply: the next H line directly followed by an S line (an H on its
        own is a C reply or a boot line)."""
        self.send(bp.Query())
        h = self.expect(bp.Handshake)
        for _ in range(10):
            after = self.next()
            if isinstance(after, bp.Status):
                return h, after
            h = after if isinstance(after, bp.Handshake) else self.expect(bp.Handshake)
        raise AssertionError("no H line followed by S")

    def drain(self) -> None:
        """Forget what the board sent so far."""
        self.ser.reset_input_buffer()
        self.split = bp.LineSplitter()
        self.pending.clear()

    def close(self) -> None:
        self.ser.close()


@pytest.fixture
def host(sim) -> Host:
    h = Host(sim.port)
    yield h
    h.close()


def parse(e: fs.SimEvent) -> bp.BoardMessage:
    return bp.parse_board_line(e.text.encode("ascii"))


def is_tx(kind: type, pred: Callable = lambda m: True) -> Callable[[fs.SimEvent], bool]:
    letter = {bp.Handshake: "H,", bp.Tick: "T,", bp.Status: "S,"}[kind]

    def check(e: fs.SimEvent) -> bool:
        if e.kind != "tx" or not e.text.startswith(letter):
            return False
        try:
            msg = parse(e)
        except bp.LineError:  # a line a reset cut short
            return False
        return pred(msg)

    return check


def wait_tx(sim: fs.FirmwareSim, kind: type, pred: Callable = lambda m: True, since: int = 0):
    """(event, message): the first line of that type the AVR sent from `since` on."""
    ev = sim.wait_for(is_tx(kind, pred), since=since)
    return ev, parse(ev)


def sent(sim: fs.FirmwareSim, kind: type, since: int = 0) -> list[tuple[int, bp.BoardMessage]]:
    """(t_ns, message) of every line of that type the AVR sent from `since` on."""
    return [(e.t_ns, parse(e)) for e in sim.events(since) if is_tx(kind)(e)]


def brake_events(sim: fs.FirmwareSim, since: int = 0) -> list[tuple[int, tuple[int, ...]]]:
    return [(e.t_ns, tuple(int(a) for a in e.args)) for e in sim.events(since, "brake")]


def released(e: fs.SimEvent) -> bool:
    return e.kind == "brake" and e.args == ("0", "0", "0", "0")


def send_and_stamp(sim: fs.FirmwareSim, host: Host, msg: bp.HostMessage | bytes) -> int:
    """Send one line; the simulated time its newline reached the AVR's UART."""
    m = sim.mark()
    host.send(msg)
    return sim.wait_for(lambda e: e.kind == "rx-nl", since=m).t_ns


def nth(sim: fs.FirmwareSim, pred: Callable, n: int, since: int = 0) -> fs.SimEvent:
    """The n-th event from `since` on satisfying pred."""
    seen: list[fs.SimEvent] = []

    def count(e: fs.SimEvent) -> bool:
        if pred(e):
            seen.append(e)
        return len(seen) >= n

    sim.wait_for(count, since=since)
    return seen[n - 1]


def both_done(sim: fs.FirmwareSim, since: int) -> int:
    """When the last of both wheels' `steps` finished (ns)."""
    return max(
        sim.wait_for(lambda e, w=w: e.kind == "done" and e.args[0] == w, since=since).t_ns
        for w in "LR"
    )


def first_tick_after(sim: fs.FirmwareSim, t_ns: int) -> fs.SimEvent:
    return nth(sim, lambda e: e.t_ns > t_ns and is_tx(bp.Tick)(e), 1)


def ticks_after(sim: fs.FirmwareSim, t_ns: int, n: int = 2) -> bp.Tick:
    """The n-th tick report sent after t_ns; the 2nd was sampled after t_ns (reports
    leave a few ms after they are sampled, 10 ms apart)."""
    return parse(nth(sim, lambda e: e.t_ns > t_ns and is_tx(bp.Tick)(e), n))


# -- handshake ---------------------------------------------------------------------------
def test_query_gets_handshake_then_status(sim, host):
    boot = sent(sim, bp.Handshake)
    assert [h for _, h in boot] == [bp.Handshake(1, "1.0.0", 100, 256, 1)]  # power-on
    host.send(bp.Query())
    h = host.expect(bp.Handshake)
    s = host.next()  # the line right after H
    assert h == bp.Handshake(proto=1, firmware="1.0.0", rate_hz=100, cpr=256, reset_flags=1)
    assert h.reset_cause == "power-on"
    assert s == bp.Status(1, 0, 0, 0, 0, 0, 0, 0)
    # 115200 8N1 as the AVR's UART is set: UBRR0 16 with U2X0, 117647 baud (+2.1 %)
    ubrr, u2x, baud, _ = sim.uart_config()
    assert (ubrr, u2x) == (16, True)
    assert abs(baud / bp.BAUD - 1) < 0.025
    # the pty is a pty: setting DTR fails there, and the port still works
    with contextlib.suppress(OSError):
        host.ser.dtr = True
    assert host.query()[1].rx_lines == 2


# -- encoders ----------------------------------------------------------------------------
def test_counts_every_edge_in_both_directions(sim, host):
    done = sim.steps("L", 1000, period_us=100, wait=True)
    t = ticks_after(sim, done.t_ns)
    assert (t.left, t.right) == (1000, 0)
    done = sim.steps("R", -357, period_us=150, wait=True)
    t = ticks_after(sim, done.t_ns)
    assert (t.left, t.right) == (1000, -357)
    # both wheels at once, edges interleaved at unrelated periods
    m = sim.mark()
    sim.steps("L", -250, period_us=70)
    sim.steps("R", 1200, period_us=40)
    last = both_done(sim, m)
    t = ticks_after(sim, last)
    assert (t.left, t.right) == (750, 843) == sim.counts()
    assert t.flags & bp.TICK_QUAD_ERROR_FLAG == 0
    # fast: both wheels at 20 us per edge (50 000 edges/s each)
    m = sim.mark()
    sim.steps("L", 3000, period_us=20)
    sim.steps("R", -3000, period_us=21)
    last = both_done(sim, m)
    t = ticks_after(sim, last)
    assert (t.left, t.right) == (3750, -2157)
    assert host.query()[1].quad_errors == 0


def test_both_channels_at_once_is_a_quadrature_error(sim, host):
    sim.steps("L", 40, period_us=100, wait=True)
    # (long enough after the last edge for every report sent from now on to have been
    # sampled after it; and a glitch within the board's interrupt latency of an edge
    # would be, for the board, one ordinary edge)
    sim.wait_sim(0.02)
    m = sim.mark()
    sim.glitch("L")
    t_glitch = sim.sim_time_ns()
    ticks_after(sim, t_glitch, n=3)
    after = [t for _, t in sent(sim, bp.Tick, m)]
    # flagged in the one report sampled after the error, not counted as motion
    assert [bool(t.flags & bp.TICK_QUAD_ERROR_FLAG) for t in after].count(True) == 1
    assert {t.left for t in after} == {40}
    assert host.query()[1].quad_errors == 1
    # the decoder goes on from the new phase: further edges count exactly
    sim.steps("L", -15, period_us=100)
    sim.glitch("R")  # the right wheel has not moved for a while
    done = sim.steps("R", 7, period_us=100, wait=True)
    t = ticks_after(sim, done.t_ns)
    assert (t.left, t.right) == (25, 7)
    assert host.query()[1].quad_errors == 2
    assert sum(1 for _, t in sent(sim, bp.Tick, m) if t.flags & bp.TICK_QUAD_ERROR_FLAG) == 2


def test_set_counts_moves_the_wheels_to_the_true_counts(sim):
    # what the live simulation does: its wheels' counts, 100-200 times a second
    for i in range(1, 51):
        sim.set_counts(7 * i, -3 * i)
    sim.set_counts(400, -150)
    t_set = sim.sim_time_ns()
    t = ticks_after(sim, t_set + 60 * MS)  # 550 edges at 10 kHz take 55 ms
    assert (t.left, t.right) == (400, -150) == sim.counts()
    # edges at up to the given rate: 200 counts at 1 kHz take 200 ms
    sim.set_counts(600, -150, max_rate_hz=1000)
    t0 = sim.sim_time_ns()
    early = ticks_after(sim, t0 + 100 * MS, n=1)  # sampled 87-110 ms after t0
    assert 480 <= early.left <= 515
    late = ticks_after(sim, t0 + 220 * MS)
    assert (late.left, late.right) == (600, -150)


# -- tick reports ------------------------------------------------------------------------
def reports_per_second(sim: fs.FirmwareSim, since: int, seconds: float = 1.0):
    """The tick reports sent over `seconds` of simulated time from the second one after
    `since` on (the first may have been sampled before a rate change: the firmware
    sends the C reply before a report already due): ([(t_ns, Tick)], t0_ns)."""
    t0 = nth(sim, is_tx(bp.Tick), 2, since).t_ns
    sim.wait_until(t0 + round(seconds * 1e9) + 50 * MS)
    return [(t, m) for t, m in sent(sim, bp.Tick, since) if t >= t0], t0


def check_rate(sim: fs.FirmwareSim, since: int, rate_hz: int, period_us: int) -> None:
    ticks, t0 = reports_per_second(sim, since)
    seqs = [m.seq for _, m in ticks]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "seq must go up by 1"
    spacing = [b.t_us - a.t_us for (_, a), (_, b) in itertools.pairwise(ticks)]
    assert all(abs(d - period_us) <= 8 for d in spacing), spacing
    half = period_us * 500  # ns: a window half a period off the reports ignores jitter
    in_second = [t for t, _ in ticks if t0 + half <= t < t0 + half + 1_000_000_000]
    assert len(in_second) == rate_hz
    # the board's microsecond clock runs at the MCU's: a report's newline leaves a
    # varying time after it was sampled (formatting and sending depend on its digits,
    # other lines may be queued before it), but among lines of one length the shortest
    # delay is the same early and late in the second
    length = statistics.mode(len(m.line()) for _, m in ticks)
    delay_us = [t / 1000 - m.t_us for t, m in ticks if len(m.line()) == length]
    half_n = len(delay_us) // 2
    assert abs(min(delay_us[:half_n]) - min(delay_us[half_n:])) <= 8


def test_tick_reports_at_100_hz(sim, host):
    m = sim.mark()
    check_rate(sim, m, 100, 10_000)
    # a status line every second (the first 1 s after power-on, unasked), sent once the
    # tick report due in the same millisecond has gone: within the UART time of the two
    # lines, plus a byte either side and a millisecond of formatting
    status = sent(sim, bp.Status)
    tick_at_1s = max((m for t, m in sent(sim, bp.Tick) if t < status[0][0]), key=lambda m: m.seq)
    byte_ns = 10e9 / sim.uart_config()[2]
    both = len(tick_at_1s.line()) + len(status[0][1].line()) + 2
    assert len(status) == 1 and 1000 * MS < status[0][0] < 1001 * MS + both * byte_ns
    # and over the pty, as a driver reads them: consecutive, with good checksums
    first = host.expect(bp.Tick)
    later = [host.expect(bp.Tick) for _ in range(20)]
    assert [t.seq for t in later] == list(range(first.seq + 1, first.seq + 21))
    assert all(t.flags & bp.TICK_TIMEOUT_FLAG for t in later)  # no command yet
    assert len(host.bad) <= 1  # at most the partial line at the opening


def test_configure_changes_the_rate(sim, host):
    host.send(bp.Configure(50))
    assert host.expect(bp.Handshake).rate_hz == 50
    check_rate(sim, sim.mark(), 50, 20_000)
    host.send(bp.Configure(250))
    assert host.expect(bp.Handshake).rate_hz == 250
    check_rate(sim, sim.mark(), 250, 4_000)
    # the period is rounded to whole milliseconds: 300 Hz -> 3 ms
    host.send(bp.Configure(300))
    assert host.expect(bp.Handshake).rate_hz == 300
    m = sim.mark()
    ticks, _ = reports_per_second(sim, m, seconds=0.2)
    spacing = {b.t_us - a.t_us for (_, a), (_, b) in itertools.pairwise(ticks)}
    assert all(abs(d - 3000) <= 8 for d in spacing)


# -- brakes ------------------------------------------------------------------------------
def duty_of(ocr: int) -> float:
    """Fast PWM 8-bit, non-inverting: high for OCR + 1 of 256 counts."""
    return (ocr + 1) / 256


def test_brake_outputs_follow_commands(sim, host):
    cases = [(100, 200), (0, 200), (37, 0), (254, 1), (255, 128), (0, 0)]
    for seq, (left, right) in enumerate(cases, start=1):
        m = sim.mark()
        host.send(bp.Brake(seq, left, right))
        ev = sim.wait_for(lambda e: e.kind == "brake", since=m)
        com = (2 if left else 0, 2 if right else 0)
        assert tuple(int(a) for a in ev.args) == (left, right, *com)
        sim.wait_sim(0.005)  # a few PWM periods
        st = sim.brake_state()
        assert (st.ocr_left, st.ocr_right, st.com_left, st.com_right) == (left, right, *com)
        assert (st.left, st.right) == (left, right)
        assert sim.brake_outputs()[1:] == (left, right)
        for ocr, duty, level in (
            (left, st.pin_duty_left, st.pin_left),
            (right, st.pin_duty_right, st.pin_right),
        ):
            if ocr == 0:  # disconnected: the pin is held low
                assert duty == 0.0 and level == 0
            elif ocr < 255:  # simavr drops the pulse when OCR is TOP (255)
                assert abs(duty - duty_of(ocr)) < 0.002
        for ocr, hz in ((left, st.pin_hz_left), (right, st.pin_hz_right)):
            if 0 < ocr < 255:  # 16 MHz / 64 / 256
                assert abs(hz - 976.5625) < 0.2  # a cycle of jitter is 0.06 Hz
        tick = ticks_after(sim, ev.t_ns)
        assert (tick.pwm_left, tick.pwm_right) == (left, right)
        assert not tick.flags & bp.TICK_TIMEOUT_FLAG
    # every change was one event (OCR and COM written together count once)
    assert len(brake_events(sim)) == len(cases)


def test_command_timeout_releases_within_300_ms(sim, host):
    m = sim.mark()
    t_cmd = send_and_stamp(sim, host, bp.Brake(1, 180, 90))
    applied = sim.wait_for(lambda e: e.kind == "brake", since=m)
    assert applied.args == ("180", "90", "2", "2")
    rel = sim.wait_for(released, since=m)
    dt_ms = (rel.t_ns - t_cmd) / MS
    assert 298.0 <= dt_ms <= 300.0, dt_ms  # within 300 ms, not much before
    t = ticks_after(sim, rel.t_ns)
    assert t.flags & bp.TICK_TIMEOUT_FLAG and (t.pwm_left, t.pwm_right) == (0, 0)
    s = host.query()[1]
    assert (s.cmd_timeouts, s.last_cmd_seq, s.cmd_seq_gaps) == (1, 1, 0)


def test_the_timeout_counts_from_the_newline_when_the_main_loop_is_late(firmware_built):
    """A command that waits in the receive ring (the main loop busy 20 ms, as behind a
    slow report) still releases within 300 ms of its newline's arrival, not of when the
    main loop reached it."""
    with fs.FirmwareSim(elf=fs.TEST_FIRMWARE_ELF, tx_events=True, timeout_s=WAIT_S) as sim:
        wait_tx(sim, bp.Handshake)
        host = Host(sim.port)
        try:
            m = sim.mark()
            host.send(bp.encode("X", 2, 20), bp.Brake(1, 150, 150))
            nl = [e.t_ns for e in nth_events(sim, "rx-nl", 2, m)]
            applied = sim.wait_for(lambda e: e.kind == "brake", since=m)
            assert applied.t_ns - nl[1] > 15 * MS  # the command waited for the busy loop
            rel = sim.wait_for(released, since=m)
            assert 298.0 <= (rel.t_ns - nl[1]) / MS <= 300.0
        finally:
            host.close()


def nth_events(sim: fs.FirmwareSim, kind: str, n: int, since: int) -> list[fs.SimEvent]:
    """The first n events of `kind` from `since` on (waiting for them)."""
    nth(sim, lambda e: e.kind == kind, n, since)
    return sim.events(since, kind)[:n]


def test_resending_every_100_ms_keeps_the_brakes(sim, host):
    m = sim.mark()
    stamps = []
    for seq in range(1, 11):
        stamps.append(send_and_stamp(sim, host, bp.Brake(seq, 120, 60)))
        sim.wait_until(stamps[-1] + 100 * MS)
    gaps = [(b - a) / MS for a, b in itertools.pairwise(stamps)]
    assert max(gaps) < 250, f"the test could not keep its 100 ms pace: {gaps}"
    assert [a for _, a in brake_events(sim, m)] == [(120, 60, 2, 2)]  # applied, never released
    rel = sim.wait_for(released, since=m)
    assert 298.0 <= (rel.t_ns - stamps[-1]) / MS <= 300.0
    s = host.query()[1]
    assert (s.rx_lines, s.cmd_timeouts, s.cmd_seq_gaps, s.last_cmd_seq) == (11, 1, 0, 10)
    # missing sequence numbers are counted; a host that restarts its count is not a gap
    host.send(bp.Brake(14, 10, 10), bp.Brake(15, 10, 10), bp.Brake(0, 0, 0))
    s = host.query()[1]
    assert (s.cmd_seq_gaps, s.last_cmd_seq) == (3, 0)


def test_bad_lines_are_counted_and_never_acted_on(sim, host):
    good = bp.Brake(2, 200, 200).line()
    wrong_crc = good[:-3] + (b"00" if good[-3:-1] != b"00" else b"01") + b"\n"
    bad_crc = [wrong_crc, good.replace(b"200,200", b"250,250")]
    malformed = [
        b"B,2,200,200\n",  # no checksum
        bp.encode("B", 3, 300, 0),  # out of range
        bp.encode("B", 4, -1, 0),
        bp.encode("B", 5, 200),  # too few fields
        bp.encode("B", 6, "2x", 0),  # not a number
        bp.encode("Z", 1),  # unknown type
        bp.encode("BB", 7, 200, 200),  # type not one letter
        bp.encode("X", 1),  # the test build's hang: unknown to this firmware
        bp.encode("C", 0),  # rate out of range
        b"\x00\xff\xfe*\n",  # binary garbage
        good[:-4] + b"*2\n",  # one-digit checksum
    ]
    # extra fields are ignored, so a B line can be padded to the length limit
    pad = bp.MAX_LINE - len(b"B,9,33,44,*CC")
    longest = bp.encode("B", 9, 33, 44, "1" * pad)
    assert len(longest) == bp.MAX_LINE + 1
    payload = b"B,9,33,44," + b"1" * (pad + 1)  # one byte more, with a good checksum
    overflow = [payload + b"*%02X\n" % bp.crc8(payload), b"B,8," + b"1" * 200 + b"\n"]
    noise = [b"\n", b"\r\n"]  # empty lines are not lines
    m = sim.mark()
    host.send(*bad_crc, *malformed, *overflow, *noise)
    h, s = host.query()
    assert h.rate_hz == 100  # the bad C did nothing
    counts = (s.rx_lines, s.rx_bad_crc, s.rx_malformed, s.rx_overflow)
    assert counts == (1, len(bad_crc), len(malformed), len(overflow))
    assert brake_events(sim, m) == []  # none of them moved a brake
    assert sim.brake_outputs()[1:] == (0, 0)
    # the longest line is good, and so is a line ending in CR LF
    host.send(longest)
    ev = sim.wait_for(lambda e: e.kind == "brake", since=m)
    assert ev.args == ("33", "44", "2", "2")
    m = sim.mark()
    host.send(bp.Brake(10, 5, 6).line()[:-1] + b"\r\n")
    assert sim.wait_for(lambda e: e.kind == "brake", since=m).args == ("5", "6", "2", "2")
    s = host.query()[1]
    assert (s.rx_lines, s.last_cmd_seq, s.rx_overflow, s.cmd_seq_gaps) == (4, 10, 2, 0)


def with_crc(payload: bytes, crc: int | None = None, fmt: bytes = b"%02X") -> bytes:
    return payload + b"*" + fmt % (bp.crc8(payload) if crc is None else crc) + b"\n"


def test_lines_are_judged_as_the_host_codec_judges_them(sim, host):
    lines = [
        with_crc(b"B,0,-0,9"),  # "-0" is a number, 0
        with_crc(b"B,4294967295,1,2"),
        with_crc(b"B,00000000003,00000000255,0"),  # 11 digits
        with_crc(b"B,5,7,8,12,x"),  # fields after the known ones are ignored
        with_crc(b"B,6,11,12", fmt=b"%02x"),  # lower-case checksum
        with_crc(b"Q,1"),
        with_crc(b"C,100"),
        with_crc(b"B,4294967296,1,2"),
        with_crc(b"B,7,+5,2"),
        with_crc(b"B,7,000000000255,2"),  # 12 digits
        with_crc(b"B,,1,2"),
        with_crc(b"B,7,2"),
        with_crc(b"B"),
        with_crc(b"C,501"),
        with_crc(b"C,-1"),
        with_crc(b"q"),
        with_crc(b",1,2"),
        with_crc(b""),
        with_crc(b"B,7,1,2", crc=0x00 if bp.crc8(b"B,7,1,2") else 0x01),
        with_crc(b"B,7,1,2")[:-4] + b"*G0\n",
        with_crc(b"B,7,1,2," + b"9" * (bp.MAX_LINE - 10)),  # one byte over the limit
    ]
    verdict = {"ok": 0, "crc": 0, "malformed": 0, "overflow": 0}
    for line in lines:
        try:
            bp.parse_host_line(line.rstrip(b"\n"))
            verdict["ok"] += 1
        except bp.LineError as e:
            verdict[e.kind] += 1
    assert min(verdict.values()) >= 1
    m = sim.mark()
    host.send(*lines)
    host.expect(bp.Status)  # the reply to the Q,1 among them
    h, s = host.query()
    assert h.rate_hz == 100 and s.rx_lines == verdict["ok"] + 1
    assert (s.rx_bad_crc, s.rx_malformed, s.rx_overflow) == (
        verdict["crc"],
        verdict["malformed"],
        verdict["overflow"],
    )
    applied = [a[:2] for _, a in brake_events(sim, m)][:5]
    assert applied == [(0, 9), (1, 2), (255, 0), (7, 8), (11, 12)]
    # seq 0 -> 4294967295 went back (a new host count), -> 3 skipped 3, -> 5 one
    assert (s.last_cmd_seq, s.cmd_seq_gaps) == (6, 4)


# -- faults ------------------------------------------------------------------------------
def test_reset_mid_run_restarts_counts_and_releases(sim, host):
    sim.steps("R", -120, period_us=100)
    done = sim.steps("L", 300, period_us=100, wait=True)
    before = ticks_after(sim, done.t_ns)
    assert (before.left, before.right) == (300, -120)
    host.drain()
    m = sim.mark()
    host.send(bp.Brake(1, 90, 90))
    sim.wait_for(lambda e: e.kind == "brake", since=m)
    m = sim.mark()
    t_reset = sim.reset()  # while the brakes are applied (their timeout is 300 ms away)
    assert sim.wait_for(lambda e: e.kind == "reset", since=m).args == ("2",)  # external
    rel = sim.wait_for(released, since=m)
    assert abs(rel.t_ns - t_reset) < 0.01 * MS
    # the firmware boots again: H with the reset flags, reports from seq 0
    _, boot = wait_tx(sim, bp.Handshake, since=m)
    assert boot.reset_flags == 2 and boot.reset_cause == "external"
    assert host.expect(bp.Handshake) == boot  # the driver sees the boot line too
    first = parse(first_tick_after(sim, t_reset))
    assert (first.seq, first.left, first.right) == (0, 0, 0)
    assert first.t_us <= 10_100 and first.flags & bp.TICK_TIMEOUT_FLAG
    # counting from zero; the harness's true position went on
    done = sim.steps("L", 25, period_us=100, wait=True)
    t = ticks_after(sim, done.t_ns)
    assert (t.left, t.right) == (25, 0) and sim.counts() == (325, -120)
    # the brakes stay released until the first valid command after the reset
    sim.wait_sim(0.4)
    assert brake_events(sim, m) == [(rel.t_ns, (0, 0, 0, 0))]
    h, s = host.query()
    assert h.reset_flags == 2 and s == bp.Status(1, 0, 0, 0, 0, 0, 0, 0)
    m2 = sim.mark()
    host.send(bp.Brake(2, 70, 0))
    assert sim.wait_for(lambda e: e.kind == "brake", since=m2).args == ("70", "0", "2", "0")


def test_watchdog_resets_a_hung_mcu_and_releases(firmware_built):
    with fs.FirmwareSim(elf=fs.TEST_FIRMWARE_ELF, tx_events=True, timeout_s=WAIT_S) as sim:
        _, boot = wait_tx(sim, bp.Handshake)
        assert boot.firmware == "1.0.0-test" and boot.reset_flags == 1
        host = Host(sim.port)
        try:
            m = sim.mark()
            host.send(bp.Brake(1, 150, 150))
            sim.wait_for(lambda e: e.kind == "brake", since=m)
            m = sim.mark()
            t_hang = send_and_stamp(sim, host, bp.encode("X", 1))  # cli(); for (;;);
            reset = sim.wait_for(lambda e: e.kind == "reset", since=m)
            assert reset.args == ("8",)  # WDRF
            # WDTO_250MS: 2^15 cycles of the 128 kHz watchdog oscillator = 256 ms
            assert 250 <= (reset.t_ns - t_hang) / MS <= 258
            rel = sim.wait_for(released, since=m)
            assert abs(rel.t_ns - reset.t_ns) < 0.01 * MS  # the reset did it, not the timeout
            hung = [e for e in sim.events(m, "tx") if t_hang + MS < e.t_ns < reset.t_ns]
            assert hung == []  # it was hung: nothing sent, nothing released
            _, again = wait_tx(sim, bp.Handshake, since=m)
            assert again.reset_flags == 8 and again.reset_cause == "watchdog"
            assert parse(first_tick_after(sim, reset.t_ns)).seq == 0
            # and the watchdog is under control again: the board keeps running
            sim.wait_sim(0.5)
            assert [e.args for e in sim.events(m, "reset")] == [("8",)]
        finally:
            host.close()


def test_unplug_replug_keeps_the_firmware_running(sim, host):
    m = sim.mark()
    t_cmd = send_and_stamp(sim, host, bp.Brake(1, 150, 150))
    seq_before = ticks_after(sim, t_cmd, n=1).seq
    sim.unplug()
    assert not os.path.lexists(sim.port)
    with pytest.raises(serial.SerialException):
        for _ in range(100):
            host.ser.read(100)
    host.close()
    # the MCU goes on: it counts, and its command timeout releases the brakes
    done = sim.steps("L", 500, period_us=100, wait=True)
    rel = sim.wait_for(released, since=m)
    assert 298.0 <= (rel.t_ns - t_cmd) / MS <= 300.0
    slave = sim.replug()
    assert os.path.realpath(sim.port) == slave
    host2 = Host(sim.port)
    try:
        h, s = host2.query()
        assert h.reset_flags == 1  # no reset happened
        assert (s.cmd_timeouts, s.last_cmd_seq) == (1, 1)
        t = host2.expect(bp.Tick)
        assert t.left == 500 and t.seq > seq_before and t.flags & bp.TICK_TIMEOUT_FLAG
        assert ticks_after(sim, done.t_ns).left == 500
    finally:
        host2.close()


# -- build options -----------------------------------------------------------------------
def test_counts_per_rev_is_a_build_option(firmware_built, tmp_path):
    out = tmp_path / "cpr"
    r = subprocess.run(
        ["make", "-C", str(fs.FIRMWARE_DIR), f"BUILD={out}", "CPR=1024", "firmware"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    with fs.FirmwareSim(elf=out / "walker_board.elf", tx_events=True, timeout_s=WAIT_S) as sim:
        _, boot = wait_tx(sim, bp.Handshake)
        assert boot.cpr == 1024
