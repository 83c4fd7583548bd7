"""Mapping a device's clock onto the host clock from report arrival times."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.clock import ClockMap, HostClock


def simulate(drift_ppm, offset_s, seconds=60.0, rate=100.0, seed=0):
    """Reports stamped on a device clock, arriving after a random latency (always > 0:
    a floor of 1 ms plus an exponential tail with bursts of several reports at once)."""
    rng = np.random.default_rng(seed)
    device = np.arange(0.0, seconds, 1.0 / rate)
    true_host = offset_s + device * (1.0 + drift_ppm * 1e-6)
    latency = 0.001 + rng.exponential(0.004, device.size)
    latency[rng.random(device.size) < 0.05] += 0.03  # USB / scheduler hiccups
    return device, true_host, true_host + latency


@pytest.mark.parametrize(("drift_ppm", "offset"), [(0.0, 5.0), (80.0, -3.0), (-2000.0, 12.5)])
def test_drift_and_offset_are_recovered(drift_ppm, offset):
    device, true_host, arrival = simulate(drift_ppm, offset)
    cm = ClockMap()
    mapped = []
    for d, a in zip(device, arrival, strict=True):
        cm.observe(d, a)
        mapped.append(cm.to_host(d, not_after=a))
    mapped = np.array(mapped)
    assert cm.drift == pytest.approx(drift_ppm * 1e-6, abs=3e-6)
    err = mapped - true_host
    # after the first windows the mapping is within the latency floor of the truth
    late = device > 10.0
    assert np.abs(err[late]).max() < 0.0015
    # never later than the arrival (latency is never negative), never backwards
    assert np.all(mapped <= arrival + 1e-12)
    assert np.all(np.diff(mapped) >= 0.0)


def test_reset_forgets_the_old_clock_but_stays_monotonic():
    device, _, arrival = simulate(0.0, 1.0, seconds=5.0)
    cm = ClockMap()
    for d, a in zip(device, arrival, strict=True):
        cm.observe(d, a)
    last = cm.to_host(device[-1])
    cm.reset()
    assert not cm.ready
    # the device restarted its clock at zero, 0.2 s later
    cm.observe(0.0, arrival[-1] + 0.2)
    assert cm.to_host(0.0) == pytest.approx(arrival[-1] + 0.2)
    assert cm.to_host(0.0) >= last


def test_clock_map_needs_an_observation():
    with pytest.raises(RuntimeError):
        ClockMap().to_host(1.0)
    with pytest.raises(ValueError):
        ClockMap(window_s=0.0)


def test_host_clock_counts_from_its_start():
    c = HostClock(start=100.0)
    assert c.to_host(101.5) == pytest.approx(1.5)
    assert HostClock().now() >= 0.0
