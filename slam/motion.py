"""Motion models: odometry messages → increments (ds, dθ) with noise, and the exact arc.

Every localizer moves its pose(s) the same way: `OdometryModel.increment(msg)` turns an
`EncoderTicks` or `VelocityOdometry` message into an `Increment` (distance ds along an
arc that turns by dθ, and its 2×2 covariance); `apply_increment` moves poses along the
exact arc; `increment_jacobians` gives ∂pose'/∂pose and ∂pose'/∂(ds, dθ) for filters.

Noise (`MotionNoise`): each wheel's distance is a random walk, σ² = k_wheel·|d| (+ k_turn
for the turn's share). Velocity odometry errors are, by default (velocity_model "time"),
a random walk in time, so that the noise does not depend on the message rate: over dt,
var(ds) = (k_v|v|)²·dt and var(dθ) = (k_ω|ω| + c)²·dt (k_v, k_ω in 1/√s, c in rad/√s):
right for velocities measured or commanded over real time (MRCLAM). For velocities that
are a transport of integrated wheel odometry (CARMEN's ODOM poses, whose timestamps are
too unreliable for a rate: a 1 ms piece may carry centimetres), velocity_model
"distance" makes the errors a random walk in the path instead: var(ds) = k₁|ds| + k₂|dθ|,
var(dθ) = k₃|ds| + k₄|dθ| (`distance_walk`), whatever the timing. The opt-in
brake-aware variant inflates a wheel's variance with its logged brake torque τ:
σ² += k_brake·(τ/τ_max)·|d|, and can remove an expected under-report (bias) of
bias_per_full_brake·(τ/τ_max) of the distance (the slip the brake causes); for velocity
odometry it does the same to the two wheels' distances that (v, ω) stand for.

With a yaw-rate gyro (`MotionNoise.gyro.enabled`, `slam.gyro`), an increment keeps the
odometry's ds and its variance but takes dθ from the gyro, integrated over the same
interval and corrected by the online bias and scale estimate; var(dθ) is then the
gyro's and cov(ds, dθ) = 0 (independent sensors).
An increment from encoder ticks also carries each wheel's counted distance and brake
level, so that a localizer that estimates each wheel's slip coefficient k can recompute
it (`slip_corrected`: true distance = encoder distance / (1 − k·level)); with the gyro's
turn (`Increment.gyro_turn`) only its distance (slam.slip.increment_with_slip).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, replace

import numpy as np

from hardware.calibration import WalkerCalibration
from hardware.choices import Choice, coerce
from hardware.messages import BrakeCommand, EncoderTicks, GyroRate, Message, VelocityOdometry
from hardware.small_linalg import congruence
from slam.brake_schedule import BrakeSchedule
from slam.gyro import GyroFusion, GyroHeading


def arc_increment(ds: float, dtheta: float, theta: float) -> tuple[float, float]:
    """World-frame (dx, dy) of an exact arc of length ds turning by dtheta from heading theta.

    The chord of the arc has length ds·sinc(dθ/2) and points along θ + dθ/2; this form
    is exact for any dθ and stable as dθ → 0 (straight line).
    """
    half = 0.5 * dtheta
    chord = ds * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0)
    heading = theta + half
    return chord * math.cos(heading), chord * math.sin(heading)


def wheel_increment(ds_left: float, ds_right: float, track: float) -> tuple[float, float]:
    """(ds, dθ) of the axle centre from the distances rolled by the two wheels (eqs 4.9, 4.10)."""
    return 0.5 * (ds_left + ds_right), (ds_right - ds_left) / track


def _wheel_cov(var_left: float, var_right: float, track: float) -> np.ndarray:
    """The (ds, dθ) covariance of independent wheel distances with these variances:
    (ds, dθ) = J (d_left, d_right), J = [[1/2, 1/2], [−1/B, 1/B]]."""
    a, b = var_left, var_right
    return np.array(
        [[0.25 * (a + b), 0.5 * (b - a) / track], [0.5 * (b - a) / track, (a + b) / track**2]]
    )


def sinc_and_derivative(u: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """S(u) = sin(u)/u and S'(u), stable near 0 (for one float: two floats)."""
    if isinstance(u, float):
        return _sinc_and_derivative(u)
    u = np.asarray(u, dtype=float)
    small = np.abs(u) < 1e-4
    safe = np.where(small, 1.0, u)
    s = np.where(small, 1.0 - u * u / 6.0, np.sin(safe) / safe)
    ds = np.where(small, -u / 3.0, (safe * np.cos(safe) - np.sin(safe)) / (safe * safe))
    return s, ds


