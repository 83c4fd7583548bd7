"""A simulated MEMS yaw-rate gyro on the walker: an InvenSense MPU-6050 read over I²C.

The MPU-6050 is the common I²C IMU of Arduino projects. Its z-axis rate is sampled from
the walker's true yaw rate as

    r = (1 + s) · ω̄ + b₀ + b(t) + n,   quantised to the 16-bit register (1 LSB = 1/131 °/s)

ω̄: the true rate averaged over the sample period (the gyro's low-pass filter and
decimation; so the samples integrate to the angle turned); s: the scale-factor error,
drawn once; b₀: the turn-on bias (zero-rate output), drawn once; b(t): the bias
instability, a first-order Gauss–Markov process; n: white rate noise, σ = N·√(rate) per
sample for a noise density N averaged over one sample period.

Numbers (defaults of `GyroSimConfig`) and where they come from:

- N = 0.005 °/s/√Hz: MPU-6000/MPU-6050 Product Specification PS-MPU-6000A-00 rev 3.4,
  §6.1 "Rate Noise Spectral Density" (at 10 Hz); its "Total RMS Noise" 0.05 °/s at the
  100 Hz filter setting is this density over 100 Hz, which is what the default 100 Hz
  sampling gives.
- b₀ ~ N(0, (20/3 °/s)²): §6.1 "Initial ZRO Tolerance ±20 °/s" (25 °C), read as a 3σ
  bound (pessimistic: units in the wild read a few °/s).
- s ~ N(0, 1 %²): §6.1 "Sensitivity Scale Factor Tolerance ±3 %" (25 °C) as 3σ.
- 131 LSB/(°/s), ±250 °/s full scale (FS_SEL = 0): §6.1 "Sensitivity Scale Factor".
- Bias instability 0.0012 °/s: the minimum of an Allan deviation of an MPU-6050 logged at
  500 Hz (Robotics Stack Exchange question 8860, "Angle Random Walk vs. Rate Noise
  Density (MPU6050)"; the datasheet gives no figure). A Gauss–Markov process's Allan
  deviation peaks at 0.62 σ near an averaging time of 1.9 τ, so σ = 0.0012/0.62 °/s; the
  correlation time τ = 50 s is an assumption (the minimum of such plots lies at tens of
  seconds).

Not modelled: the bias's temperature drift (§6.1: ±20 °/s over −40…85 °C; a trial is
minutes at room temperature), nonlinearity (0.2 %), cross-axis sensitivity (±2 %: the
walker barely rolls or pitches), linear-acceleration sensitivity (0.1 °/s/g).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hardware.checks import require_non_negative

DEG = math.pi / 180.0
LSB_PER_DEG_S = 131.0  # FS_SEL = 0
FULL_SCALE_LSB = 32767


@dataclass(frozen=True)
class GyroSimConfig:
    """The simulated gyro (module docstring: the numbers and their sources).

    enabled: record a GyroRate stream (off: the trial is exactly as without a gyro).
    rate_hz: samples per second (must divide the physics rate).
    noise_density_rad_s_sqrt_hz: white rate noise N; turn_on_bias_sigma_rad_s: σ of the
    constant bias b₀; bias_instability_rad_s and bias_correlation_s: σ and τ of the
    Gauss–Markov bias; scale_error_sigma: σ of the scale-factor error s; lsb_rad_s: the
    output's quantum (0: not quantised); turn_on_bias_rad_s / scale_error: fixed values
    instead of draws (None: drawn from the gyro's seed stream).
    """

    enabled: bool = False
    rate_hz: int = 100
    noise_density_rad_s_sqrt_hz: float = 0.005 * DEG
    turn_on_bias_sigma_rad_s: float = 20.0 / 3.0 * DEG
    bias_instability_rad_s: float = 0.0012 / 0.62 * DEG
    bias_correlation_s: float = 50.0
    scale_error_sigma: float = 0.01
    lsb_rad_s: float = DEG / LSB_PER_DEG_S
    turn_on_bias_rad_s: float | None = None
    scale_error: float | None = None

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError(f"gyro rate_hz must be > 0, got {self.rate_hz}")
        require_non_negative(
            self,
            (
                "noise_density_rad_s_sqrt_hz",
                "turn_on_bias_sigma_rad_s",
                "bias_instability_rad_s",
                "scale_error_sigma",
                "lsb_rad_s",
            ),
            "gyro",
        )
        if not self.bias_correlation_s > 0:
            raise ValueError(f"gyro bias_correlation_s must be > 0, got {self.bias_correlation_s}")


class SimGyro:
    """The gyro on the walker: `turn(dphi)` after each physics step with the true heading
    change, `sample()` at its rate gives the reported rate [rad/s] over the interval since
    the previous sample. Draws come from its own generator only."""

    def __init__(self, config: GyroSimConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        c = config
        self.turn_on_bias = (
            c.turn_on_bias_rad_s
            if c.turn_on_bias_rad_s is not None
            else float(rng.normal(0.0, c.turn_on_bias_sigma_rad_s))
        )
        self.scale_error = (
            c.scale_error
            if c.scale_error is not None
            else float(rng.normal(0.0, c.scale_error_sigma))
        )
        self.drift = float(rng.normal(0.0, c.bias_instability_rad_s))  # stationary start
        self._angle = 0.0  # true angle turned since the previous sample
        self._elapsed = 0.0

    @property
    def bias(self) -> float:
        """The bias now: turn-on bias + the Gauss–Markov instability [rad/s]."""
        return self.turn_on_bias + self.drift

    def turn(self, dphi: float, dt: float) -> None:
        """The walker turned by dphi [rad] (CCW) in dt [s]."""
        self._angle += dphi
        self._elapsed += dt

    def sample(self) -> float:
        """The rate the gyro reports for the interval since its previous sample (the first
        sample, at t = 0, covers one sample period of the walker at rest)."""
        c = self.config
        dt = self._elapsed or 1.0 / c.rate_hz
        a = math.exp(-dt / c.bias_correlation_s)
        step = c.bias_instability_rad_s * math.sqrt(1 - a * a)
        self.drift = a * self.drift + step * float(self.rng.standard_normal())
        noise = c.noise_density_rad_s_sqrt_hz / math.sqrt(dt) * float(self.rng.standard_normal())
        rate = (1.0 + self.scale_error) * self._angle / dt + self.bias + noise
        self._angle = self._elapsed = 0.0
        if c.lsb_rad_s > 0:
            lsb = min(max(round(rate / c.lsb_rad_s), -FULL_SCALE_LSB - 1), FULL_SCALE_LSB)
            rate = lsb * c.lsb_rad_s
        return rate
