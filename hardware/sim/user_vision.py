"""What a simulated walker user sees through vision-impairment goggles, and where they can go.

The thesis's users (§6.4) were sighted people wearing safety goggles "altered with opaque
tape, to restrict visual range and depth perception, and layers of clear tape, to blur
the non-opaque areas" (Fig 6.9): they were not blind. They saw the furniture of the room
as blurred shapes through a window in the tape, misjudged distances, and saw nothing
beside or below the walker. `GogglesVision` models that, and `free_distance` is how such
a user judges which way is passable. Every number is a modelling assumption, stated here
and in `VisionParams`:

- **What is seen.** The footprints of the obstacles' parts that reach above
  `min_height_m` (walls, table and desk tops, chair seats and backs:
  `World.footprint_polygons`) — not what lies lower, such as an office chair's star base:
  with blur, low-contrast things near the floor are the ones missed (walkers with
  simulated contrast loss paid little attention to low objects on their route:
  Vivekananda-Schmidt et al. 2004, Optom Vis Sci 81:850–859) —, by rays from the user's eyes, which
  are `eye_offset_m` behind the rear axle (the user stands behind the handles, which sit
  above the rear wheels), within a window of ±`half_field_deg` about the walker's heading
  (the tape's window; people look where they push) and out to `range_m` (beyond it the
  blurred furniture does not stand out from the room). Nearer things hide farther ones.
- **How well.** Each obstacle's distance is misjudged by a factor exp(N(0, range_sigma))
  (depth perception impaired: judged distance errors grow with distance) and its
  direction by N(0, bearing_sigma_deg) (blur), drawn once per obstacle and trial: a user
  who misjudges a table misjudges it the same way each time they look (independent
  errors per glance would average out over glances; outliers among them would close
  every gap). A glimpse happens every `period_s`; what
  was seen is remembered for `memory_s`, carried along by the user's sense of their own
  motion (so obstacles that have left the window beside the walker fade from memory
  rather than vanish at once). Walking people keep obstacles they no longer see in
  memory for a step or two (assumption: two seconds).
- **What is passable.** A direction is free for as far as a corridor of the width the
  user feels the walker to be plus a margin stays clear of everything seen (see
  `free_distance`). The walker the user feels is what they hold and see ahead of them:
  the handles (0.48 m apart) and the front of the frame (0.50 m across the castors,
  thesis Table 3.1). The frame widens to 0.56 m at the rear struts and the rear wheels
  stick out 6.5 cm beyond that (0.69 m), below and behind the user's hands, where they
  cannot see them: that is not part of the width they steer by (novice users of a wheeled
  device under-estimate the room it needs: Higuchi et al. 2004, J Exp Psychol Appl
  10:55–66). The margin is what people keep
  when passing through apertures: they turn their shoulders below 1.3 × their width
  (Warren & Whang 1987, J Exp Psychol Hum Percept Perform 13:371–383), i.e. 15 % of
  the width each side.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class VisionParams:
    """How the goggles let a user see (module docstring).

    half_field_deg: half the horizontal window; range_m: farthest obstacle seen;
    min_height_m: what lies entirely below this height is not seen;
    ray_step_deg: angular resolution of the glimpse (coarser than a Snellen limit: blur);
    eye_offset_m: eyes ahead (+) of the rear axle; range_sigma: log-normal σ of judged
    distance; bearing_sigma_deg: σ of the direction error; period_s: time between glimpses;
    memory_s: how long a glimpse is remembered; perceived_half_width_m: half the width
    the user feels the walker to be (its handles and front, 0.50 m); margin_frac:
    clearance kept each side as a share of the perceived width; plan_m: how far ahead of
    the frame's front they judge their way; nose_m: the frame's front ahead of the rear
    axle.
    """

    half_field_deg: float = 30.0
    min_height_m: float = 0.2
    range_m: float = 3.0
    ray_step_deg: float = 1.5
    eye_offset_m: float = -0.3
    range_sigma: float = 0.1
    bearing_sigma_deg: float = 1.5
    period_s: float = 0.2
    memory_s: float = 2.0
    perceived_half_width_m: float = 0.25
    margin_frac: float = 0.15
    plan_m: float = 1.5
    nose_m: float = 0.64

    def __post_init__(self) -> None:
        for name in ("half_field_deg", "range_m", "ray_step_deg", "period_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"vision {name} must be > 0, got {getattr(self, name)}")
        for name in ("range_sigma", "bearing_sigma_deg", "memory_s", "margin_frac"):
            if getattr(self, name) < 0:
                raise ValueError(f"vision {name} must be >= 0, got {getattr(self, name)}")

    @property
    def corridor_half_width_m(self) -> float:
        return self.perceived_half_width_m * (1.0 + 2.0 * self.margin_frac)


Footprints = Sequence[tuple[str, np.ndarray]]  # (obstacle name, 4×2 corners) per box


def _edges(footprints: Footprints) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Start points, direction vectors and owning obstacle (an index per distinct name)
    of every footprint edge, and the number of obstacles."""
    if not footprints:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=int), 0
    index = {n: i for i, n in enumerate(dict.fromkeys(n for n, _ in footprints))}
    polys = np.array([p for _, p in footprints], dtype=float)
    owner = np.repeat([index[n] for n, _ in footprints], 4)
    a = polys.reshape(-1, 2)
    b = np.roll(polys, -1, axis=1).reshape(-1, 2)
    return a, b - a, owner, len(index)


