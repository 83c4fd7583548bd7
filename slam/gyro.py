"""Heading from a yaw-rate gyro, with its bias and scale error estimated online.

`GyroHeading` is what `slam.motion.OdometryModel` consults when `MotionNoise.gyro` is
enabled: an odometry increment then keeps the encoders' distance ds but takes its turn
dθ from the gyro, the rate integrated over the increment's interval and corrected by
the estimated bias and scale error.

Integration (`GyroIntegrator`). Each `GyroRate` sample is the mean rate over the
interval since the previous one, so the raw angle Θ(t) is exact at the sample times and
linear in between. An increment that ends between samples, or after the latest one (the
encoder ticks of an instant may come before the gyro sample of that instant), takes the
latest rate on to its end; the next sample settles the difference, which the next
increment then carries. The increments' turns thus always add up to Θ at the latest
sample, whatever the two streams' rates and interleaving. Without a sample for
`max_hold_s`, an increment falls back to the encoders' turn (counted).

Bias and scale (`GyroBiasFilter`). The gyro reports r = (1 + s)·ω + b + n. A small
Kalman filter estimates the bias b (a random walk from a prior σ of the part's turn-on
tolerance) and the scale error s, with a third state: the heading error that the
estimates in use have put into the integrated heading since the start. Its measurements
are windows of `window_s` during which both brakes have been released for at least
`settle_s`: without braking the rear wheels do not slip, so the encoders' turn E over a
window is a slip-free measurement of the true turn, and the raw gyro angle G over the
same window of length T gives

    G − b̂·T − (1 + ŝ)·E = δb·T + δs·E + noise

(δ: the estimates' errors; noise: the gyro's white noise over T, the encoders' turn
noise without braking, `encoder_wheel_m`, and their count quantisation). At a standstill
E = 0 and the
window measures the bias alone; while the walker turns, the turn is in E and in G alike,
so it is not taken for bias — it measures the scale error. A window a brake cuts short
is used as far as it got. Each update also corrects the heading integrated so far
(through the filter's heading-error state): the increment after it carries that
correction, so a large turn-on bias learned in the first seconds does not stay in the
heading. An increment's dθ variance is the gyro's: N²·dt + σ_b²·dt² + σ_s²·dθ².
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from hardware.checks import require_non_negative
from hardware.messages import GyroRate

DEG = math.pi / 180.0


@dataclass(frozen=True)
class GyroFusion:
    """Gyro fusion in the odometry model (module docstring); defaults describe an
    InvenSense MPU-6050 (the simulated part, `hardware.sim.gyro`).

    enabled: take each increment's turn from the gyro (a source without gyro messages
    is then refused by the commands, naming it).
    noise_density_rad_s_sqrt_hz: white rate noise N (datasheet: 0.005 °/s/√Hz).
    bias_sigma_rad_s: prior σ of the bias (the datasheet's ±20 °/s turn-on tolerance).
    bias_walk_rad_s_sqrt_s: random walk of the bias [rad/s/√s] (the simulated part's
    bias instability as a walk: √(2σ²/τ)).
    scale_error: the scale error to start from (a bench calibration's; 0: none) and
    scale_sigma its σ (uncalibrated: the datasheet's ±3 %); 0: the scale error is not
    estimated.
    encoder_wheel_m: per-wheel variance per metre rolled [m²/m] of the encoders' turn
    while both brakes are released, besides their count quantisation, for the bias
    windows (MotionNoise.wheel_m covers braked slip too). The simulated encoders' turn
    error over 1 s windows without braking is the quantisation alone (σ 2.3e-3 rad
    measured on dusty thesis-course trials, seeds 0–2, against 2.25e-3 expected); 1e-5
    (σ 0.7 ° of turn per metre rolled) is a margin for real floors and tyres.
    window_s: length of a bias measurement window; settle_s: how long both brakes must
    have been released before a window starts; released_level: a brake at most this
    share of its torque range above its residual torque counts as released.
    max_hold_s: how long after the latest gyro sample its rate is carried on.
    error_horizon_s: the bias and scale errors are the same from one increment to the
    next; an increment's var(dθ) takes them as a random walk that reaches their true
    effect, (δb + δs·ω)·H, after this time H.
    correct_heading: an update of the bias and scale estimates also takes out the
    heading error their earlier values caused. Right for dead reckoning (whose config
    turns it on); a filter or smoother whose observations have corrected its heading
    meanwhile would get the correction twice.
    """

    enabled: bool = False
    noise_density_rad_s_sqrt_hz: float = 0.005 * DEG
    bias_sigma_rad_s: float = 20.0 * DEG
    bias_walk_rad_s_sqrt_s: float = 0.0012 / 0.62 * DEG * math.sqrt(2.0 / 50.0)
    scale_error: float = 0.0
    scale_sigma: float = 0.03
    encoder_wheel_m: float = 1e-5
    window_s: float = 1.0
    settle_s: float = 0.3
    released_level: float = 0.01
    max_hold_s: float = 0.1
    error_horizon_s: float = 10.0
    correct_heading: bool = False

    def __post_init__(self) -> None:
        require_non_negative(
            self,
            (
                "noise_density_rad_s_sqrt_hz",
                "bias_sigma_rad_s",
                "bias_walk_rad_s_sqrt_s",
                "scale_sigma",
                "encoder_wheel_m",
                "settle_s",
                "released_level",
                "max_hold_s",
                "error_horizon_s",
            ),
            "gyro",
        )
        if not (math.isfinite(self.scale_error) and self.scale_error > -1.0):
            raise ValueError(f"gyro.scale_error must be > -1, got {self.scale_error}")
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"gyro.window_s must be > 0, got {self.window_s}")


class GyroIntegrator:
    """The raw gyro angle Θ(t) [rad] from rate samples (module docstring, "Integration");
    the latest samples are kept, so Θ is exact at any time since the oldest of them."""

    def __init__(self, max_hold_s: float, keep: int = 64) -> None:
        self.max_hold_s = max_hold_s
        self.times: deque[float] = deque(maxlen=keep)  # sample times
        self.angles: deque[float] = deque(maxlen=keep)  # Θ at them
        self.rate = 0.0  # the latest sample's rate, carried on after it

    def add(self, msg: GyroRate) -> None:
        """A sample: its rate held over the interval since the previous one (a sample
        older than the latest is ignored)."""
        if not self.times:
            self.times.append(msg.t)
            self.angles.append(0.0)
        elif msg.t > self.times[-1]:
            self.angles.append(self.angles[-1] + msg.rate_rad_s * (msg.t - self.times[-1]))
            self.times.append(msg.t)
        else:
            return
        self.rate = msg.rate_rad_s

    def angle_at(self, t: float) -> float | None:
        """Θ(t): interpolated between kept samples, carried on up to max_hold_s after the
        latest; None before the oldest kept sample, after the hold, or without samples."""
        if not self.times or t < self.times[0] or t - self.times[-1] > self.max_hold_s:
            return None
        if t >= self.times[-1]:
            return self.angles[-1] + self.rate * (t - self.times[-1])
        k = bisect.bisect_left(self.times, t)  # times[k - 1] < t <= times[k]
        if k == 0:
            return self.angles[0]
        t0, t1 = self.times[k - 1], self.times[k]
        a0, a1 = self.angles[k - 1], self.angles[k]
        return a1 - (a1 - a0) / (t1 - t0) * (t1 - t)


class GyroBiasFilter:
    """Kalman filter on the errors x = (heading error e, bias error δb, scale error δs) of
    the gyro heading, with the estimates b̂, ŝ (module docstring, "Bias and scale")."""

    def __init__(self, config: GyroFusion) -> None:
        self.config = config
        self.bias = 0.0
        self.scale = config.scale_error
        self.P = np.diag([0.0, config.bias_sigma_rad_s**2, config.scale_sigma**2])
        self.correction = 0.0  # heading correction [rad] owed to the next increment
        self.updates = 0

    def turn(self, raw: float, dt: float) -> float:
        """The corrected turn of an interval whose raw gyro angle is `raw`, and the error
        covariance moved over it: e += δb·dt + δs·dθ + noise, the bias walks."""
        dtheta = (raw - self.bias * dt) / (1.0 + self.scale)
        f = np.array([[1.0, dt, dtheta], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        c = self.config
        q = np.diag([c.noise_density_rad_s_sqrt_hz**2 * dt, c.bias_walk_rad_s_sqrt_s**2 * dt, 0.0])
        self.P = f @ self.P @ f.T + q
        return dtheta

    def turn_variance(self, dt: float, dtheta: float) -> float:
        """Variance of one increment's corrected turn: white noise N²·dt, and the bias and
        scale errors as a random walk over the error horizon H: H·dt·(σ_b² + σ_s²·ω²)."""
        c = self.config
        n, h = c.noise_density_rad_s_sqrt_hz, c.error_horizon_s
        omega = dtheta / dt
        return n * n * dt + h * dt * (self.P[1, 1] + self.P[2, 2] * omega * omega)

    def update(self, gyro: float, encoders: float, duration: float, variance: float) -> None:
        """A window of `duration` [s]: raw gyro angle `gyro`, the encoders' turn `encoders`
        and its variance (the gyro's white noise is added here)."""
        c = self.config
        y = gyro - self.bias * duration - (1.0 + self.scale) * encoders
        h = np.array([0.0, duration, encoders])
        r = c.noise_density_rad_s_sqrt_hz**2 * duration + (1.0 + self.scale) ** 2 * variance
        ph = self.P @ h
        k = ph / (h @ ph + r)
        dx = k * y
        self.bias += dx[1]
        self.scale += dx[2]
        if c.correct_heading:
            self.correction -= dx[0]  # the heading had error e: take it out
        ikh = np.eye(3) - np.outer(k, h)
        self.P = ikh @ self.P @ ikh.T + r * np.outer(k, k)  # Joseph form
        self.updates += 1

    def take_correction(self) -> float:
        """The heading correction owed, once."""
        out, self.correction = self.correction, 0.0
        return out


@dataclass
class _Window:
    """A bias measurement window being filled."""

    gyro: float = 0.0
    encoders: float = 0.0
    variance: float = 0.0
    duration: float = 0.0


class GyroHeading:
    """Turns from the gyro for the odometry model: samples in, brake state in, each
    increment's turn and its variance out (module docstring)."""

    def __init__(self, config: GyroFusion, count_quantum_rad: float = 0.0) -> None:
        """count_quantum_rad: the turn of one encoder count on one wheel (metres per count /
        track), for the quantisation of a window's encoder turn (0: none)."""
        self.config = config
        self.integrator = GyroIntegrator(config.max_hold_s)
        self.filter = GyroBiasFilter(config)
        self.quantisation_var = count_quantum_rad**2 / 3.0  # both wheels, both ends
        self._mark: float | None = None  # Θ at the previous odometry message
        self._window = _Window()
        self._braking = False
        self._settled_at = -math.inf  # when the brakes' last release has settled
        self.fallbacks = 0

    def add(self, msg: GyroRate) -> None:
        self.integrator.add(msg)

    def brakes(self, t: float, levels: tuple[float, float]) -> None:
        """The brake command at t as levels in [0, 1] above the residual torque."""
        braking = max(levels) > self.config.released_level
        if braking:
            self._close_window()
        elif self._braking:
            self._settled_at = t + self.config.settle_s
        self._braking = braking

    def turn(
        self, t0: float, t1: float, encoder_turn: float, encoder_var: float
    ) -> tuple[float, float] | None:
        """(dθ, its variance) over (t0, t1] from the gyro, or None when the gyro does not
        cover it (the caller keeps the encoders' turn). Call it for every odometry
        message, also the first (t0 = t1), so the integration starts there."""
        angle = self.integrator.angle_at(t1)
        mark, self._mark = self._mark, angle
        if t1 <= t0:
            return None
        if mark is None:  # the gyro did not cover t0 then: it may now (same instant)
            mark = self.integrator.angle_at(t0)
        if angle is None or mark is None:
            self.fallbacks += 1
            self._close_window()
            return None
        raw, dt = angle - mark, t1 - t0
        dtheta = self.filter.turn(raw, dt)
        variance = self.filter.turn_variance(dt, dtheta)
        self._measure(t0, t1, raw, encoder_turn, encoder_var)
        return dtheta + self.filter.take_correction(), variance

    def _measure(self, t0: float, t1: float, raw: float, turn: float, var: float) -> None:
        """Add the interval to the bias window when the wheels cannot have slipped."""
        if self._braking or t0 < self._settled_at:
            self._close_window()
            return
        w = self._window
        w.gyro += raw
        w.encoders += turn
        w.variance += var
        w.duration += t1 - t0
        if w.duration >= self.config.window_s - 1e-9:
            self._close_window()

    def _close_window(self) -> None:
        w = self._window
        if w.duration > 0:
            self.filter.update(w.gyro, w.encoders, w.duration, w.variance + self.quantisation_var)
        self._window = _Window()

    def diagnostics(self) -> dict:
        f = self.filter
        return {
            "bias_rad_s": float(f.bias),
            "bias_sigma_rad_s": math.sqrt(f.P[1, 1]),
            "scale_error": float(f.scale),
            "scale_sigma": math.sqrt(f.P[2, 2]),
            "bias_windows": f.updates,
            "encoder_fallbacks": self.fallbacks,
        }
