"""Map hygiene: keeping what slip did to the map from lasting (a mitigation of dragging).

Three mechanisms, each off unless configured (`HygieneConfig`), applied by the pipeline
around the mapper:

- **Periodic reset** (`reset_every_s`): the map and its keyframes are emptied every so
  often — what the thesis walker did: "the map is cleared and reset after every 100
  timesteps ... roughly 10 seconds" (§4, eq 4.10; its code resets every 20 frames), so
  that dead reckoning's accumulated error and out-of-date obstacles do not persist.
- **Decay** (`decay_half_life_s`): every cell's log-odds evidence fades toward unknown
  with this half-life, so a cell keeps its state only while it is seen again; obstacles
  dragged by a braked turn fade once the walker looks elsewhere, while what is in view
  is renewed every frame. (Only the log-odds map models have evidence that can fade; a
  smoother's map rebuilt from keyframes is rebuilt at full strength and fades from
  there.)
- **Gating**: a depth frame or scan is not mapped (the localizer still gets it) while the
  localizer's heading standard deviation exceeds `gate_heading_sigma_rad`, or, with
  `gate_braked_turn`, while a brake is commanded more than `brake_level` of its range
  above its residual torque and the estimated yaw rate exceeds `turn_rate_rad_s` — the
  braked turns whose slip makes the odometry over-rotate and drags what is mapped
  (thesis Fig 6.11).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HygieneConfig:
    """What map hygiene does (module docstring); the defaults do nothing."""

    reset_every_s: float | None = None
    decay_half_life_s: float | None = None
    gate_heading_sigma_rad: float | None = None
    gate_braked_turn: bool = False
    brake_level: float = 0.05
    turn_rate_rad_s: float = 0.15

    def __post_init__(self) -> None:
        for name in ("reset_every_s", "decay_half_life_s", "gate_heading_sigma_rad"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"hygiene {name} must be > 0 or None, got {v}")
        if not 0.0 <= self.brake_level <= 1.0:
            raise ValueError(f"hygiene brake_level must be in [0, 1], got {self.brake_level}")
        if self.turn_rate_rad_s < 0:
            raise ValueError(f"hygiene turn_rate_rad_s must be >= 0, got {self.turn_rate_rad_s}")

    @property
    def active(self) -> bool:
        return (
            self.reset_every_s is not None
            or self.decay_half_life_s is not None
            or self.gate_heading_sigma_rad is not None
            or self.gate_braked_turn
        )


class MapHygiene:
    """The state of map hygiene over a run: when the map was last reset and faded, the
    latest brake levels and heading estimates; counts of what it did."""

    def __init__(self, config: HygieneConfig) -> None:
        self.config = config
        self._last_reset: float | None = None
        self._last_decay: float | None = None
        self._heading: tuple[float, float] | None = None  # (t, θ) at the previous frame
        self.brake_levels = (0.0, 0.0)
        self.counts = {"resets": 0, "gated_uncertain": 0, "gated_braked_turn": 0}

    def due_reset(self, t: float) -> bool:
        """Whether the map is due to be emptied before the frame at t."""
        every = self.config.reset_every_s
        if every is None:
            return False
        if self._last_reset is None:
            self._last_reset = t
            return False
        if t - self._last_reset < every:
            return False
        self._last_reset = t
        self.counts["resets"] += 1
        return True

    def decay_factor(self, t: float) -> float:
        """The factor the map's evidence fades by since the previous frame (1: none)."""
        half = self.config.decay_half_life_s
        last, self._last_decay = self._last_decay, t
        if half is None or last is None or t <= last:
            return 1.0
        return 0.5 ** ((t - last) / half)

    def admit(self, t: float, pose: np.ndarray, covariance: np.ndarray) -> bool:
        """Whether to map the frame at t taken at the estimated `pose` with `covariance`."""
        c = self.config
        previous, self._heading = self._heading, (t, float(pose[2]))
        sigma = math.sqrt(max(float(covariance[2, 2]), 0.0))
        if c.gate_heading_sigma_rad is not None and sigma > c.gate_heading_sigma_rad:
            self.counts["gated_uncertain"] += 1
            return False
        if c.gate_braked_turn and previous is not None and t > previous[0]:
            rate = math.remainder(float(pose[2]) - previous[1], 2 * math.pi) / (t - previous[0])
            braked = max(self.brake_levels) > c.brake_level
            if braked and abs(rate) > c.turn_rate_rad_s:
                self.counts["gated_braked_turn"] += 1
                return False
        return True