def _sinc_and_derivative(u: float) -> tuple[float, float]:
    """sinc_and_derivative of one float: the same operations on floats (math's sin and
    cos give numpy's bits here: tests/slam/test_motion.py), without the arrays."""
    if abs(u) < 1e-4:
        return 1.0 - u * u / 6.0, -u / 3.0
    sin_u = math.sin(u)
    return sin_u / u, (u * math.cos(u) - sin_u) / (u * u)


def apply_increment(
    poses: np.ndarray, ds: np.ndarray | float, dtheta: np.ndarray | float
) -> np.ndarray:
    """Move poses (..., 3) along exact arcs (ds, dθ) (broadcast, e.g. per particle)."""
    if (
        isinstance(ds, float)
        and isinstance(dtheta, float)
        and isinstance(poses, np.ndarray)
        and poses.shape == (3,)
    ):
        return _apply_one(poses, ds, dtheta)
    poses = np.asarray(poses, dtype=float)
    ds = np.asarray(ds, dtype=float)
    half = 0.5 * np.asarray(dtheta, dtype=float)
    s, _ = sinc_and_derivative(half)
    chord = ds * s
    h = poses[..., 2] + half
    out = np.empty(np.broadcast_shapes(poses.shape, (*np.shape(chord), 3)))
    out[..., 0] = poses[..., 0] + chord * np.cos(h)
    out[..., 1] = poses[..., 1] + chord * np.sin(h)
    out[..., 2] = np.mod(poses[..., 2] + 2 * half + np.pi, 2 * np.pi) - np.pi
    return out


def _apply_one(pose: np.ndarray, ds: float, dtheta: float) -> np.ndarray:
    """apply_increment of one pose (the odometry of a smoother or filter, every message):
    the same operations in the same order on floats."""
    x, y, th = (float(v) for v in pose)
    half = 0.5 * dtheta
    s, _ = _sinc_and_derivative(half)
    chord = ds * s
    h = th + half
    two_pi = 2 * math.pi
    return np.array(
        [
            x + chord * math.cos(h),
            y + chord * math.sin(h),
            (th + 2 * half + math.pi) % two_pi - math.pi,
        ]
    )


def increment_jacobians(theta: float, ds: float, dtheta: float) -> tuple[np.ndarray, np.ndarray]:
    """F = ∂pose'/∂pose (3×3) and G = ∂pose'/∂(ds, dθ) (3×2) of the exact arc."""
    half = 0.5 * float(dtheta)
    s, s_prime = _sinc_and_derivative(half)
    chord = ds * s
    dchord = 0.5 * ds * s_prime  # ∂chord/∂dθ
    h = theta + half
    c, sn = math.cos(h), math.sin(h)
    f = np.array([[1.0, 0.0, -chord * sn], [0.0, 1.0, chord * c], [0.0, 0.0, 1.0]])
    g = np.array(
        [
            [s * c, dchord * c - 0.5 * chord * sn],
            [s * sn, dchord * sn + 0.5 * chord * c],
            [0.0, 1.0],
        ]
    )
    return f, g


