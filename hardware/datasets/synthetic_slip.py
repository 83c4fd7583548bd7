"""Synthetic wheel slip injected into a dataset's velocity odometry (MRCLAM `slip=K`).

A braking walker steers by braking the wheel on the inside of the turn, and that wheel
slips and under-reports. Datasets of robots without brakes have no such slip; to test
the slip mitigations on real sensor data, this module puts a walker's slip into their
odometry, documented and seeded:

- each odometry row (t, v, ω) is split into wheel speeds on the robot's track b:
  v_L = v − ω b/2, v_R = v + ω b/2;
- while the robot turns, the wheel on the inside of the turn (left for ω > 0) is taken
  as braked at level = min(|ω| / full_turn_rad_s, 1) — the harder the turn, the harder
  a walker would brake — and under-reports by a slip ratio s = K · level · m(t), where
  m(t) is the simulator's time-correlated log-normal factor (mean 1;
  `hardware.sim.slip.SlipModel`, seeded), so the slip comes and goes like a real one;
- the odometry is rebuilt from the slipped wheel speeds, and a `BrakeCommand` with that
  level on the inner wheel is emitted at each row whose level changed, so that
  localizers which read brake commands (brake-aware noise, slip estimation) see the
  "brake" that caused the slip, as on the walker.

The true slip of every row is kept (`SlipInjection.ratio`) and summarised in the
dataset's metadata "slip" (k per unit level of each wheel, as the simulator writes it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.calibration import BrakeCalibration
from hardware.messages import BrakeCommand
from hardware.sim.slip import SlipModel


@dataclass(frozen=True)
class SlipInjection:
    """Odometry with slip (t, v, ω rows), the inner-wheel brake levels (left, right) per
    row, and the slip ratio each wheel was given per row."""

    odometry: np.ndarray
    levels: np.ndarray
    ratio: np.ndarray

    def brake_commands(self, brake: BrakeCalibration) -> list[BrakeCommand]:
        """A command at the first row and at every row whose levels changed."""
        out: list[BrakeCommand] = []
        last = None
        span = brake.torque_max_nm - brake.torque_off_nm
        for t, (left, right) in zip(
            self.odometry[:, 0].tolist(), self.levels.tolist(), strict=True
        ):
            if last == (left, right):
                continue
            last = (left, right)
            out.append(
                BrakeCommand(
                    t,
                    brake.torque_off_nm + left * span,
                    brake.torque_off_nm + right * span,
                    "synthetic-slip",
                )
            )
        return out

    def summary(self, k: float) -> dict:
        """Metadata "slip": the injected K per wheel, its effective value per unit level
        (the least-squares slope of the ratio on the level, weighted by distance), and
        the distance each wheel rolled with a level above 0."""
        dt = np.diff(self.odometry[:, 0], append=self.odometry[-1, 0])
        eff, braked = [], []
        for i in (0, 1):
            w = self.levels[:, i] * dt
            num = float(np.sum(w * self.ratio[:, i]))
            den = float(np.sum(w * self.levels[:, i]))
            eff.append(num / den if den > 0 else None)
            braked.append(
                float(
                    np.sum(
                        dt[self.levels[:, i] > 0] * np.abs(self.odometry[self.levels[:, i] > 0, 1])
                    )
                )
            )
        return {"k_wheel": [k, k], "k_effective": eff, "braked_distance_m": braked}


def inject_slip(
    odometry: np.ndarray,
    k: float,
    track_m: float,
    seed: int,
    full_turn_rad_s: float = 0.5,
) -> SlipInjection:
    """`odometry` (rows t, v, ω) with slip K on the inner wheel of each turn (module
    docstring)."""
    if not (math.isfinite(k) and 0.0 <= k < 0.95):
        raise ValueError(f"slip must be in [0, 0.95), got {k}")
    if not full_turn_rad_s > 0:
        raise ValueError(f"full_turn_rad_s must be > 0, got {full_turn_rad_s}")
    t, v, w = odometry[:, 0], odometry[:, 1], odometry[:, 2]
    half = 0.5 * track_m
    wheels = np.column_stack([v - w * half, v + w * half])
    level = np.minimum(np.abs(w) / full_turn_rad_s, 1.0)
    levels = np.zeros((len(t), 2))
    inner = np.where(w > 0, 0, 1)
    levels[np.arange(len(t)), inner] = np.where(np.abs(w) > 1e-9, level, 0.0)
    model = SlipModel(k, 1.0, np.random.default_rng(seed))
    ratio = np.zeros((len(t), 2))
    previous = t[0] if len(t) else 0.0
    for i, ti in enumerate(t.tolist()):
        ratio[i] = model.step(max(ti - previous, 1e-3), tuple(levels[i].tolist()))
        previous = ti
    slipped = wheels * (1.0 - ratio)
    out = np.column_stack([t, slipped.mean(axis=1), (slipped[:, 1] - slipped[:, 0]) / track_m])
    return SlipInjection(out, levels, ratio)
