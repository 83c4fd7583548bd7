"""Wheel slip under braking and the quadrature encoders that under-report because of it.

A braked wheel transmits its brake force to the floor through the tyre; the tyre skids
by a longitudinal slip ratio s (wheel circumference rolled = (1 − s) · ground distance)
that grows with the force it carries and with how slippery the floor is. This is the
mechanism of thesis Fig 6.1: the encoder of the braked wheel under-reports, and dead
reckoning curves toward the braked side — much more on a dusty floor.

Model (a modelling assumption, not a measurement): s = k_surface · F_b / F_b,max ·
m(t), clipped to [0, 0.95], where m(t) is a log-normal, time-correlated factor (an
Ornstein–Uhlenbeck process in log space) drawn from the run's seed. k_surface is the slip
ratio at full brake force: `clean` 0.02, `dusty` 0.12, or any number in [0, 0.95];
each wheel's k is k_surface times its own factor (`wheel_scale`, default (1, 1): a
left tyre that slips more than the right is (1.5, 1.0)).

What a localizer can estimate of k (`SlipTruth`): the localizers know the commanded
torque τ of each brake, as a level l = (τ − τ_off)/(τ_max − τ_off) ∈ [0, 1], and model
s = k·l. The simulator's s differs from k_wheel·l: its force follows the command
through the brakes' 25 ms lag, carries the residual torque τ_off even at l = 0 (F_b /
F_b,max = τ/τ_max = 0.017 + 0.983·l), fades at walking pace near standstill, and m(t)
is 1 only on average. The *effective* k of a wheel is the least-squares slope of its
simulated slip on the commanded level, weighted by the ground distance the wheel
rolled: k_eff = Σ|g|·s·l / Σ|g|·l² over the physics steps (those at l = 0 count in
neither sum) — the k that best explains the encoder's lost distance in the localizers'
parameterisation, and what their estimates are judged against.
"""

from __future__ import annotations

import math

import numpy as np

from hardware.errors import ConfigError

SURFACES: dict[str, float] = {"clean": 0.02, "dusty": 0.12}


def surface_coefficient(surface: str | float) -> float:
    """Slip ratio at full brake force for a named surface or a number."""
    if isinstance(surface, str):
        if surface in SURFACES:
            return SURFACES[surface]
        try:
            value = float(surface)
        except ValueError:
            raise ConfigError(
                f"unknown surface '{surface}'; valid: {', '.join(SURFACES)} "
                "or a number in [0, 0.95]"
            ) from None
    else:
        value = float(surface)
    if not 0.0 <= value <= 0.95:
        raise ConfigError(f"surface slip coefficient must be in [0, 0.95], got {value}")
    return value


def proposed_localizer_settings(surface: str | float) -> dict[str, float]:
    """The odometry noise a simulated trial on `surface` proposes to its localizers
    (trial-log metadata "localizer_settings", applied before the user's --set, as a
    dataset importer's fitted noise levels are).

    wheel_m [m²/m] = 5e-5 + 7e-3 · k^1.25 (k: the surface's slip ratio at full brake
    force). Measured on simulated thesis-course trials with open-loop braking (seed 1,
    1 s windows of each wheel's encoder distance against the true wheel arcs): variance
    per metre rolled 1.8e-5 (clean) / 3.5e-5 (dusty) without brakes; in windows with a
    brake on, 3.6e-5 on clean (k = 0.02), 3.0e-4 on dusty (0.12), 9.8e-4 at k = 0.3 —
    about 4.3e-3 · k^1.25. The proposal is ~1.7 times that, plus a floor for the wheel
    diameter's 0.5 % mis-calibration, because slip is biased (it only under-reports) and
    correlated over a braking episode. The walker-wide default (slam.motion.MotionNoise,
    2.5e-3: the thesis's 5 % encoder error) is 5–25 times more: a filter whose particles
    spread that wide loses the map frame (FastSLAM's surviving lineage drifts by several
    degrees; BENCHMARKS.md, "Simulated course")."""
    k = surface_coefficient(surface)
    return {"noise.wheel_m": 5e-5 + 7e-3 * k**1.25}