def cast_rays(
    origin: np.ndarray, angles: np.ndarray, starts: np.ndarray, dirs: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray (world angles) from `origin` to the first edge it meets
    (inf where none within max_range), and that edge's index (-1 where none)."""
    ray = np.column_stack([np.cos(angles), np.sin(angles)])  # (R, 2)
    w = starts - origin  # (E, 2)
    # origin + t·ray = start + u·dir  →  t·ray − u·dir = w
    denom = ray[:, None, 0] * (-dirs[None, :, 1]) - ray[:, None, 1] * (-dirs[None, :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 0] * (-dirs[None, :, 1]) - w[None, :, 1] * (-dirs[None, :, 0])) / denom
        u = (ray[:, None, 0] * w[None, :, 1] - ray[:, None, 1] * w[None, :, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 0.0) & (u >= 0.0) & (u <= 1.0) & (t <= max_range)
    if not t.shape[1]:
        return np.full(len(angles), np.inf), np.full(len(angles), -1)
    t = np.where(hit, t, np.inf)
    first = np.argmin(t, axis=1)
    dist = t[np.arange(len(angles)), first]
    return dist, np.where(np.isfinite(dist), first, -1)


@njit(cache=True, nogil=True)
def _carry(p: np.ndarray, ds: float, c: float, s: float) -> None:
    """Move the points p (N, 2) in place by ds forward and a turn whose cosine and sine
    are c, s (per physics step: one compiled loop, not six small numpy calls)."""
    for i in range(p.shape[0]):
        x, y = p[i, 0] - ds, p[i, 1]
        p[i, 0] = c * x + s * y
        p[i, 1] = -s * x + c * y


class GogglesVision:
    """Glimpses of the world through the goggles, remembered in the walker's frame.

    footprints: what can be seen, (obstacle name, 4×2 corners) of every box reaching
    above params.min_height_m into the walker's height (`World.footprint_polygons`)."""

    def __init__(
        self, footprints: Footprints, params: VisionParams, rng: np.random.Generator
    ) -> None:
        self.p = params
        self.rng = rng
        self._starts, self._dirs, self._owner, n_obstacles = _edges(footprints)
        # How this user misjudges each obstacle, for the whole trial: a factor on its
        # distance and an offset of its direction (module docstring).
        self._range_factor = np.exp(params.range_sigma * rng.standard_normal(n_obstacles))
        self._bearing_offset = np.radians(params.bearing_sigma_deg) * rng.standard_normal(
            n_obstacles
        )
        half = math.radians(params.half_field_deg)
        n = max(round(2 * half / math.radians(params.ray_step_deg)), 1) + 1
        self._offsets = np.linspace(-half, half, n)
        # Remembered points in the walker frame (x forward, y left; rear-axle origin) and
        # the time each was seen.
        self._points = np.zeros((0, 2))
        self._seen_t = np.zeros(0)
        self._t = 0.0
        self._next_glimpse = 0.0

    @property
    def points(self) -> np.ndarray:
        """What the user remembers seeing, in the walker frame (moved in place by
        `carry`: copy it to keep a snapshot)."""
        return self._points

    def carry(self, ds: float, dphi: float) -> None:
        """Move the remembered points by the user's felt motion (ds forward, turned dphi)."""
        if len(self._points) == 0:
            return
        _carry(self._points, ds, math.cos(dphi), math.sin(dphi))

    def step(self, t: float, pose: tuple[float, float, float]) -> bool:
        """Take a glimpse from the true pose when one is due; forget what is too old.
        Returns whether a glimpse was taken."""
        self._t = t
        # seen in time order: only when the oldest is too old is there anything to forget
        if len(self._seen_t) and self._seen_t[0] < t - self.p.memory_s:
            keep = self._seen_t >= t - self.p.memory_s
            self._points, self._seen_t = self._points[keep], self._seen_t[keep]
        if t + 1e-9 < self._next_glimpse:
            return False
        self._next_glimpse = t + self.p.period_s
        x, y, phi = pose
        eye = np.array(
            [x + self.p.eye_offset_m * math.cos(phi), y + self.p.eye_offset_m * math.sin(phi)]
        )
        dist, edge = cast_rays(eye, phi + self._offsets, self._starts, self._dirs, self.p.range_m)
        seen = edge >= 0
        if not seen.any():
            return True
        n = int(seen.sum())
        owner = self._owner[edge[seen]]
        judged = dist[seen] * self._range_factor[owner]
        bearing = self._offsets[seen] + self._bearing_offset[owner]
        pts = np.column_stack(
            [self.p.eye_offset_m + judged * np.cos(bearing), judged * np.sin(bearing)]
        )
        self._points = np.vstack([self._points, pts])
        self._seen_t = np.concatenate([self._seen_t, np.full(n, t)])
        return True

    def sees_something(self) -> bool:
        """Whether anything was seen in the last glimpse period (for the user's sense of
        where they are on the route)."""
        # (seen in time order: the last is the latest)
        return bool(len(self._seen_t)) and float(self._seen_t[-1]) >= self._t - self.p.period_s


def route_coordinates(
    points: np.ndarray, route: np.ndarray, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(distance along, signed distance across) of each point from a route polyline
    sampled every `spacing_m` (K×2, K >= 2, the same frame as the points; + across = to
    the left of the direction of travel), measured at the nearest sample. Points beyond the route's
    ends (farther along or behind than half a sample) get NaN."""
    tangent = np.gradient(route, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    d = points[:, None, :] - route[None, :, :]
    k = np.argmin(np.einsum("nkj,nkj->nk", d, d), axis=1)
    rel = points - route[k]
    along = np.einsum("nj,nj->n", rel, tangent[k])
    # The distance to the route, on the side the point is: a point off the outside of a
    # bend lies beyond every segment's end, and its offset from the nearest segment's
    # line alone would put it on the route.
    side = np.where(np.einsum("nj,nj->n", rel, normal[k]) >= 0.0, 1.0, -1.0)
    across = side * np.hypot(rel[:, 0], rel[:, 1])
    outside = ((k == 0) & (along < -0.5 * spacing_m)) | (
        (k == len(route) - 1) & (along > 0.5 * spacing_m)
    )
    s = k * spacing_m + along
    return np.where(outside, np.nan, s), np.where(outside, np.nan, across)


def choose_offset(
    along: np.ndarray, across: np.ndarray, half_width_m: float, margin_m: float
) -> tuple[float, float]:
    """The offset across the route (+ = left) a user walks at to pass what they see, and
    how far ahead along the route that way is free (inf: all the way they look).

    Obstacles are solid: what they see left of the route is a wall on their left, and
    what they see right of it one on their right. They walk between the two, their
    corridor (`half_width_m` each side) clear of both: on the route when it is, nearest
    the route otherwise, keeping `margin_m` more from the sides where the way is wide
    enough (people keep to their way in the open and pass through the middle of a tight
    gap). When the gap they see is narrower than their corridor, they aim at its middle
    and the way is free only up to the first point in their corridor."""
    ok = np.isfinite(along)
    along, across = along[ok], across[ok]
    left, right = across >= 0.0, across < 0.0
    hi = float(across[left].min()) - half_width_m if left.any() else math.inf
    lo = float(across[right].max()) + half_width_m if right.any() else -math.inf
    if lo <= hi:
        mid = 0.5 * (lo + hi)
        return float(min(max(0.0, min(lo + margin_m, mid)), max(hi - margin_m, mid))), math.inf
    offset = 0.5 * (lo + hi)
    inside = np.abs(across - offset) < half_width_m
    return offset, float(along[inside].min())
