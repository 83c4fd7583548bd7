"""Live devices merged on one host clock (hardware.live.LiveSources)."""

from __future__ import annotations

import threading

from hardware.clock import HostClock
from hardware.live import LiveSources
from hardware.messages import EncoderTicks


class _Burst:
    """A device whose driver decoded `n` reports in one read that it yields only once
    it is being closed (as a serial driver does when the host fell behind)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._closing = threading.Event()

    def messages(self):
        self._closing.wait(timeout=5.0)
        for k in range(self.n):
            yield EncoderTicks(0.01 * k, k, k)

    def close(self) -> None:
        self._closing.set()


def test_what_a_device_yields_while_it_is_closed_is_left_for_the_recording():
    """close() stops the run before the device's thread has delivered its last reports;
    remaining() must still hand all of them over (a fresh-clone CI once recorded 690 of
    the 771 reports the board driver had decoded)."""
    sources = LiveSources([("board", _Burst(81))], HostClock())
    sources.start()
    sources.close()
    left = sources.remaining()
    assert [m.left for m in left] == list(range(81))
    assert sources.stats["board"].received == 81
