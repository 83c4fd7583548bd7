"""Simulated users who push the walker with forward forces on the two handles.

`RouteFollower` models a vision-impaired user who knows the route but not where the
obstacles are: they track their position by feel (their own dead reckoning of the
walker's motion, which drifts — that drift is the impairment), steer toward the route
by pure pursuit through differential handle force, and feel the brakes only through the
walker's dynamics. A collision is felt: the user steps back briefly, re-orients (their
belief snaps back to the truth) and carries on. `ConstantPush` applies fixed handle
forces (physics tests, parameter sweeps).

`UserProfile` makes one user differ from another in a study: a seeded draw (from the
trial seed, so the same trial index is the same user under every controller) of where
they walk relative to the route, how fast and how hard they push, and how impaired their
sense of heading is. Without a profile the simulator's user is exactly `UserParams`
walking `World.route`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from hardware.geometry import to_walker_frame
from hardware.sim.dynamics import WalkerParams, WalkerState
from hardware.sim.user_vision import (
    Footprints,
    GogglesVision,
    VisionParams,
    choose_offset,
    route_coordinates,
)


@dataclass(frozen=True)
class UserParams:
    """How a simulated user pushes and how well they know where they are.

    speed_mps: preferred walking speed; lookahead_m: pure-pursuit lookahead on the route;
    speed_gain / yaw_gain: feedback from felt speed / turning [N per m/s, N·m per rad/s];
    speed_integral_gain: how fast they push harder while slower than they want [N per m];
    max_push_n: largest total forward force; max_steer_n: largest handle-force difference;
    heading_drift_rad_per_sqrt_m: random walk of the user's sense of heading per √metre
    walked (the impairment); heading_bias_rad_per_m: a constant veer of that sense;
    distance_scale_error: relative error of their sense of distance walked;
    backoff_s / backoff_speed_mps / backoff_turn_rad_s: after a collision, how long and how
    fast they pull the walker back, swinging its front away from what they touched;
    stuck_s: how long they push against something that does not give before stepping back;
    min_turn_speed_mps: they slow into a turn to no faster than they can steer it (80 % of
    the yaw rate their largest handle-force difference holds), but not below this.
    vision: what they see through the goggles (`hardware.sim.user_vision`; None: nothing,
    a blindfolded user who finds obstacles only by touch); visual_fix_s: while they see
    furniture, their sense of where they are on the route is drawn to the truth with this
    time constant (they recognise where they are by what they see); look_ahead_s: they
    walk no faster than covers the free distance they see ahead in this time;
    preview_m: they slow for a bend of the route this far before it;
    gap_margin_m: the clearance from what they see either side that they keep, beyond
    their corridor, when the way is wide enough (`user_vision.choose_offset`);
    scrape_turn_rad_s / scrape_s: a contact
    they feel but that does not stop them (a scrape) makes them steer away from it this
    fast for this long.
    sighted: they see where the walker is (e.g. a helper pushing it along tape on the
    floor for a calibration run): their sense of position is the true pose, and the
    impairment values above do not apply.
    """

    speed_mps: float = 0.75
    lookahead_m: float = 0.9
    speed_gain: float = 40.0
    speed_integral_gain: float = 15.0
    yaw_gain: float = 20.0
    max_push_n: float = 60.0
    max_steer_n: float = 45.0
    heading_drift_rad_per_sqrt_m: float = 0.06
    heading_bias_rad_per_m: float = 0.0
    distance_scale_error: float = 0.0
    finish_radius_m: float = 0.4
    backoff_s: float = 1.0
    backoff_speed_mps: float = 0.25
    backoff_turn_rad_s: float = 0.4
    stuck_s: float = 1.0
    min_turn_speed_mps: float = 0.2
    vision: VisionParams | None = field(default_factory=VisionParams)
    visual_fix_s: float = 3.0
    look_ahead_s: float = 2.0
    preview_m: float = 1.0
    gap_margin_m: float = 0.3
    scrape_turn_rad_s: float = 0.3
    scrape_s: float = 0.5
    sighted: bool = False


@dataclass(frozen=True)
class UserProfile:
    """How one simulated user of a study differs from the nominal user and route.

    Route (what they actually try to walk): route_offset_m, a constant sideways offset
    from the course route (+ = to the left of the direction of travel: some users keep
    to one side); route_wander_m, the amplitude of a smooth sideways wander around that,
    a sum of three sinusoids with wavelengths route_wander_wavelength_m × (1, 0.53, 0.29)
    and random phases drawn from wander_seed. Offset and wander fade in over the first
    and out over the last ROUTE_TAPER_M of the route, so the user starts at the start pose
    and ends where the course ends.
    Push: speed_scale multiplies the preferred speed; push_scale the largest push and
    steering forces (how hard they are able / willing to push).
    Impairment: heading_drift_scale multiplies the random walk of their sense of heading;
    heading_bias_rad_per_m and distance_scale_error are added to the base values.

    `sample(seed)` draws a profile (distributions in its docstring); `apply(params)` and
    `walk_route(route)` give the user's parameters and route. The identity profile
    (`UserProfile()`) leaves the parameters unchanged; its route is the course route
    resampled every 0.1 m.
    """

    route_offset_m: float = 0.0
    route_wander_m: float = 0.0
    route_wander_wavelength_m: float = 4.0
    wander_seed: int = 0
    speed_scale: float = 1.0
    push_scale: float = 1.0
    heading_drift_scale: float = 1.0
    heading_bias_rad_per_m: float = 0.0
    distance_scale_error: float = 0.0

    @classmethod
    def sample(cls, seed: int) -> UserProfile:
        """A user drawn from `seed` (deterministic): offset N(0, 0.05 m) clipped to
        ±0.1 m; wander amplitude U(0, 0.08) m with wavelength U(2.5, 6) m; speed scale
        U(0.85, 1.15) (0.64–0.86 m/s with the default 0.75); push scale U(0.8, 1.25);
        heading-drift scale U(0.5, 1.5); heading bias N(0, 0.005) rad/m; distance error
        N(0, 0.03)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), PROFILE_STREAM]))
        return cls(
            route_offset_m=round(float(np.clip(rng.normal(0.0, 0.05), -0.1, 0.1)), 4),
            route_wander_m=round(float(rng.uniform(0.0, 0.08)), 4),
            route_wander_wavelength_m=round(float(rng.uniform(2.5, 6.0)), 3),
            wander_seed=int(rng.integers(0, 2**31 - 1)),
            speed_scale=round(float(rng.uniform(0.85, 1.15)), 4),
            push_scale=round(float(rng.uniform(0.8, 1.25)), 4),
            heading_drift_scale=round(float(rng.uniform(0.5, 1.5)), 4),
            heading_bias_rad_per_m=round(float(rng.normal(0.0, 0.005)), 5),
            distance_scale_error=round(float(rng.normal(0.0, 0.03)), 4),
        )

    def apply(self, params: UserParams) -> UserParams:
        """`params` as this user has them."""
        return replace(
            params,
            speed_mps=params.speed_mps * self.speed_scale,
            max_push_n=params.max_push_n * self.push_scale,
            max_steer_n=params.max_steer_n * self.push_scale,
            heading_drift_rad_per_sqrt_m=params.heading_drift_rad_per_sqrt_m
            * self.heading_drift_scale,
            heading_bias_rad_per_m=params.heading_bias_rad_per_m + self.heading_bias_rad_per_m,
            distance_scale_error=params.distance_scale_error + self.distance_scale_error,
        )

    def walk_route(self, route: np.ndarray) -> np.ndarray:
        """The route this user tries to walk: `route` resampled every 0.1 m and shifted
        sideways by the offset plus the wander (tapered at both ends)."""
        route = np.asarray(route, dtype=float)
        seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
        arclen = np.concatenate([[0.0], np.cumsum(seg)])
        n = max(math.ceil(arclen[-1] / 0.1), 1) + 1
        s = np.linspace(0.0, arclen[-1], n)
        pts = np.column_stack(
            [np.interp(s, arclen, route[:, 0]), np.interp(s, arclen, route[:, 1])]
        )
        tangent = np.gradient(pts, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
        phases = np.random.default_rng(self.wander_seed).uniform(0.0, 2.0 * math.pi, 3)
        wavelengths = self.route_wander_wavelength_m * np.array(WANDER_HARMONICS)
        wander = math.sqrt(2.0 / 3.0) * np.sum(
            np.sin(2.0 * math.pi * s[:, None] / wavelengths + phases), axis=1
        )
        taper = np.clip(np.minimum(s, arclen[-1] - s) / ROUTE_TAPER_M, 0.0, 1.0)
        lateral = taper * (self.route_offset_m + self.route_wander_m * wander)
        return pts + lateral[:, None] * normal


# Seed-sequence stream of the profile draw, apart from the simulator's own streams.
PROFILE_STREAM = 0x05E4
# Wavelengths of the wander's sinusoids, relative to route_wander_wavelength_m (the three
# have unit total variance: each sin has variance 1/2, scaled by √(2/3)).
WANDER_HARMONICS = (1.0, 0.53, 0.29)
ROUTE_TAPER_M = 1.0

ROUTE_STEP_M = 0.02
# Spacing of the route ahead against which the user judges what they see.
ROUTE_PLAN_SPACING_M = 0.1
SEARCH_BEHIND = round(0.5 / ROUTE_STEP_M)
SEARCH_AHEAD = round(2.0 / ROUTE_STEP_M)


class ConstantPush:
    """Fixed forward forces on the left and right handles."""

    def __init__(self, left_n: float, right_n: float) -> None:
        self.left_n, self.right_n = left_n, right_n
        self.finished = False

    def forces(self, state: WalkerState, dt: float) -> tuple[float, float]:
        return self.left_n, self.right_n

    def on_collision(self, state: WalkerState, point: np.ndarray) -> None:
        pass

    def on_scrape(self, state: WalkerState, point: np.ndarray) -> None:
        pass

    def touching(self, state: WalkerState, point: np.ndarray | None, dt: float) -> None:
        pass


class RouteFollower:
    """A user who walks a route they know, on their own sense of where they are, looking
    through vision-impairment goggles (see the module docstring). sight: what they can
    see (`user_vision.GogglesVision`; None, or params.vision None: nothing);
    course_route: the route whose bends they slow for (default `route`)."""

    def __init__(
        self,
        route: np.ndarray,
        start: WalkerState,
        walker: WalkerParams,
        params: UserParams,
        rng: np.random.Generator,
        sight: Footprints | None = None,
        vision_rng: np.random.Generator | None = None,
        course_route: np.ndarray | None = None,
    ) -> None:
        route = np.asarray(route, dtype=float)
        if route.ndim != 2 or route.shape[1] != 2 or len(route) < 2:
            raise ValueError(f"route must be an (N>=2, 2) array of waypoints, got {route.shape}")
        self.route = route
        seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
        arclen = np.concatenate([[0.0], np.cumsum(seg)])
        self.length_m = float(arclen[-1])
        # The route resampled every ROUTE_STEP_M, so progress is an index into it.
        self._dense = _resample(route)
        # The bends they slow for are the course's (a user's own sideways wander around
        # it is no corner), at the same share of the way.
        bends = _resample(np.asarray(course_route, float)) if course_route is not None else None
        self._curvature = (
            _route_curvature(self._dense)
            if bends is None
            else np.interp(
                np.linspace(0.0, 1.0, len(self._dense)),
                np.linspace(0.0, 1.0, len(bends)),
                _route_curvature(bends),
            )
        )
        self._curvature_at = (-1, 0.0)  # (progress, the bend ahead of it)
        self.walker = walker
        self.p = params
        self.rng = rng
        self.belief = np.array([start.x, start.y, start.phi])
        self._progress = 0  # index into the dense route
        self.finished = False
        self._backoff_left_s = 0.0
        self._backoff_turn = 0.0
        self._scrape_left_s = 0.0
        self._scrape_turn = 0.0
        self._speed_error_integral = 0.0
        self._touching_s = 0.0
        self._t = 0.0
        self._offset = 0.0  # the offset across the route they walk at (+ = left)
        self._free = math.inf  # free distance ahead of the frame, as they see it
        self.vision = (
            GogglesVision(sight, params.vision, vision_rng or np.random.default_rng(0))
            if sight is not None and params.vision is not None
            else None
        )

    @property
    def progress_m(self) -> float:
        return self._progress * ROUTE_STEP_M

    def _curvature_ahead(self) -> float:
        """The sharpest bend of the route within preview_m ahead: they know the route and
        slow before its corners, not in them."""
        k = self._progress
        if self._curvature_at[0] != k:  # (the progress moves every few physics steps)
            n = round(self.p.preview_m / ROUTE_STEP_M)
            self._curvature_at = (k, float(self._curvature[k : k + n + 1].max()))
        return self._curvature_at[1]

    # -- belief -----------------------------------------------------------------------
    def _feel_motion(self, state: WalkerState, dt: float) -> None:
        if self.p.sighted:
            self.belief[:] = (state.x, state.y, state.phi)
            return
        ds = state.v * dt * (1.0 + self.p.distance_scale_error)
        walked = abs(state.v * dt)
        dphi = state.omega * dt + self.p.heading_bias_rad_per_m * walked
        if walked > 0:
            dphi += (
                self.p.heading_drift_rad_per_sqrt_m * math.sqrt(walked) * self.rng.standard_normal()
            )
        b = self.belief
        th = b[2] + 0.5 * dphi
        b[0] += ds * math.cos(th)
        b[1] += ds * math.sin(th)
        b[2] += dphi

    def _look(self, state: WalkerState, dt: float) -> None:
        """Carry what was seen along with the walker's motion, glimpse when due, and
        while furniture is in view draw the sense of position toward the truth."""
        if self.vision is None:
            return
        self.vision.carry(state.v * dt, state.omega * dt)
        if self.vision.step(self._t, (state.x, state.y, state.phi)):
            self._plan()
        if self.vision.sees_something():
            gain = min(dt / self.p.visual_fix_s, 1.0)
            b = self.belief  # (per physics step: scalars, not small arrays)
            bx, by, bphi = b.tolist()
            b[0] = bx + gain * (state.x - bx)
            b[1] = by + gain * (state.y - by)
            b[2] = bphi + gain * math.remainder(state.phi - bphi, 2.0 * math.pi)

    def on_collision(self, state: WalkerState, point: np.ndarray) -> None:
        """Felt a collision at `point` (world): step back, swinging the front away from it."""
        self.belief[:] = (state.x, state.y, state.phi)
        self._backoff_left_s = self.p.backoff_s
        self._backoff_turn = -math.copysign(self.p.backoff_turn_rad_s, _lateral(state, point))
        self._touching_s = 0.0

    def on_scrape(self, state: WalkerState, point: np.ndarray) -> None:
        """Felt a contact that does not stop them at `point`: steer away from it a while."""
        self._scrape_left_s = self.p.scrape_s
        self._scrape_turn = -math.copysign(self.p.scrape_turn_rad_s, _lateral(state, point))

    def touching(self, state: WalkerState, point: np.ndarray | None, dt: float) -> None:
        """Contact at `point` this step (None: no contact). Pushing against something that
        does not give for `stuck_s` makes the user step back again, as a collision does."""
        if point is None or self._backoff_left_s > 0.0:
            self._touching_s = 0.0
            return
        self._touching_s += dt
        if self._touching_s >= self.p.stuck_s:
            self.on_collision(state, point)

    # -- route ------------------------------------------------------------------------
    def _update_progress(self) -> None:
        # Closest route point to the belief, searched only a little behind and ahead so
        # the user never skips a loop of a route that passes near itself.
        lo = max(self._progress - SEARCH_BEHIND, 0)
        bx, by = self.belief[0], self.belief[1]
        nearest = _nearest(self._dense, lo, self._progress + SEARCH_AHEAD, bx, by)
        self._progress = max(self._progress, nearest)

    def _route_aim(self) -> tuple[np.ndarray, float]:
        """The pursuit point (the route point lookahead_m on, moved across the route by
        the chosen offset) in the walker frame as the user believes it, and the route
        length left."""
        remaining = self.length_m - self.progress_m
        end = self.route[-1]
        if (
            remaining < self.p.finish_radius_m
            and math.dist(self.belief[:2], end) < self.p.finish_radius_m
        ):
            self.finished = True
        dense = self._dense
        i = min(self._progress + round(self.p.lookahead_m / ROUTE_STEP_M), len(dense) - 1)
        px, py = dense[i].tolist()
        if self._offset:
            j = min(i + 1, len(dense) - 1)
            (x1, y1), (x0, y0) = dense[j].tolist(), dense[max(j - 1, 0)].tolist()
            tx, ty = x1 - x0, y1 - y0
            norm = max(float(np.hypot(tx, ty)), 1e-12)
            tx, ty = tx / norm, ty / norm
            px, py = px + self._offset * -ty, py + self._offset * tx
        return self._point_to_walker(px, py), remaining

    def _point_to_walker(self, x: float, y: float) -> tuple[float, float]:
        """One world point in the walker frame as the user believes it (as
        hardware.geometry.to_walker_frame at the belief, the same arithmetic, without the
        arrays: it runs every physics step)."""
        bx, by, bphi = self.belief.tolist()
        c, s = math.cos(bphi), math.sin(bphi)
        rx, ry = x - bx, y - by
        return (c * rx + s * ry, -s * rx + c * ry)

    def _plan(self) -> None:
        """After a glimpse: the offset across the route to walk at and the free distance
        ahead (`user_vision.choose_offset` on what they see ahead of the frame's middle,
        against the route of the next nose + plan metres as they believe it)."""
        vp = self.p.vision
        assert vp is not None and self.vision is not None
        pts = self.vision.points
        pts = pts[pts[:, 0] > 0.5 * vp.nose_m]
        step = round(ROUTE_PLAN_SPACING_M / ROUTE_STEP_M)
        n = round((vp.nose_m + vp.plan_m) / ROUTE_STEP_M)
        ahead = self._dense[self._progress : self._progress + n + 1 : step]
        if len(pts) == 0 or len(ahead) < 2:
            self._offset, self._free = 0.0, math.inf
            return
        ahead = to_walker_frame(ahead, self.belief)
        along, across = route_coordinates(pts, ahead, ROUTE_PLAN_SPACING_M)
        chosen, first = choose_offset(along, across, vp.corridor_half_width_m, self.p.gap_margin_m)
        self._offset = chosen
        self._free = max(first - vp.nose_m, 0.0)

    # -- forces -----------------------------------------------------------------------
    def forces(self, state: WalkerState, dt: float) -> tuple[float, float]:
        self._t += dt
        self._feel_motion(state, dt)
        self._look(state, dt)
        self._update_progress()
        target, remaining = self._route_aim()
        err = math.atan2(target[1], target[0])
        v_des, omega_des = self._desired(state, err, remaining, self._free, dt)
        return self._handle_forces(state, v_des, omega_des, dt)

    def _desired(
        self, state: WalkerState, err: float, remaining: float, free: float, dt: float
    ) -> tuple[float, float]:
        """Desired forward speed and yaw rate toward the chosen direction `err`."""
        v_des = self.p.speed_mps * max(0.3, math.cos(err)) * min(1.0, remaining / 0.8 + 0.2)
        # Slow into a turn: no faster than the turn they can steer (pure pursuit needs
        # ω = 2 v sin(err) / lookahead, the route's bends ahead ω = v κ; their largest
        # handle-force difference holds ω_max against the walker's rotational damping).
        w = self.walker
        omega_max = self.p.max_steer_n * w.alpha * w.half_track_m / w.yaw_damping
        turn = max(2.0 * abs(math.sin(err)) / self.p.lookahead_m, self._curvature_ahead())
        if turn > 0.0:
            v_des = min(v_des, max(0.8 * omega_max / turn, self.p.min_turn_speed_mps))
        # No faster than covers the free distance they see in look_ahead_s.
        v_des = min(v_des, max(free / self.p.look_ahead_s, self.p.min_turn_speed_mps))
        v_ref = max(abs(state.v), 0.3)
        omega_des = 2.0 * v_ref * math.sin(err) / self.p.lookahead_m
        if self._scrape_left_s > 0.0:
            self._scrape_left_s -= dt
            omega_des += self._scrape_turn
        if self.finished:
            v_des = 0.0
        elif self._backoff_left_s > 0.0:
            self._backoff_left_s -= dt
            v_des, omega_des = -self.p.backoff_speed_mps, self._backoff_turn
        return v_des, omega_des

    def _handle_forces(
        self, state: WalkerState, v_des: float, omega_des: float, dt: float
    ) -> tuple[float, float]:
        """Handle forces that push toward (v_des, ω_des): a PI speed loop, a P yaw loop."""
        w = self.walker
        if self.finished or self._backoff_left_s > 0.0:
            self._speed_error_integral = 0.0
        else:
            # Anti-windup: the integral alone never asks for more than the largest push.
            limit = self.p.max_push_n / max(self.p.speed_integral_gain, 1e-9)
            self._speed_error_integral = min(
                max(self._speed_error_integral + (v_des - state.v) * dt, 0.0), limit
            )
        total = (
            w.damping * v_des
            + self.p.speed_gain * (v_des - state.v)
            + self.p.speed_integral_gain * self._speed_error_integral
        )
        total = min(max(total, -0.5 * self.p.max_push_n), self.p.max_push_n)
        yaw_torque = w.yaw_damping * omega_des + self.p.yaw_gain * (omega_des - state.omega)
        diff = yaw_torque / (w.alpha * w.half_track_m)
        diff = min(max(diff, -self.p.max_steer_n), self.p.max_steer_n)
        return 0.5 * (total - diff), 0.5 * (total + diff)


@njit(cache=True, nogil=True)
def _nearest(points: np.ndarray, lo: int, hi: int, x: float, y: float) -> int:
    """The index in [lo, hi) of the point (N, 2) nearest to (x, y); the first of equals."""
    best, at = np.inf, lo
    for i in range(lo, min(hi, points.shape[0])):
        d2 = (points[i, 0] - x) ** 2 + (points[i, 1] - y) ** 2
        if d2 < best:
            best, at = d2, i
    return at


def _resample(route: np.ndarray) -> np.ndarray:
    """`route` resampled every ROUTE_STEP_M along its length."""
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    arclen = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, arclen[-1] + ROUTE_STEP_M, ROUTE_STEP_M)
    return np.column_stack([np.interp(s, arclen, route[:, 0]), np.interp(s, arclen, route[:, 1])])


def _route_curvature(dense: np.ndarray, span_m: float = 0.1) -> np.ndarray:
    """Unsigned curvature [1/m] of a densely resampled route at each point: the turn of
    its direction across ±span_m over the arc length between."""
    k = max(round(span_m / ROUTE_STEP_M), 1)
    heading = np.unwrap(np.arctan2(*np.diff(dense, axis=0).T[::-1]))
    heading = np.concatenate([heading, heading[-1:]])
    ahead = np.concatenate([heading[k:], np.repeat(heading[-1:], k)])
    behind = np.concatenate([np.repeat(heading[:1], k), heading[:-k]])
    return np.abs(ahead - behind) / (2 * k * ROUTE_STEP_M)


def _lateral(state: WalkerState, point: np.ndarray) -> float:
    """Sideways offset of `point` (world) from the walker's centre line, + to the left."""
    return -math.sin(state.phi) * (point[0] - state.x) + math.cos(state.phi) * (point[1] - state.y)