def carry_increment(
    delta: np.ndarray,
    cov: np.ndarray,
    ds: float,
    dth: float,
    q: np.ndarray,
    added: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The motion since a reference pose (delta, its 3×3 covariance) carried on by an
    increment along the exact arc: (delta', F cov Fᵀ + (G q Gᵀ, or `added` when given),
    F, G) with F, G as `increment_jacobians` at delta's heading."""
    f, g = increment_jacobians(delta[2], ds, dth)
    moved = apply_increment(delta, ds, dth)
    return moved, congruence(f, cov) + (congruence(g, q) if added is None else added), f, g


Pose = tuple[float, float, float]
Cov3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


def propagate(
    pose: Pose, cov: Cov3, ds: float, dtheta: float, q: np.ndarray
) -> tuple[Pose, Cov3, tuple[float, float]]:
    """One pose moved along the exact arc (ds, dθ) with its covariance, P' = F P Fᵀ + G Q Gᵀ,
    in closed form on floats (this runs for every odometry message; ~10× cheaper than the
    3×3 numpy products): F = [[1, 0, a], [0, 1, b], [0, 0, 1]] and G = ∂pose'/∂(ds, dθ) as
    `increment_jacobians`; Q the increment's 2×2 covariance. Returns (pose', P', (a, b)):
    a filter with more state (landmarks) moves its pose–landmark cross-covariance rows by
    F, i.e. row x += a·row θ and row y += b·row θ, and the (a, b) of successive steps add up.
    θ' is wrapped to [−π, π]."""
    x, y, th = pose
    dx, dy = arc_increment(ds, dtheta, th)
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = cov
    a, b = -dy, dx
    n00 = p00 + 2 * a * p02 + a * a * p22
    n01 = p01 + a * p12 + b * p02 + a * b * p22
    n02 = p02 + a * p22
    n11 = p11 + 2 * b * p12 + b * b * p22
    n12 = p12 + b * p22
    # G for the exact arc, written out (see increment_jacobians)
    half = 0.5 * dtheta
    s, sp = _sinc_and_derivative(half)
    chord, dchord = ds * s, 0.5 * ds * sp
    h = th + half
    c, sn = math.cos(h), math.sin(h)
    g = (
        (s * c, dchord * c - 0.5 * chord * sn),
        (s * sn, dchord * sn + 0.5 * chord * c),
        (0.0, 1.0),
    )
    q00, q01, q11 = float(q[0, 0]), float(q[0, 1]), float(q[1, 1])
    gq = [(r[0] * q00 + r[1] * q01, r[0] * q01 + r[1] * q11) for r in g]
    add = [[gq[i][0] * g[j][0] + gq[i][1] * g[j][1] for j in range(3)] for i in range(3)]
    new_cov = (
        (n00 + add[0][0], n01 + add[0][1], n02 + add[0][2]),
        (n01 + add[1][0], n11 + add[1][1], n12 + add[1][2]),
        (n02 + add[2][0], n12 + add[2][1], p22 + add[2][2]),
    )
    return (x + dx, y + dy, math.remainder(th + dtheta, 2.0 * math.pi)), new_cov, (a, b)


class VelocityModel(Choice):
    """How velocity odometry's noise grows (module docstring): with time or with distance."""

    TIME = "time"
    DISTANCE = "distance"


@dataclass(frozen=True)
class MotionNoise:
    """Odometry noise (see the module docstring); defaults suit the walker's encoders.

    wheel_m: per-wheel variance per metre rolled [m²/m] (0.0025: σ = 5 cm after 1 m, the
    thesis's 5 % encoder error); velocity_frac [1/√s], omega_frac [1/√s], omega_floor
    [rad/√s]: velocity odometry noise, σ over one second (module docstring). The defaults
    fit MRCLAM's commanded-velocity odometry (robot 1 of dataset 7, 1 s windows against
    the ground truth: σ(ds) = 0.011 m at a mean 0.056 m/s, σ(dθ) = 0.045 rad at a mean
    0.066 rad/s). velocity_model: "time" or "distance" (module docstring), with
    distance_walk = (k₁ [m²/m], k₂ [m²/rad], k₃ [rad²/m], k₄ [rad²/rad]), by default
    σ(ds) = 5 cm per metre, σ(dθ) = 0.1 rad per radian turned and 0.077 rad per metre;
    brake_aware: inflate (and optionally de-bias) a braked wheel.
    gyro: the turn from a yaw-rate gyro, its bias estimated online (`slam.gyro`); off by
    default.
    unknown_sigma: (σ of ds [m], σ of dθ [rad]) of a motion the odometry did not measure
    (velocity odometry of NaN: a gap in a log's odometry); a full turn by default.
    brake_delay_s: None: an increment's brake level is the last command's; a number:
    each command takes effect this much later (loop latency and brake lag; the simulator
    has 0.03 s + a 0.025 s time constant) and an increment's level is the time average
    of the levels in force over it (slam.brake_schedule). The level matters only with
    brake_aware or a slip estimate (slam.slip).
    """

    wheel_m: float = 0.0025
    velocity_frac: float = 0.2
    omega_frac: float = 0.2
    omega_floor: float = 0.03
    velocity_model: VelocityModel = VelocityModel.TIME
    distance_walk: tuple[float, float, float, float] = (0.0025, 0.001, 0.006, 0.01)
    brake_aware: bool = False
    brake_wheel_m: float = 0.02
    bias_per_full_brake: float = 0.0
    gyro: GyroFusion = field(default_factory=GyroFusion)
    brake_delay_s: float | None = None
    unknown_sigma: tuple[float, float] = (1.0, math.pi)

    def __post_init__(self) -> None:
        coerce(self, velocity_model=VelocityModel)
        if len(self.unknown_sigma) != 2 or not min(self.unknown_sigma) > 0:
            raise ValueError(f"unknown_sigma must be two values > 0, got {self.unknown_sigma}")
        if self.brake_delay_s is not None and not 0.0 <= self.brake_delay_s < math.inf:
            raise ValueError(f"brake_delay_s must be >= 0 (or None), got {self.brake_delay_s}")
        if len(self.distance_walk) != 4 or min(self.distance_walk) < 0:
            raise ValueError(f"distance_walk must be four values >= 0, got {self.distance_walk}")


def uses_gyro(config: object) -> bool:
    """Whether a localizer's config asks for the gyro: a MotionNoise among its fields with
    gyro fusion enabled."""
    return dataclasses.is_dataclass(config) and any(
        isinstance(value, MotionNoise) and value.gyro.enabled
        for value in (getattr(config, f.name) for f in dataclasses.fields(config))
    )


@dataclass(frozen=True)
class Increment:
    """Motion from t − dt to t: arc length ds, turn dθ and their 2×2 covariance.

    Also what a slip estimate needs (`slip_corrected`): wheels, each wheel's distance [m]
    (left, right) as counted by its encoder, before any brake-aware de-biasing (from
    velocity odometry, the distances its (v, ω) stand for on the calibration's track);
    brake_level, each brake's commanded level in [0, 1] over the increment; unknown: the
    odometry did not measure this motion (a gap: velocity odometry of NaN), so ds = dθ = 0
    and cov is MotionNoise.unknown_sigma's; gyro_turn: dθ is a gyro's (`slam.gyro`), which
    slip does not bias, so a slip estimate corrects ds alone."""

    t: float
    dt: float
    ds: float
    dtheta: float
    cov: np.ndarray
    wheels: tuple[float, float] | None = None
    brake_level: tuple[float, float] = (0.0, 0.0)
    unknown: bool = False
    gyro_turn: bool = False


def split_increment(inc: Increment, t: float) -> tuple[Increment, Increment]:
    """The increment's motion before and after time t, in proportion to time (the walker
    taken to move at a constant rate over an increment: the two arcs compose exactly to
    the whole); t is clipped to the increment's span. For a landmark observation made
    between two odometry messages, applied at the pose of its own time."""
    t0 = inc.t - inc.dt
    f = min(max((t - t0) / inc.dt, 0.0), 1.0) if inc.dt > 0 else 0.0
    parts = []
    for share, end, dt in ((f, t0 + f * inc.dt, f * inc.dt), (1.0 - f, inc.t, (1 - f) * inc.dt)):
        wheels = None if inc.wheels is None else (share * inc.wheels[0], share * inc.wheels[1])
        parts.append(
            Increment(
                end,
                dt,
                share * inc.ds,
                share * inc.dtheta,
                share * inc.cov,
                wheels,
                inc.brake_level,
                inc.unknown,
                inc.gyro_turn,
            )
        )
    return parts[0], parts[1]


# the most of a wheel's distance that slip may be taken to hide (k·level is clipped to it)
MAX_SLIP = 0.9


def slip_corrected(
    wheels: tuple[float, float], levels: tuple[float, float], k: np.ndarray, track: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ds, dθ) of an increment whose wheels slipped by s = k·level, and J = ∂(ds, dθ)/∂k.

    A wheel with slip ratio s rolls (1 − s) of the ground it covers, so its true distance
    is its encoder distance / (1 − k·level) (k·level clipped to ±MAX_SLIP, where J's
    column is 0). k (..., 2): (k_left, k_right), e.g. one row per particle; returns ds,
    dθ (...) and J (..., 2, 2), rows (ds, dθ), columns (k_left, k_right)."""
    k = np.asarray(k, dtype=float)
    level = np.asarray(levels, dtype=float)
    u = k * level
    inside = np.abs(u) < MAX_SLIP
    scale = 1.0 / (1.0 - np.clip(u, -MAX_SLIP, MAX_SLIP))
    d = np.asarray(wheels, dtype=float) * scale
    dd = np.where(inside, d * scale * level, 0.0)  # ∂d/∂k of each wheel
    j = np.empty((*k.shape[:-1], 2, 2))
    j[..., 0, :] = 0.5 * dd
    j[..., 1, 0] = -dd[..., 0] / track
    j[..., 1, 1] = dd[..., 1] / track
    ds, dth = wheel_increment(d[..., 0], d[..., 1], track)
    return ds, dth, j


class OdometryModel:
    """Turns odometry messages into increments; remembers the previous message."""

    def __init__(self, calibration: WalkerCalibration, noise: MotionNoise | None = None) -> None:
        self.cal = calibration
        self.noise = noise or MotionNoise()
        self._ticks: EncoderTicks | None = None
        self._velocity: VelocityOdometry | None = None
        self._brake_level = (0.0, 0.0)
        self.gyro = (
            GyroHeading(self.noise.gyro, calibration.metres_per_count / calibration.track_m)
            if self.noise.gyro.enabled
            else None
        )
        delay = self.noise.brake_delay_s
        self._brake_schedule = None if delay is None else BrakeSchedule(delay)

    @property
    def has_odometry(self) -> bool:
        """Whether an odometry message has been seen (the start of the trajectory)."""
        return self._ticks is not None or self._velocity is not None

    def increment(self, msg: Message) -> Increment | None:
        """The motion since the previous odometry message, or None (first or other msg)."""
        if isinstance(msg, EncoderTicks):
            prev, self._ticks = self._ticks, msg
            inc = None if prev is None else self._from_ticks(prev, msg)
            return self._with_gyro(prev or msg, msg, inc)
        if isinstance(msg, VelocityOdometry):
            prev, self._velocity = self._velocity, msg
            inc = None if prev is None else self._from_velocity(prev, msg)
            return self._with_gyro(prev or msg, msg, inc)
        if isinstance(msg, BrakeCommand):
            self._brake_level = self.cal.brake.levels(msg)
            if self.gyro is not None:
                self.gyro.brakes(msg.t, self._brake_level)
            if self._brake_schedule is not None:
                self._brake_schedule.command(msg.t, self._brake_level)
        elif isinstance(msg, GyroRate) and self.gyro is not None:
            self.gyro.add(msg)
        return None

    def _with_gyro(self, prev: Message, msg: Message, inc: Increment | None) -> Increment | None:
        """The increment with its turn from the gyro when gyro fusion is on and the gyro
        covers (prev.t, msg.t]; else as it is (`slam.gyro.GyroHeading.turn`, which also
        gets the odometry's turn and its variance without braking for the bias)."""
        if self.gyro is None:
            return inc
        if inc is None:
            self.gyro.turn(prev.t, msg.t, 0.0, 0.0)  # the start, or no time passed
            return None
        if isinstance(msg, EncoderTicks) and isinstance(prev, EncoderTicks):
            counts = abs(msg.left - prev.left) + abs(msg.right - prev.right)
            rolled = counts * self.cal.metres_per_count
            var = self.noise.gyro.encoder_wheel_m * rolled / self.cal.track_m**2
        else:
            var = float(inc.cov[1, 1])
        fused = self.gyro.turn(prev.t, msg.t, inc.dtheta, var)
        if fused is None:
            return inc
        dtheta, var = fused
        cov = np.array([[float(inc.cov[0, 0]), 0.0], [0.0, var]])
        # a gap in the odometry (unknown) is a measured turn now, its distance as wide
        return replace(inc, dtheta=dtheta, cov=cov, unknown=False, gyro_turn=True)

    def diagnostics(self) -> dict:
        """The gyro's bias and scale estimates, windows, fallbacks (empty without it)."""
        return {} if self.gyro is None else {"gyro": self.gyro.diagnostics()}

    def _from_ticks(self, prev: EncoderTicks, msg: EncoderTicks) -> Increment:
        n = self.noise
        m_left, m_right = self.cal.metres_per_count_per_wheel
        d = [(msg.left - prev.left) * m_left, (msg.right - prev.right) * m_right]
        counted = (d[0], d[1])
        levels = self._levels(prev.t, msg.t)
        var = [n.wheel_m * abs(d[0]), n.wheel_m * abs(d[1])]
        self._brake_aware(d, var, levels)
        track = self.cal.track_m
        ds, dth = wheel_increment(d[0], d[1], track)
        return Increment(msg.t, msg.t - prev.t, ds, dth, _wheel_cov(*var, track), counted, levels)

    def _levels(self, t0: float, t1: float) -> tuple[float, float]:
        """The brake levels over [t0, t1]: the schedule's mean when commands are
        scheduled, else the latest command's."""
        if self._brake_schedule is not None:
            return self._brake_schedule.mean(t0, t1)
        return self._brake_level

    def _brake_aware(self, d: list[float], var: list[float], levels) -> None:
        """With `noise.brake_aware`: each wheel's distance d grown by the under-report its
        brake level causes and its variance var by the braked-wheel term (in place); the
        same for encoder ticks and for the wheels a velocity odometry stands for."""
        n = self.noise
        if not n.brake_aware:
            return
        for i in (0, 1):
            var[i] += n.brake_wheel_m * levels[i] * abs(d[i])
            d[i] /= 1.0 - min(n.bias_per_full_brake * levels[i], 0.9)

    def _from_velocity(self, prev: VelocityOdometry, msg: VelocityOdometry) -> Increment | None:
        dt = msg.t - prev.t
        if dt <= 0:
            return None
        n = self.noise
        if math.isnan(prev.v) or math.isnan(prev.omega):  # the motion is not known
            cov = np.diag(np.square(n.unknown_sigma))
            return Increment(msg.t, dt, 0.0, 0.0, cov, None, self._levels(prev.t, msg.t), True)
        ds, dth = prev.v * dt, prev.omega * dt
        if n.velocity_model == "distance":
            k1, k2, k3, k4 = n.distance_walk
            cov = np.diag([k1 * abs(ds) + k2 * abs(dth), k3 * abs(ds) + k4 * abs(dth)])
        else:
            sv = n.velocity_frac * abs(prev.v)
            sw = n.omega_frac * abs(prev.omega) + n.omega_floor
            cov = np.diag([sv * sv * dt, sw * sw * dt])
        # The wheels' distances a differential drive's (v, ω) stand for, and the brake
        # levels over the increment: what a slip estimate corrects (slam.slip).
        track = self.cal.track_m
        wheels = (ds - 0.5 * dth * track, ds + 0.5 * dth * track)
        levels = self._levels(prev.t, msg.t)
        if n.brake_aware:
            d, var = list(wheels), [0.0, 0.0]
            self._brake_aware(d, var, levels)
            ds, dth = wheel_increment(d[0], d[1], track)
            cov = cov + _wheel_cov(*var, track)
        return Increment(msg.t, dt, ds, dth, cov, wheels, levels)
