"""Closed-loop braking (thesis §5.3.2, eqs 5.11 and 5.14–5.16).

Each tick the controller

1. estimates the user's handle forces from the measured forward speed v, yaw rate φ̇ and
   the brake forces currently applied, by inverting the steady-state dynamics (5.11) —
   optionally with the inertial terms m v̇, I φ̈ added and low-passed (see below);
2. finds the nearest obstacle ahead (distance d from the depth camera) and, if it is
   closer than d_max, picks the turn side from the polar free-space integrals (§5.2) and
   the desired radius R_d = ±(d + radius_offset_m) (+ = turn left);
3. solves for the least total braking that gives R_d at steady state: the outer brake at
   its minimum, φ̇_d from (5.16), v_d = R_d φ̇_d, and the inner brake from (5.14), clamped
   to the brake's limits.

Brake force and torque are related by the *wheel radius*, F_b = τ / r_wheel (the thesis
code used r_b and treated the torque limits as forces; see EQUATIONS.md). The model
parameters D, Dφ, α, r_b are the controller's own belief and may differ from the walker's.

Below d_min the obstacle is already inside the distance at which the walker can still
pivot about one stationary rear wheel without hitting it (the thesis's reason for
d_min), so no steady radius is worth solving for: the inner brake goes to its maximum
and the outer to its minimum (the tightest turn the walker can make, as the open loop's
V = 12 V below d_min). Beyond d_max, and while not moving forward, both brakes are at
their minimum.

Why the estimate is not 5.11 alone: 5.11 assumes the walker is at steady state. Right
after a brake change it is not, and 5.11 attributes the whole change to the user (the
estimated push rises with the brake force until the walker has slowed). Fed back through
5.14 that is a positive feedback of gain ≈ 1 at high frequency — in effect an integrator
that corrects the whole radius error every 0.1 s tick on a walker whose time constants
are m/D ≈ 2 s and I/Dφ ≈ 1 s. In simulation (true parameters, constant push, R_d = 2 m)
the thesis's form never settles: the inner brake cycles between its minimum and ~3 N·m
and the radius between ~1.2 and 3.6 m (period ~3.5 s). Adding the inertial terms m v̇ and
I φ̈ (the full dynamics 5.2–5.3 instead of their steady state) and a 0.3 s low-pass on the
estimate makes it settle: within 10 % of R_d 1–4 s after starting from rest, within 2 %
after that (tests/experiments/test_closed_loop_sim.py).

Why the default is nevertheless 5.11 alone (mass_kg = yaw_inertia = handle_filter_s = 0):
it is the thesis's controller, and its over-estimate of the push right after the brakes
engage is what makes it turn corners. The thesis says as much (§6.3.3: the handle force
prediction "would be artificially high, causing the control algorithm to apply more force
to the brakes and thus a tighter turn"). In the simulated corner test (1.0–1.1 m/s, d_max
1.25 m) the steady-state form turns 97° and clears the wall by 2–6 cm, as the thesis's
Fig 6.7 shows for 1250 mm, while the settling form brakes for R_d = d + 0.5 m — a circle
that cannot clear a wall d ahead — and hits it head-on. The settling form is the better
radius tracker; the radius rule is what it exposes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from control.base import ControlInput, Controller
from control.perception import distance_ahead, turn_direction
from hardware.calibration import WalkerCalibration
from hardware.geometry import to_walker_frame
from hardware.messages import BrakeCommand
from hardware.registry import Spec


@dataclass(frozen=True)
class ClosedLoopConfig:
    """Closed-loop braking parameters (defaults: the thesis code's values).

    D: translational damping the controller assumes [N·s/m] (measured 9–30; 16 used);
    D_phi: rotational damping it assumes [N·m·s/rad] (7 in the thesis code; the spin
    trials measured 10.9 ± 0.95);
    alpha: handle-to-brake lever ratio r_h / r_b (46/64);
    r_b: half the rear track, centre line to the rear wheel [m] (0.32);
    d_min_m / d_max_m: pivot below d_min, least-braking turn between, no braking beyond
    d_max [m] (front distance measured from the depth camera, as the thesis);
    radius_offset_m: desired radius R_d = d + radius_offset_m [m] (0.5);
    half_width_m: half-width of the band ahead searched for obstacles (walker 0.69 m);
    arc_half_deg / n_arcs: the turn-decision fan (±60°, 32 sub-arcs: the closed-loop code);
    unseen_free_radius_m: free radius of arcs outside the view with no obstacle (1 m in the
    closed-loop code);
    latch_turn: keep the side chosen when a braking episode starts until it ends (as
    OpenLoopConfig.latch_turn; False: decide every tick, as the thesis code);
    min_speed_mps: brakes act only while moving forward faster than this;
    wheel_speed_eps_mps: the brake force applied opposes each wheel's rolling and is
    scaled down linearly below this wheel speed (as the simulated brakes) when the current
    brake forces are reconstructed from the applied torques;
    mass_kg / yaw_inertia: the m v̇ and I φ̈ terms added to the handle-force estimate
    (0 and 0: the thesis's steady-state eq 5.11; the walker's values are 31.5 kg and
    8.69 kg·m², which with handle_filter_s 0.3 make a commanded radius settle — see the
    module docstring for why that is not the default);
    handle_filter_s: time constant of a first-order low-pass on the estimated handle
    forces [s] (0: none).
    v and φ̇ come from the pipeline, averaged over the last two control steps (thesis);
    v̇ and φ̈ are their differences between ticks. See "Why the estimate is not 5.11
    alone" in the module docstring.
    """

    D: float = 16.0
    D_phi: float = 7.0
    alpha: float = 46.0 / 64.0
    r_b: float = 0.32
    d_min_m: float = 0.45
    d_max_m: float = 1.25
    radius_offset_m: float = 0.5
    half_width_m: float = 0.345
    arc_half_deg: float = 60.0
    n_arcs: int = 32
    unseen_free_radius_m: float = 1.0
    min_speed_mps: float = 0.05
    wheel_speed_eps_mps: float = 0.02
    mass_kg: float = 0.0
    yaw_inertia: float = 0.0
    handle_filter_s: float = 0.0
    latch_turn: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.d_min_m < self.d_max_m:
            raise ValueError(f"need 0 <= d_min < d_max, got {self.d_min_m}, {self.d_max_m}")
        for name in ("D", "D_phi", "alpha", "r_b", "wheel_speed_eps_mps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("mass_kg", "yaw_inertia", "handle_filter_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.radius_offset_m < 0:
            raise ValueError(f"radius_offset_m must be >= 0, got {self.radius_offset_m}")


# -- the model, as pure functions ---------------------------------------------------------


def handle_forces(
    v: float,
    omega: float,
    brake_left_n: float,
    brake_right_n: float,
    D: float,
    D_phi: float,
    alpha: float,
    r_b: float,
) -> tuple[float, float]:
    """Handle forces (F_hL, F_hR) [N] that hold (v, φ̇) at steady state under the given
    brake forces (eq 5.11)."""
    total = v * D + (brake_left_n + brake_right_n)
    diff = omega * D_phi / (r_b * alpha) + (brake_right_n - brake_left_n) / alpha
    return 0.5 * (total - diff), 0.5 * (total + diff)


def handle_forces_dynamic(
    v: float,
    omega: float,
    v_dot: float,
    omega_dot: float,
    brake_left_n: float,
    brake_right_n: float,
    D: float,
    D_phi: float,
    alpha: float,
    r_b: float,
    mass: float,
    inertia: float,
) -> tuple[float, float]:
    """Handle forces (F_hL, F_hR) [N] from the full dynamics (5.2, 5.3) rather than their
    steady state: eq 5.11 with D v → D v + m v̇ and Dφ φ̇ → Dφ φ̇ + I φ̈."""
    return handle_forces(
        v + mass * v_dot / D,
        omega + inertia * omega_dot / D_phi,
        brake_left_n,
        brake_right_n,
        D,
        D_phi,
        alpha,
        r_b,
    )


def brake_forces(
    v_d: float,
    omega_d: float,
    handle_left_n: float,
    handle_right_n: float,
    D: float,
    D_phi: float,
    alpha: float,
    r_b: float,
) -> tuple[float, float]:
    """Brake forces (F_bL, F_bR) [N] that give the steady state (v_d, φ̇_d) under the given
    handle forces (eq 5.14). Unclamped: they may be negative or beyond the brake's limit."""
    s = handle_left_n + handle_right_n
    d = handle_right_n - handle_left_n
    yaw = omega_d * D_phi / r_b
    left = 0.5 * (-v_d * D + s + yaw - alpha * d)
    right = 0.5 * (-v_d * D + s - yaw + alpha * d)
    return left, right


def least_braking_yaw_rate(
    radius: float,
    handle_left_n: float,
    handle_right_n: float,
    brake_min_n: float,
    D: float,
    D_phi: float,
    alpha: float,
    r_b: float,
) -> float:
    """Desired yaw rate φ̇_d for radius R (≠ 0, + = left) with the outer brake at its
    minimum force (eq 5.16)."""
    s = handle_left_n + handle_right_n
    d = handle_right_n - handle_left_n
    if radius > 0:  # turn left: the right brake is the outer one
        return -(2.0 * brake_min_n - s - alpha * d) / (D_phi / r_b + radius * D)
    if radius < 0:  # turn right: the left brake is the outer one
        return (2.0 * brake_min_n - s + alpha * d) / (D_phi / r_b - radius * D)
    raise ValueError("radius must be non-zero")


def least_braking_forces(
    radius: float,
    handle_left_n: float,
    handle_right_n: float,
    brake_min_n: float,
    brake_max_n: float,
    D: float,
    D_phi: float,
    alpha: float,
    r_b: float,
) -> tuple[float, float]:
    """Brake forces (F_bL, F_bR) [N] for the desired radius with least total braking
    (eqs 5.14–5.16): outer brake at brake_min_n, inner from (5.14) at v_d = R φ̇_d, clamped
    to [brake_min_n, brake_max_n]. An infinite radius (straight on) releases both."""
    if not math.isfinite(radius):
        return brake_min_n, brake_min_n
    omega_d = least_braking_yaw_rate(
        radius, handle_left_n, handle_right_n, brake_min_n, D, D_phi, alpha, r_b
    )
    left, right = brake_forces(
        radius * omega_d, omega_d, handle_left_n, handle_right_n, D, D_phi, alpha, r_b
    )
    clamp = lambda f: min(max(f, brake_min_n), brake_max_n)  # noqa: E731
    if radius > 0:
        return clamp(left), brake_min_n
    return brake_min_n, clamp(right)


# -- the controller -----------------------------------------------------------------------


class ClosedLoop(Controller):
    """See the module docstring. Diagnostics of the last tick: last_distance (front
    distance, m), last_radius (signed desired radius, inf when not turning), last_handle
    (estimated F_hL, F_hR in N), last_direction (+1 left, −1 right, 0 none)."""

    def __init__(self, config: ClosedLoopConfig, calibration: WalkerCalibration) -> None:
        self.config = config
        self.cal = calibration
        off = calibration.brake.torque_off_nm
        self._last_torque = (off, off)
        self.last_distance = math.inf
        self.last_radius = math.inf
        self.last_direction = 0
        self.last_handle = (math.nan, math.nan)
        self._handle: tuple[float, float] | None = None
        self._prev: tuple[float, float, float] | None = None  # t, v, φ̇ of the last tick

    @property
    def wheel_radius_m(self) -> float:
        return 0.5 * self.cal.wheel_diameter_m

    def desired_radius(self, inp: ControlInput, points_walker: np.ndarray) -> float:
        """Signed desired turn radius (+ = left): inf for no braking, |R| <= r_b for a pivot
        about the inner wheel (inner brake full), else R_d = ±(d + radius_offset_m)."""
        cfg = self.config
        d = distance_ahead(points_walker, self.cal, cfg.half_width_m)
        self.last_distance = d
        if d > cfg.d_max_m:
            return math.inf
        direction = turn_direction(points_walker, self.cal, cfg, self.last_direction)
        if d <= cfg.d_min_m:
            return direction * cfg.r_b
        return direction * (d + cfg.radius_offset_m)

    def applied_brake_forces(self, inp: ControlInput) -> tuple[float, float]:
        """Brake forces at the ground [N] from the torques currently applied (the input's,
        else this controller's last command): τ / r_wheel, opposing each wheel's rolling."""
        cfg = self.config
        torque = inp.brake_nm if all(math.isfinite(x) for x in inp.brake_nm) else self._last_torque
        r_w = self.wheel_radius_m
        speeds = (inp.v - cfg.r_b * inp.omega, inp.v + cfg.r_b * inp.omega)
        eps = cfg.wheel_speed_eps_mps
        return tuple(  # type: ignore[return-value]
            tau / r_w * max(-1.0, min(1.0, u / eps)) for tau, u in zip(torque, speeds, strict=True)
        )

    def _out(self, t: float, left_nm: float, right_nm: float) -> BrakeCommand:
        self._last_torque = (left_nm, right_nm)
        return BrakeCommand(t, left_nm, right_nm, "closed-loop")

    def estimate_handle_forces(self, inp: ControlInput) -> tuple[float, float]:
        """Handle forces from this tick's v, φ̇, their change since the last tick and the
        applied brake forces (eq 5.11 plus the inertial terms), low-passed with time
        constant handle_filter_s."""
        cfg = self.config
        f_bl, f_br = self.applied_brake_forces(inp)
        prev, self._prev = self._prev, (inp.t, inp.v, inp.omega)
        dt = inp.t - prev[0] if prev is not None else 0.0
        v_dot = (inp.v - prev[1]) / dt if prev is not None and dt > 0 else 0.0
        omega_dot = (inp.omega - prev[2]) / dt if prev is not None and dt > 0 else 0.0
        raw = handle_forces_dynamic(
            inp.v,
            inp.omega,
            v_dot,
            omega_dot,
            f_bl,
            f_br,
            cfg.D,
            cfg.D_phi,
            cfg.alpha,
            cfg.r_b,
            cfg.mass_kg,
            cfg.yaw_inertia,
        )
        if self._handle is None or cfg.handle_filter_s <= 0 or not dt > 0:
            est = raw
        else:
            a = 1.0 - math.exp(-dt / cfg.handle_filter_s)
            est = (
                self._handle[0] + a * (raw[0] - self._handle[0]),
                self._handle[1] + a * (raw[1] - self._handle[1]),
            )
        self._handle = est
        return est

    def command(self, inp: ControlInput) -> BrakeCommand:
        cfg, brake = self.config, self.cal.brake
        off, full = brake.torque_off_nm, brake.torque_max_nm
        # The estimate runs every tick, so its filter and v̇, φ̈ are warm when braking starts.
        f_hl, f_hr = self.last_handle = self.estimate_handle_forces(inp)
        if inp.v <= cfg.min_speed_mps:
            self.last_radius, self.last_direction = math.inf, 0
            return self._out(inp.t, off, off)
        pts = to_walker_frame(inp.occupied_xy, inp.pose)
        radius = self.desired_radius(inp, pts)
        self.last_radius = radius
        if not math.isfinite(radius):
            self.last_direction = 0
            return self._out(inp.t, off, off)
        self.last_direction = 1 if radius > 0 else -1
        if abs(radius) <= cfg.r_b:  # pivot about the inner wheel
            if radius > 0:
                return self._out(inp.t, full, off)
            return self._out(inp.t, off, full)
        r_w = self.wheel_radius_m
        model = (cfg.D, cfg.D_phi, cfg.alpha, cfg.r_b)
        left, right = least_braking_forces(radius, f_hl, f_hr, off / r_w, full / r_w, *model)
        return self._out(inp.t, brake.clamp(left * r_w), brake.clamp(right * r_w))


SPEC = Spec(
    "closed-loop",
    ClosedLoopConfig,
    ClosedLoop,
    "least one-sided braking for the radius R = d + 0.5 m, eqs 5.11, 5.14-5.16",
)
