"""Rigid-body dynamics of the braking walker (thesis eqs 5.1–5.4) and its brakes.

State: planar pose of the rear-axle centre (x, y, φ), forward speed v and yaw rate φ̇.
The rear axle cannot move sideways (5.4), so (v, φ̇) are the only velocities:

    m v̇  = (F_hL − F_bL) + (F_hR − F_bR) − D v
    I φ̈  = r_b [(α F_hR − F_bR) − (α F_hL − F_bL)] − Dφ φ̇

F_h are the user's forward handle forces; F_b are the brake forces at the ground, which
oppose each wheel's rolling and are bounded by brake torque / wheel radius. Brake torque
follows its command through a first-order lag (the magnetic-particle brake's 20–35 ms
response).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WalkerParams:
    """True physical parameters of the simulated walker (defaults: the thesis walker)."""

    mass_kg: float = 31.5  # walker + the user's weight on the handles
    yaw_inertia: float = 8.69  # kg·m², bifilar pendulum (6.1)
    damping: float = 16.0  # D, N·s/m
    yaw_damping: float = 9.0  # Dφ, N·m·s/rad (7–11 measured)
    alpha: float = 46.0 / 64.0  # handle / brake lever ratio
    half_track_m: float = 0.32  # r_b
    wheel_diameter_m: float = 0.204
    brake_torque_off_nm: float = 0.068
    brake_torque_max_nm: float = 3.95
    brake_time_constant_s: float = 0.025
    # Below this wheel speed the Coulomb brake force is scaled down linearly, which keeps
    # the integration smooth where the wheel's rolling direction changes.
    brake_regularisation_mps: float = 0.02

    @property
    def wheel_radius_m(self) -> float:
        return 0.5 * self.wheel_diameter_m


@dataclass(slots=True)
class WalkerState:
    x: float = 0.0
    y: float = 0.0
    phi: float = 0.0
    v: float = 0.0
    omega: float = 0.0

    def wheel_speeds(self, half_track: float) -> tuple[float, float]:
        """Ground speed of the left and right rear-wheel contact points."""
        return self.v - half_track * self.omega, self.v + half_track * self.omega


class Brakes:
    """Two brakes: commanded torques reached through a first-order lag, clamped to limits."""

    def __init__(self, params: WalkerParams) -> None:
        self.p = params
        self.command = [params.brake_torque_off_nm, params.brake_torque_off_nm]
        self.torque = [params.brake_torque_off_nm, params.brake_torque_off_nm]

    def set_command(self, left_nm: float, right_nm: float) -> None:
        lo, hi = self.p.brake_torque_off_nm, self.p.brake_torque_max_nm
        self.command = [min(max(left_nm, lo), hi), min(max(right_nm, lo), hi)]

    def step(self, dt: float) -> None:
        a = 1.0 - math.exp(-dt / self.p.brake_time_constant_s)
        for i in (0, 1):
            self.torque[i] += a * (self.command[i] - self.torque[i])

    def ground_forces(self, wheel_left: float, wheel_right: float) -> tuple[float, float]:
        """Magnitude-with-sign of the brake forces along the direction of motion.

        Positive force opposes forward rolling; it changes sign with the wheel's rolling
        direction and is scaled down near zero wheel speed.
        """
        eps = self.p.brake_regularisation_mps
        r = self.p.wheel_radius_m
        out = []
        for torque, speed in ((self.torque[0], wheel_left), (self.torque[1], wheel_right)):
            out.append(torque / r * max(-1.0, min(1.0, speed / eps)))
        return out[0], out[1]


def step(
    state: WalkerState,
    params: WalkerParams,
    handle_left: float,
    handle_right: float,
    brake_left: float,
    brake_right: float,
    dt: float,
) -> None:
    """Advance the state in place by dt (semi-implicit Euler; exact arc for the pose)."""
    p = params
    force = (handle_left - brake_left) + (handle_right - brake_right)
    torque = p.half_track_m * (
        (p.alpha * handle_right - brake_right) - (p.alpha * handle_left - brake_left)
    )
    # Damping terms are integrated implicitly: stable for any dt.
    state.v = (state.v + dt * force / p.mass_kg) / (1.0 + dt * p.damping / p.mass_kg)
    state.omega = (state.omega + dt * torque / p.yaw_inertia) / (
        1.0 + dt * p.yaw_damping / p.yaw_inertia
    )
    ds, dphi = state.v * dt, state.omega * dt
    half = 0.5 * dphi
    chord = ds * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
    state.x += chord * math.cos(state.phi + half)
    state.y += chord * math.sin(state.phi + half)
    state.phi = math.remainder(state.phi + dphi, 2.0 * math.pi)


def steady_state_radius(
    params: WalkerParams,
    handle_left: float,
    handle_right: float,
    brake_left: float,
    brake_right: float,
) -> float:
    """Turn radius R = v / φ̇ at steady state (eq 5.9); +inf when going straight."""
    p = params
    num = p.yaw_damping * ((handle_left - brake_left) + (handle_right - brake_right))
    den = (
        p.damping
        * p.half_track_m
        * ((p.alpha * handle_right - brake_right) - (p.alpha * handle_left - brake_left))
    )
    return math.inf if den == 0 else num / den
