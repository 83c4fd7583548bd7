"""One clock for a live run, and the mapping of a device's own clock onto it.

`HostClock` is the run's time base: seconds of the host's monotonic clock since the run
started (so a live recording starts near t = 0 like a simulated one, and trial-log times
are never negative). Every live device stamps its messages on it.

`ClockMap` maps a device's clock (the walker board's microsecond counter) onto the host
clock from pairs (device time, host time of arrival). A report arrives some latency
after it was stamped, and the latency varies (USB polling, the OS scheduler), but it is
never negative: the smallest host − device difference seen in a window is the closest
to the true offset. The map keeps those per-window minima and fits a line through them
(offset and drift: crystals differ from the host by tens of ppm, and simulated boards by
much more), so host = device + offset + drift · device. Until two windows are complete
it uses the minimum difference so far with no drift.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque


class HostClock:
    """Seconds since the run started, on the host's monotonic clock (thread-safe)."""

    def __init__(self, start: float | None = None) -> None:
        self.start = time.monotonic() if start is None else start

    def now(self) -> float:
        return time.monotonic() - self.start

    def to_host(self, monotonic_s: float) -> float:
        """A `time.monotonic()` reading on this clock."""
        return monotonic_s - self.start


class ClockMap:
    """Device time → host time by a line through per-window minimum offsets.

    window_s: length of a window of device time [s]; windows: how many recent windows
    the fit uses (the line follows slow drift changes, e.g. temperature).
    """

    def __init__(self, window_s: float = 1.0, windows: int = 30) -> None:
        if not window_s > 0 or windows < 2:
            raise ValueError("ClockMap needs window_s > 0 and windows >= 2")
        self.window_s = window_s
        self._minima: deque[tuple[float, float]] = deque(maxlen=windows)
        self._win_start: float | None = None
        self._win_min: tuple[float, float] | None = None
        self._min_so_far = math.inf
        self._fit: tuple[float, float, float] | None = None  # (t_ref, offset at t_ref, drift)
        self._last_host = -math.inf
        self._lock = threading.Lock()

    def reset(self) -> None:
        """Forget everything (the device restarted its clock)."""
        with self._lock:
            self._minima.clear()
            self._win_start = self._win_min = self._fit = None
            self._min_so_far = math.inf

    def observe(self, device_t: float, host_t: float) -> None:
        """One report stamped `device_t` on the device that arrived at `host_t`."""
        d = host_t - device_t
        with self._lock:
            self._min_so_far = min(self._min_so_far, d)
            if self._win_start is None:
                self._win_start = device_t
            if device_t - self._win_start >= self.window_s:
                if self._win_min is not None:
                    self._minima.append(self._win_min)
                    self._refit()
                self._win_start, self._win_min = device_t, None
            if self._win_min is None or d < self._win_min[1]:
                self._win_min = (device_t, d)

    def _refit(self) -> None:
        if len(self._minima) < 2:
            return
        ts = [t for t, _ in self._minima]
        ds = [d for _, d in self._minima]
        t_ref = sum(ts) / len(ts)
        d_mean = sum(ds) / len(ds)
        sxx = sum((t - t_ref) ** 2 for t in ts)
        drift = sum((t - t_ref) * (d - d_mean) for t, d in zip(ts, ds, strict=True)) / sxx
        # The line must stay below every window minimum (latency is never negative).
        lift = min(d - (d_mean + drift * (t - t_ref)) for t, d in self._minima)
        self._fit = (t_ref, d_mean + lift, drift)

    @property
    def ready(self) -> bool:
        return math.isfinite(self._min_so_far)

    @property
    def drift(self) -> float:
        """Estimated rate difference (host − device) / device, 0 before a fit."""
        return self._fit[2] if self._fit else 0.0

    def offset_at(self, device_t: float) -> float:
        """host − device at device time `device_t` (without the arrival latency)."""
        with self._lock:
            if self._fit is None:
                return self._min_so_far
            t_ref, off, drift = self._fit
            return off + drift * (device_t - t_ref)

    def to_host(self, device_t: float, not_after: float | None = None) -> float:
        """Host time of `device_t`, at most `not_after` (e.g. the report's arrival: a
        report is not stamped later than it arrived, which an extrapolated drift could
        otherwise do) and never earlier than a previous answer (a refit must not send a
        stream's time backwards; this wins when the two conflict)."""
        if not self.ready:
            raise RuntimeError("ClockMap.to_host before any observation")
        t = device_t + self.offset_at(device_t)
        if not_after is not None:
            t = min(t, not_after)
        with self._lock:
            t = max(t, self._last_host)
            self._last_host = t
        return t
