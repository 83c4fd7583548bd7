"""Differential-drive kinematics: exact arc integration of wheel or velocity increments."""

from __future__ import annotations

import math


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


def wheel_increment_jacobian(
    theta: float, ds: float, dtheta: float, track: float
) -> tuple[tuple[float, float], ...]:
    """∂(dx, dy, dθ)/∂(ds_left, ds_right) of the midpoint form of the arc (3 rows of 2),
    for noise propagation."""
    h = theta + 0.5 * dtheta
    c, s = math.cos(h), math.sin(h)
    # ds = (L + R)/2, dθ = (R − L)/B, dx = ds cos(h), dy = ds sin(h), h = θ + dθ/2
    k = 0.5 * ds / track
    return (
        (0.5 * c + k * s, 0.5 * c - k * s),
        (0.5 * s - k * c, 0.5 * s + k * c),
        (-1.0 / track, 1.0 / track),
    )
