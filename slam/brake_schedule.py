"""Each brake's commanded level over time, as the brakes apply it.

A brake command is logged when it is sent; the brake acts on it later (the loop's
latency, the driver, the coil's lag: 30 ms + a 25 ms time constant in the simulator),
and the encoders tick on their own clock (50 Hz against commands at 10 Hz). The slip
of an odometry increment follows the level in force *during* it: `BrakeSchedule.mean`
is the time average of each level over an increment, with every command taking effect
`delay_s` after its time (slam.motion.MotionNoise.brake_delay_s).
"""

from __future__ import annotations

from collections import deque


class BrakeSchedule:
    """Commanded levels (left, right) in [0, 1] in time order; both 0 before the first."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self._events: deque[tuple[float, tuple[float, float]]] = deque()
        self._level = (0.0, 0.0)  # in force at the start of the next increment

    def command(self, t: float, levels: tuple[float, float]) -> None:
        """A command sent at t (in time order), in force from t + delay_s."""
        self._events.append((t + self.delay_s, levels))

    def mean(self, t0: float, t1: float) -> tuple[float, float]:
        """Each level's time average over [t0, t1] (the level at t1 if t1 <= t0); the
        commands in force before t0 are forgotten (increments come in time order)."""
        while self._events and self._events[0][0] <= t0:
            self._level = self._events.popleft()[1]
        if t1 <= t0:
            return self._level
        left = right = 0.0
        t, level = t0, self._level
        for te, next_level in self._events:
            if te >= t1:
                break
            left += level[0] * (te - t)
            right += level[1] * (te - t)
            t, level = te, next_level
        left += level[0] * (t1 - t)
        right += level[1] * (t1 - t)
        return left / (t1 - t0), right / (t1 - t0)