def wheel_slip_coefficients(
    surface: str | float, wheel_scale: tuple[float, float]
) -> tuple[float, float]:
    """Each wheel's slip ratio at full brake force, k_surface · scale (left, right)."""
    k = surface_coefficient(surface)
    if len(wheel_scale) != 2:
        raise ConfigError(f"slip_scale must be two factors (left, right), got {wheel_scale}")
    out = []
    for side, f in zip(("left", "right"), wheel_scale, strict=True):
        try:
            value = k * float(f)
        except (TypeError, ValueError):
            raise ConfigError(f"slip_scale {side} must be a number, got {f!r}") from None
        if not (math.isfinite(value) and float(f) >= 0 and value <= 0.95):
            raise ConfigError(
                f"slip_scale {side} {f}: the wheel's slip coefficient {k} × {f} must be "
                "in [0, 0.95]"
            )
        out.append(value)
    return out[0], out[1]


class SlipTruth:
    """The effective per-wheel k of a run (module docstring), accumulated step by step:
    Σ|g|·s·l and Σ|g|·l² per wheel, l the commanded brake level."""

    def __init__(self) -> None:
        self._sl = [0.0, 0.0]
        self._ll = [0.0, 0.0]
        self.braked_m = [0.0, 0.0]  # ground distance rolled with l > 0

    def add(self, ground: tuple[float, float], slip: tuple[float, float], level) -> None:
        """One physics step: each wheel's ground distance, slip ratio and brake level."""
        for i in (0, 1):
            if level[i] > 0.0:
                g = abs(ground[i])
                self._sl[i] += g * slip[i] * level[i]
                self._ll[i] += g * level[i] * level[i]
                self.braked_m[i] += g

    def effective_k(self) -> tuple[float | None, float | None]:
        """(left, right) least-squares k per unit level; None for a wheel never braked."""
        out = [self._sl[i] / self._ll[i] if self._ll[i] > 0 else None for i in (0, 1)]
        return out[0], out[1]


class SlipModel:
    """Slip ratio of each rear wheel as a function of its brake force."""

    def __init__(
        self,
        surface: str | float,
        max_brake_force_n: float,
        rng: np.random.Generator,
        variability: float = 0.3,
        correlation_time_s: float = 0.5,
        wheel_scale: tuple[float, float] = (1.0, 1.0),
    ) -> None:
        self.k = surface_coefficient(surface)
        self.k_wheel = wheel_slip_coefficients(surface, wheel_scale)
        self.max_force = max_brake_force_n
        self.rng = rng
        self.sigma = variability
        self.tau = correlation_time_s
        self._log_factor = [0.0, 0.0]

    def step(self, dt: float, brake_forces: tuple[float, float]) -> tuple[float, float]:
        """Advance the random factor by dt and return the slip ratios (left, right)."""
        a = math.exp(-dt / self.tau)
        scale = self.sigma * math.sqrt(1.0 - a * a)
        noise = self.rng.standard_normal(2)
        out = []
        for i in (0, 1):
            self._log_factor[i] = a * self._log_factor[i] + scale * float(noise[i])
            factor = math.exp(self._log_factor[i] - 0.5 * self.sigma**2)
            out.append(
                min(
                    max(self.k_wheel[i] * abs(brake_forces[i]) / self.max_force * factor, 0.0), 0.95
                )
            )
        return out[0], out[1]


class Encoders:
    """Quadrature encoders on the true wheels: cumulative counts of wheel rotation.

    wheel_diameter_m: both wheels', or (left, right) when they differ."""

    def __init__(self, wheel_diameter_m: float | tuple[float, float], counts_per_rev: int) -> None:
        left, right = (
            wheel_diameter_m if isinstance(wheel_diameter_m, tuple) else (wheel_diameter_m,) * 2
        )
        self._counts_per_metre = (
            counts_per_rev / (math.pi * left),
            counts_per_rev / (math.pi * right),
        )
        self._rolled = [0.0, 0.0]  # metres of circumference rolled (signed)

    def roll(self, ground_left: float, ground_right: float, slip: tuple[float, float]) -> None:
        """Wheels cover ground distances; the encoders see (1 − s) of it."""
        self._rolled[0] += ground_left * (1.0 - slip[0])
        self._rolled[1] += ground_right * (1.0 - slip[1])

    def counts(self) -> tuple[int, int]:
        # A quadrature counter reports whole counts (floor, also for negative rotation).
        return (
            math.floor(self._rolled[0] * self._counts_per_metre[0]),
            math.floor(self._rolled[1] * self._counts_per_metre[1]),
        )
