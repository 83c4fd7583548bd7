"""A safety layer around any braking controller.

`SafeController(controller, calibration, config)` is itself a controller. Each tick it
asks the wrapped controller for a command and then, per wheel:

1. replaces anything not finite by the residual torque and clamps to
   [torque_off, torque_max];
2. releases the brakes (target = residual torque) unless the walker moves forward faster
   than `min_speed_mps` — brakes only ever act while moving forward;
3. when the pose, the map or the odometry is older than `max_data_age_s`, ignores the
   controller and ramps the torque linearly from where it was when the data went stale
   down to the residual torque over `ramp_time_s` (a brake that freezes on, or drops
   off at once, under a user leaning on the handles is a fall risk); fresh data again
   hands control back to the controller;
4. limits the rate of change to `rate_limit_nm_per_s` in both directions (a sudden
   release lurches the walker forward as much as a sudden grab stops it).

Data ages come from the input's pose_t / map_t / sensor_t (NaN: not reported, not
checked; -inf: nothing received yet, stale).

The default rate limit, 40 N·m/s, lets the brake swing its whole range (0.068 → 3.95
N·m, 3.88 N·m) within one 0.1 s tick of the thesis's 10 Hz loop, so it never binds
there and leaves the open loop's results unchanged; what it fixes is the slew per
second, so a faster loop (or a glitching controller) cannot step the brakes faster than
that. The brakes themselves respond in 20–35 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from control.base import ControlInput, Controller
from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand


@dataclass(frozen=True)
class SafetyConfig:
    """Safety-layer parameters.

    min_speed_mps: brakes act only while the forward speed exceeds this [m/s] (0.05);
    max_data_age_s: pose, map or odometry older than this is stale [s] (0.3);
    ramp_time_s: on stale data, time to ramp from the current torque to the residual
    torque [s] (0.5);
    rate_limit_nm_per_s: largest change of brake torque per second [N·m/s] (40: a full
    swing within one 10 Hz tick, see the module docstring).
    """

    min_speed_mps: float = 0.05
    max_data_age_s: float = 0.3
    ramp_time_s: float = 0.5
    rate_limit_nm_per_s: float = 40.0

    def __post_init__(self) -> None:
        if not self.max_data_age_s > 0:
            raise ValueError(f"max_data_age_s must be > 0, got {self.max_data_age_s}")
        if not self.ramp_time_s >= 0:
            raise ValueError(f"ramp_time_s must be >= 0, got {self.ramp_time_s}")
        if not self.rate_limit_nm_per_s > 0:
            raise ValueError(f"rate_limit_nm_per_s must be > 0, got {self.rate_limit_nm_per_s}")


def data_ages(inp: ControlInput) -> dict[str, float]:
    """Age [s] of the pose, map and odometry at inp.t; NaN for what the input does not
    report, inf for what was never received."""
    return {name: inp.t - getattr(inp, f"{name}_t") for name in ("pose", "map", "sensor")}


class SafeController(Controller):
    """Wraps `controller`; see the module docstring. Diagnostics of the last tick:
    last_stale (names of the stale data streams), last_raw (the wrapped command)."""

    def __init__(
        self,
        controller: Controller,
        calibration: WalkerCalibration,
        config: SafetyConfig | None = None,
    ) -> None:
        self.controller = controller
        self.config = config or SafetyConfig()
        self.brake = calibration.brake
        off = self.brake.torque_off_nm
        self._out = (off, off)
        self._t: float | None = None
        self._stale_since: float | None = None
        self._stale_from = (off, off)
        self.last_stale: tuple[str, ...] = ()
        self.last_raw: BrakeCommand | None = None

    def _clamp(self, torque: float) -> float:
        if not math.isfinite(torque):
            return self.brake.torque_off_nm
        return self.brake.clamp(torque)

    def command(self, inp: ControlInput) -> BrakeCommand:
        cfg, off = self.config, self.brake.torque_off_nm
        raw = self.controller.command(inp)
        self.last_raw = raw
        target = [self._clamp(raw.left_nm), self._clamp(raw.right_nm)]
        if not inp.v > cfg.min_speed_mps:
            target = [off, off]
        ages = data_ages(inp)
        stale = tuple(
            n for n, age in ages.items() if not math.isnan(age) and age > cfg.max_data_age_s
        )
        self.last_stale = stale
        if stale:
            if self._stale_since is None:
                self._stale_since, self._stale_from = inp.t, self._out
            elapsed = inp.t - self._stale_since
            keep = max(0.0, 1.0 - elapsed / cfg.ramp_time_s) if cfg.ramp_time_s > 0 else 0.0
            target = [off + (x - off) * keep for x in self._stale_from]
        else:
            self._stale_since = None
        if self._t is not None:
            step = cfg.rate_limit_nm_per_s * max(inp.t - self._t, 0.0)
            target = [
                min(max(x, prev - step), prev + step)
                for x, prev in zip(target, self._out, strict=True)
            ]
        out = (self._clamp(target[0]), self._clamp(target[1]))
        self._out, self._t = out, inp.t
        return replace(raw, t=inp.t, left_nm=out[0], right_nm=out[1])
