"""Simulated worlds: rooms of vertical boxes (walls and furniture), AprilTags and a route.

A `World` is what the simulator's sensors see and what the walker collides with: every
obstacle is a set of oriented vertical boxes, every tag a square on a vertical face, and
the route is the polyline a simulated user tries to follow. Built-in courses live in
`hardware/sim/courses/*.json` (`available_courses()`, `load_world(name)`).

Coordinates: world frame z up, metres, angles in radians counter-clockwise from +x
(any angle key may instead be given in degrees with the suffix `_deg`, e.g. `yaw_deg`).

Course JSON format (one object)::

    {
      "name": "thesis-course",
      "bounds": [xmin, xmax, ymin, ymax],          # area of interest (map extent)
      "start_pose": [x, y, theta],                 # or {"x": .., "y": .., "theta_deg": ..}
      "route": [[x, y], ...],                      # used as is, or
      "route": {"points": [[x, y], [x, y, r], ...],  # corner points; r = fillet radius
                "corner_radius": 0.5,              # default fillet radius at corners
                "spacing": 0.5},                   # longest segment after resampling
      "obstacles": [ ... ],
      "tags": [ ... ],
      "user": {"sighted": true, "lookahead_m": 0.5}  # optional: how the route is walked
    }

`user` (optional) sets fields of the simulated user's `UserParams`
(`hardware/sim/user.py`) for this course, e.g. a sighted helper following tape on the
floor for a calibration run (`umbmark`); without it the user is the simulation's.

`World.to_dict` adds "format": "walker-slam-world" and "version": 1, and writes the
route as a plain list, obstacles as explicit boxes and tags as explicit poses. Unknown
keys anywhere are an error (a typo would otherwise be silently ignored).

Route corners are rounded with circular fillets (clipped so that neighbouring fillets do
not overlap), arcs are sampled every <= 10°, and segments longer than `spacing` are
split evenly. A plain list is only split (so a saved route loads back unchanged).

Obstacles (`name` must be unique; it defaults to "<kind>-<index>"). Furniture has a local
frame at its centre whose +x axis points along `yaw` (the way a person sitting at a desk
or on a chair faces); `depth` is the extent along local x, `width` along local y:

- {"kind": "wall", "from": [x, y], "to": [x, y], "thickness": 0.1, "height": 2.4}
  one box centred on the segment from→to (it does not extend past its end points).
  Its local frame has its origin at `from` and +x towards `to`.
- {"kind": "table", "x", "y", "yaw", "width", "depth", "height": 0.75}
  a 3 cm top and four 5 cm square legs inset 3 cm from the edges.
- {"kind": "desk", "x", "y", "yaw", "width", "depth", "height": 0.75, "modesty": true}
  a 3 cm top, two 2.5 cm side panels at the ±y ends (floor to top) and, if `modesty`,
  a 2 cm modesty panel flush with the front (+x) edge from 0.10 m up to the top.
- {"kind": "chair", "x", "y", "yaw", "width": 0.45, "depth": 0.45, "seat_height": 0.45,
  "back_height": 0.85} a 5 cm seat, four 3 cm legs and a 4 cm back rest on the −x edge.
- {"kind": "office-chair", "x", "y", "yaw", "width": 0.46, "depth": 0.46,
  "seat_height": 0.47, "back_height": 0.95, "base_radius": 0.33} a 6 cm seat on a
  central column, a 4 cm back rest on the −x edge, and a five-star base on the floor:
  five 5 cm spokes, 10 cm high, reaching base_radius from the centre (the first along
  +x), wider than the seat — the office chairs of the thesis's obstacle course (§6.4).
- {"kind": "box", "x", "y", "yaw", "sx", "sy", "height", "z0": 0.0} one box from z0 up
  to `height` (sx along local x, sy along local y).
- any kind: {"kind": .., "name": .., "boxes": [{"cx", "cy", "yaw", "sx", "sy", "z0",
  "z1"}, ...]} gives the boxes explicitly (this is what `World.to_dict` writes).

Tags (tag36h11 ids; the tag size is the camera calibration's):

- {"id": 3, "x", "y", "z", "yaw"}: centre and the heading of the outward normal.
- {"id": 3, "on": "desk-2", "face": "front", "at": 0.2, "z": 0.35}: on a face of an
  obstacle given in compact form; face is front/back/left/right (local +x/−x/+y/−y of the
  obstacle's outline), `at` is the position along the face in the obstacle's local frame
  (local y on front/back faces, local x on left/right faces: for a wall, the distance
  from `from`). The loader checks that a box face is really there (not, say, the gap
  between table legs).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hardware.errors import ConfigError, UnknownNameError
from hardware.frames import make_transform
from hardware.sim.collision import Contact, PolygonSet, rectangle
from hardware.sim.user import UserParams

OBSTACLE_KINDS = ("wall", "table", "desk", "chair", "office-chair", "box")
COLLISION_BAND_M = (0.0, 0.95)  # the walker frame stands up to ~0.95 m
TAG_SURFACE_TOLERANCE_M = 0.02
_FORMAT_VERSION = 1


@dataclass(frozen=True, slots=True)
class Box:
    """An upright box: centre (cx, cy) in the plane, heading yaw, full sides sx (along
    yaw) and sy, vertical extent z0..z1."""

    cx: float
    cy: float
    yaw: float
    sx: float
    sy: float
    z0: float
    z1: float

    def __post_init__(self) -> None:
        vals = (self.cx, self.cy, self.yaw, self.sx, self.sy, self.z0, self.z1)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"box values must be finite, got {vals}")
        if self.sx <= 0 or self.sy <= 0 or self.z1 <= self.z0:
            raise ValueError(
                f"box needs sx > 0, sy > 0 and z1 > z0, got sx={self.sx} sy={self.sy} "
                f"z0={self.z0} z1={self.z1}"
            )

    def corners(self) -> np.ndarray:
        """Footprint corners (4×2, counter-clockwise)."""
        return rectangle(self.cx, self.cy, self.yaw, self.sx, self.sy)

    def as_tuple(self) -> tuple[float, ...]:
        return (self.cx, self.cy, self.yaw, self.sx, self.sy, self.z0, self.z1)


@dataclass(frozen=True, slots=True)
class Obstacle:
    """A named piece of the world (kind: wall, table, desk, chair or box) made of boxes."""

    name: str
    kind: str
    boxes: tuple[Box, ...]

    def __post_init__(self) -> None:
        if self.kind not in OBSTACLE_KINDS:
            raise ValueError(f"obstacle {self.name!r}: kind must be one of {OBSTACLE_KINDS}")
        if not self.boxes:
            raise ValueError(f"obstacle {self.name!r} has no boxes")


@dataclass(frozen=True, slots=True)
class TagPose:
    """An AprilTag on a vertical surface: centre (x, y, z) and the heading yaw of its
    outward normal (pointing into the room, towards a viewer)."""

    tag_id: int
    x: float
    y: float
    z: float
    yaw: float

    @property
    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.yaw), math.sin(self.yaw), 0.0])

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])


def _dense_route(route: np.ndarray, spacing: float) -> np.ndarray:
    """Split segments longer than spacing evenly; drop repeated points."""
    out = [route[0]]
    for p in route[1:]:
        q = out[-1]
        d = float(np.hypot(*(p - q)))
        if d < 1e-9:
            continue
        n = math.ceil(d / spacing - 1e-9)
        for k in range(1, n):
            out.append(q + (p - q) * (k / n))
        out.append(p)
    return np.array(out, dtype=float)


def smooth_route(
    points: Sequence[Sequence[float]],
    corner_radius: float = 0.0,
    spacing: float = 0.5,
    max_arc_step_rad: float = math.radians(10.0),
) -> np.ndarray:
    """Polyline through corner points with circular fillets, resampled (see module doc).

    points: (N, 2) or rows [x, y, r] whose r overrides corner_radius at that corner.
    """
    rows = [list(map(float, p)) for p in points]
    if len(rows) < 2 or any(len(r) not in (2, 3) for r in rows):
        raise ValueError("route points must be >= 2 rows of [x, y] or [x, y, radius]")
    if spacing <= 0:
        raise ValueError(f"route spacing must be > 0, got {spacing}")
    p = np.array([r[:2] for r in rows])
    radii = [r[2] if len(r) == 3 else corner_radius for r in rows]
    keep = np.concatenate([[True], np.hypot(*np.diff(p, axis=0).T) > 1e-9])
    p = p[keep]
    radii = [r for r, k in zip(radii, keep, strict=True) if k]
    n = len(p)
    seg = np.diff(p, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    out: list[np.ndarray] = [p[0]]
    for i in range(1, n - 1):
        d_in, d_out = seg[i - 1] / seg_len[i - 1], seg[i] / seg_len[i]
        turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(d_in @ d_out))
        r = radii[i]
        if r <= 0 or abs(turn) < 1e-6:
            out.append(p[i])
            continue
        avail_in = seg_len[i - 1] * (1.0 if i - 1 == 0 else 0.5)
        avail_out = seg_len[i] * (1.0 if i + 1 == n - 1 else 0.5)
        tan_half = math.tan(abs(turn) / 2.0)
        t_len = min(r * tan_half, avail_in, avail_out)
        r_eff = t_len / tan_half
        a = p[i] - t_len * d_in
        left = np.array([-d_in[1], d_in[0]])
        centre = a + math.copysign(r_eff, turn) * left
        m = max(1, math.ceil(abs(turn) / max_arc_step_rad), math.ceil(abs(turn) * r_eff / spacing))
        v = a - centre
        for k in range(m + 1):
            phi = turn * k / m
            c, s = math.cos(phi), math.sin(phi)
            out.append(centre + np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]]))
    out.append(p[-1])
    return _dense_route(np.array(out), spacing)


@dataclass(frozen=True, eq=False)
class World:
    """Obstacles, tags, the route a simulated user follows and where the walker starts.

    bounds: (xmin, xmax, ymin, ymax) area of interest; route: (N, 2) waypoints;
    start_pose: (x, y, θ) of the walker's rear-axle centre; user: `UserParams` fields
    that this course's route is walked with (module docstring).
    """

    name: str
    bounds: tuple[float, float, float, float]
    obstacles: tuple[Obstacle, ...]
    tags: tuple[TagPose, ...]
    route: np.ndarray
    start_pose: tuple[float, float, float]
    user: dict[str, Any] = field(default_factory=dict)
    _boxes: np.ndarray = field(init=False, repr=False)
    _box_owner: np.ndarray = field(init=False, repr=False)
    _tag_host: np.ndarray = field(init=False, repr=False)
    _polysets: dict[tuple[float, float], PolygonSet] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        route = np.array(self.route, dtype=float)
        if route.ndim != 2 or route.shape[1] != 2 or len(route) < 2:
            raise ValueError(f"route must be an (N>=2, 2) array, got shape {route.shape}")
        if not np.isfinite(route).all():
            raise ValueError("route has non-finite waypoints")
        route.setflags(write=False)
        object.__setattr__(self, "route", route)
        b = tuple(float(v) for v in self.bounds)
        if len(b) != 4 or not (b[0] < b[1] and b[2] < b[3]):
            raise ValueError(f"bounds must be (xmin, xmax, ymin, ymax) with min < max, got {b}")
        object.__setattr__(self, "bounds", b)
        sp = tuple(float(v) for v in self.start_pose)
        if len(sp) != 3 or not all(math.isfinite(v) for v in sp):
            raise ValueError(f"start_pose must be three finite numbers (x, y, θ), got {sp}")
        object.__setattr__(self, "start_pose", sp)
        object.__setattr__(self, "user", user_params_overrides(self.user))
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        object.__setattr__(self, "tags", tuple(self.tags))
        names = [o.name for o in self.obstacles]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"obstacle names must be unique, repeated: {dup}")
        ids = [t.tag_id for t in self.tags]
        dup_ids = sorted({i for i in ids if ids.count(i) > 1})
        if dup_ids or any(i < 0 for i in ids):
            raise ValueError(f"tag ids must be unique and >= 0, got repeated {dup_ids}")
        rows = [bx.as_tuple() for o in self.obstacles for bx in o.boxes]
        boxes = np.array(rows, dtype=float).reshape(-1, 7)
        owner = np.array([i for i, o in enumerate(self.obstacles) for _ in o.boxes], dtype=int)
        boxes.setflags(write=False)
        owner.setflags(write=False)
        object.__setattr__(self, "_boxes", boxes)
        object.__setattr__(self, "_box_owner", owner)
        object.__setattr__(self, "_polysets", {})
        host = np.array([self._find_host(t) for t in self.tags], dtype=int)
        host.setflags(write=False)
        object.__setattr__(self, "_tag_host", host)

    # -- boxes ---------------------------------------------------------------------------
    @property
    def box_array(self) -> np.ndarray:
        """All boxes as a read-only (B, 7) array of [cx, cy, yaw, sx, sy, z0, z1]."""
        return self._boxes

    @property
    def box_owner(self) -> np.ndarray:
        """Index into `obstacles` of each row of `box_array`."""
        return self._box_owner

    def iter_boxes(self) -> Iterator[tuple[Obstacle, Box]]:
        for o in self.obstacles:
            for bx in o.boxes:
                yield o, bx

    def obstacle(self, name: str) -> Obstacle:
        for o in self.obstacles:
            if o.name == name:
                return o
        raise ValueError(f"no obstacle named {name!r} in world {self.name!r}")

    # -- tags ----------------------------------------------------------------------------
    def tag(self, tag_id: int) -> TagPose:
        for t in self.tags:
            if t.tag_id == tag_id:
                return t
        raise ValueError(f"no tag {tag_id} in world {self.name!r}")

    def world_T_tag(self, tag: TagPose) -> np.ndarray:
        """4×4 pose of a tag in the pupil-apriltags tag-frame convention: origin at the
        centre, x right and y down as seen by a camera facing the tag, z into the tag."""
        n = tag.normal
        z_axis = -n
        y_axis = np.array([0.0, 0.0, -1.0])
        x_axis = np.cross(y_axis, z_axis)
        return make_transform(np.column_stack([x_axis, y_axis, z_axis]), tag.centre)

    def tag_host_box(self, tag: TagPose) -> int:
        """Row of `box_array` whose face the tag is on (-1 if it is on none)."""
        return int(self._tag_host[self.tags.index(tag)])

    @property
    def tag_host_boxes(self) -> np.ndarray:
        """Per tag (in `tags` order) the row of `box_array` it is on, or -1."""
        return self._tag_host

    def _find_host(self, tag: TagPose, tol: float = TAG_SURFACE_TOLERANCE_M) -> int:
        best, best_d = -1, math.inf
        for i, (cx, cy, yaw, sx, sy, z0, z1) in enumerate(self._boxes):
            if not (z0 - tol <= tag.z <= z1 + tol):
                continue
            c, s = math.cos(yaw), math.sin(yaw)
            dx, dy = tag.x - cx, tag.y - cy
            lx, ly = c * dx + s * dy, -s * dx + c * dy
            rel = math.remainder(tag.yaw - yaw, 2 * math.pi)
            # (outward local normal angle, distance off the face plane, position along it)
            faces = (
                (0.0, lx - sx / 2, ly, sy / 2),
                (math.pi, -lx - sx / 2, ly, sy / 2),
                (math.pi / 2, ly - sy / 2, lx, sx / 2),
                (-math.pi / 2, -ly - sy / 2, lx, sx / 2),
            )
            for ang, off, along, half in faces:
                if abs(math.remainder(rel - ang, 2 * math.pi)) > math.radians(10.0):
                    continue
                if abs(off) <= tol and abs(along) <= half + tol and abs(off) < best_d:
                    best, best_d = i, abs(off)
        return best

    # -- footprints and collisions -------------------------------------------------------
    def footprint_polygons(
        self, z_min: float = COLLISION_BAND_M[0], z_max: float = COLLISION_BAND_M[1]
    ) -> list[tuple[str, np.ndarray]]:
        """(obstacle name, 4×2 CCW corners) of every box whose height overlaps [z_min, z_max]."""
        out = []
        for o in self.obstacles:
            for bx in o.boxes:
                if bx.z0 < z_max and bx.z1 > z_min:
                    out.append((o.name, bx.corners()))
        return out

    def polygon_set(
        self, z_min: float = COLLISION_BAND_M[0], z_max: float = COLLISION_BAND_M[1]
    ) -> PolygonSet:
        """The footprints of `footprint_polygons(z_min, z_max)` as a (cached) PolygonSet."""
        key = (float(z_min), float(z_max))
        ps = self._polysets.get(key)
        if ps is None:
            fp = self.footprint_polygons(z_min, z_max)
            ps = PolygonSet([n for n, _ in fp], np.array([p for _, p in fp]).reshape(-1, 4, 2))
            self._polysets[key] = ps
        return ps

    def contacts(
        self,
        parts: Sequence[tuple[str, np.ndarray]],
        z_min: float = COLLISION_BAND_M[0],
        z_max: float = COLLISION_BAND_M[1],
    ) -> list[Contact]:
        """Contacts of named convex walker parts (CCW polygons, world frame) with the
        obstacle footprints in the height band; at most one (the deepest) per part and
        obstacle."""
        return self.polygon_set(z_min, z_max).contacts(parts)

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able description that `from_dict` turns back into an equal world."""
        keys = ("cx", "cy", "yaw", "sx", "sy", "z0", "z1")
        user = {"user": dict(self.user)} if self.user else {}
        return {
            "format": "walker-slam-world",
            "version": _FORMAT_VERSION,
            "name": self.name,
            "bounds": list(self.bounds),
            "start_pose": list(self.start_pose),
            "route": self.route.tolist(),
            "obstacles": [
                {
                    "name": o.name,
                    "kind": o.kind,
                    "boxes": [dict(zip(keys, bx.as_tuple(), strict=True)) for bx in o.boxes],
                }
                for o in self.obstacles
            ],
            "tags": [
                {"id": t.tag_id, "x": t.x, "y": t.y, "z": t.z, "yaw": t.yaw} for t in self.tags
            ],
            **user,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "world") -> World:
        """Build a world from `to_dict` output or a course file (module docstring);
        problems raise ConfigError (a ValueError) starting with `source`."""
        try:
            return _parse_world(d)
        except (_SpecError, ValueError) as e:
            raise ConfigError(f"{source}: {e}") from None


def user_params_overrides(user: dict[str, Any]) -> dict[str, Any]:
    """`user` checked as `UserParams` fields: known names, true/false for the flags, finite
    numbers for the rest (ValueError naming the field)."""
    kinds = {f.name: f.type for f in fields(UserParams)}
    out: dict[str, Any] = {}
    for name, value in dict(user).items():
        if name not in kinds:
            raise ValueError(f"user: unknown setting {name!r}; valid: {', '.join(kinds)}")
        if (kinds[name] in ("bool", bool)) != isinstance(value, bool) or not (
            isinstance(value, bool) or _is_num(value)
        ):
            want = "true or false" if kinds[name] in ("bool", bool) else "a finite number"
            raise ValueError(f"user: {name!r} must be {want}, got {value!r}")
        out[name] = value
    return out


# ---------------------------------------------------------------------------------------
# Parsing of the JSON format
# ---------------------------------------------------------------------------------------
class _SpecError(Exception):
    pass


@dataclass(frozen=True)
class _Frame:
    """Local frame and outline [x0, x1]×[y0, y1] of a compact obstacle (for tags)."""

    x: float
    y: float
    yaw: float
    x0: float
    x1: float
    y0: float
    y1: float


class _Entry:
    """A dict being read, with the place it came from for error messages."""

    def __init__(self, d: Any, where: str) -> None:
        if not isinstance(d, dict):
            raise _SpecError(f"{where}: expected an object, got {type(d).__name__}")
        self.d, self.where, self.used = d, where, set()

    def num(self, key: str, default: float | None = None) -> float:
        if key in self.d:
            v = self.d[key]
            self.used.add(key)
        elif key + "_deg" in self.d and key in ("yaw", "theta"):
            self.used.add(key + "_deg")
            v = self.d[key + "_deg"]
            if isinstance(v, int | float) and not isinstance(v, bool):
                v = math.radians(v)
        elif default is not None:
            return default
        else:
            raise _SpecError(f"{self.where}: missing key {key!r}")
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise _SpecError(f"{self.where}: {key!r} must be a finite number, got {v!r}")
        return float(v)

    def point(self, key: str) -> np.ndarray:
        if key not in self.d:
            raise _SpecError(f"{self.where}: missing key {key!r}")
        self.used.add(key)
        v = self.d[key]
        if not (isinstance(v, list) and len(v) == 2 and all(_is_num(c) for c in v)):
            raise _SpecError(f"{self.where}: {key!r} must be [x, y], got {v!r}")
        return np.array(v, dtype=float)

    def get(self, key: str, default: Any = None) -> Any:
        if key in self.d:
            self.used.add(key)
            return self.d[key]
        return default

    def done(self) -> None:
        extra = sorted(set(self.d) - self.used)
        if extra:
            raise _SpecError(f"{self.where}: unknown keys {extra}")


def _is_num(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _local_box(
    f: tuple[float, float, float], lx: float, ly: float, sx: float, sy: float, z0: float, z1: float
) -> Box:
    x, y, yaw = f
    c, s = math.cos(yaw), math.sin(yaw)
    return Box(x + c * lx - s * ly, y + s * lx + c * ly, yaw, sx, sy, z0, z1)


def table_boxes(
    x: float, y: float, yaw: float, width: float, depth: float, height: float = 0.75
) -> tuple[Box, ...]:
    """Top (3 cm) and four 5 cm square legs inset 3 cm; depth along yaw, width across."""
    f, top, leg, inset = (x, y, yaw), 0.03, 0.05, 0.03
    _positive(width=width, depth=depth, height=height - top)
    if min(width, depth) < 2 * (leg + inset):
        raise ValueError(f"table of {width}×{depth} m is too small for its legs")
    boxes = [_local_box(f, 0, 0, depth, width, height - top, height)]
    ox, oy = depth / 2 - inset - leg / 2, width / 2 - inset - leg / 2
    for sx_, sy_ in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        boxes.append(_local_box(f, sx_ * ox, sy_ * oy, leg, leg, 0.0, height - top))
    return tuple(boxes)


def desk_boxes(
    x: float,
    y: float,
    yaw: float,
    width: float,
    depth: float,
    height: float = 0.75,
    modesty: bool = True,
) -> tuple[Box, ...]:
    """Top, side panels at the ±y ends and a modesty panel on the front (+x) edge."""
    f, top, side, panel = (x, y, yaw), 0.03, 0.025, 0.02
    _positive(width=width, depth=depth, height=height - top - 0.1)
    if width < 3 * side:
        raise ValueError(f"desk width {width} m is too small for its side panels")
    boxes = [_local_box(f, 0, 0, depth, width, height - top, height)]
    for sgn in (1, -1):
        boxes.append(_local_box(f, 0, sgn * (width - side) / 2, depth, side, 0.0, height - top))
    if modesty:
        boxes.append(
            _local_box(f, (depth - panel) / 2, 0, panel, width - 2 * side, 0.10, height - top)
        )
    return tuple(boxes)


def chair_boxes(
    x: float,
    y: float,
    yaw: float,
    width: float = 0.45,
    depth: float = 0.45,
    seat_height: float = 0.45,
    back_height: float = 0.85,
) -> tuple[Box, ...]:
    """Seat (5 cm), four 3 cm legs and a 4 cm back rest on the −x edge (facing +x)."""
    f, seat, leg, back = (x, y, yaw), 0.05, 0.03, 0.04
    _positive(width=width, depth=depth, seat_legs=seat_height - seat)
    if back_height <= seat_height:
        raise ValueError(f"chair back_height {back_height} must exceed seat_height {seat_height}")
    boxes = [_local_box(f, 0, 0, depth, width, seat_height - seat, seat_height)]
    ox, oy = depth / 2 - leg / 2, width / 2 - leg / 2
    for sx_, sy_ in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        boxes.append(_local_box(f, sx_ * ox, sy_ * oy, leg, leg, 0.0, seat_height - seat))
    boxes.append(_local_box(f, -(depth - back) / 2, 0, back, width, seat_height, back_height))
    return tuple(boxes)


def office_chair_boxes(
    x: float,
    y: float,
    yaw: float,
    width: float = 0.46,
    depth: float = 0.46,
    seat_height: float = 0.47,
    back_height: float = 0.95,
    base_radius: float = 0.33,
) -> tuple[Box, ...]:
    """Seat (6 cm) on a 6 cm column, a 4 cm back rest on the −x edge and five 5 cm spokes
    of a star base, 10 cm high, out to base_radius (facing +x)."""
    f, seat, column, back, spoke, base_h = (x, y, yaw), 0.06, 0.06, 0.04, 0.05, 0.10
    _positive(width=width, depth=depth, base_radius=base_radius, column=seat_height - seat - base_h)
    if back_height <= seat_height:
        raise ValueError(f"chair back_height {back_height} must exceed seat_height {seat_height}")
    boxes = [
        _local_box(f, 0, 0, depth, width, seat_height - seat, seat_height),
        _local_box(f, 0, 0, column, column, base_h, seat_height - seat),
        _local_box(f, -(depth - back) / 2, 0, back, width, seat_height, back_height),
    ]
    for k in range(5):
        a = 2 * math.pi * k / 5
        r = base_radius / 2
        boxes.append(
            Box(
                x + r * math.cos(yaw + a),
                y + r * math.sin(yaw + a),
                yaw + a,
                base_radius,
                spoke,
                0.0,
                base_h,
            )
        )
    return tuple(boxes)


def wall_box(
    start: Sequence[float], end: Sequence[float], thickness: float = 0.1, height: float = 2.4
) -> Box:
    """A wall centred on the segment start→end."""
    a, b = np.asarray(start, float), np.asarray(end, float)
    length = float(np.hypot(*(b - a)))
    _positive(length=length, thickness=thickness, height=height)
    mid = 0.5 * (a + b)
    yaw = math.atan2(b[1] - a[1], b[0] - a[0])
    return Box(float(mid[0]), float(mid[1]), yaw, length, thickness, 0.0, height)


def _positive(**vals: float) -> None:
    for k, v in vals.items():
        if not v > 0:
            raise ValueError(f"{k} must be > 0, got {v}")


def _parse_obstacle(e: _Entry, index: int) -> tuple[Obstacle, _Frame | None]:
    kind = e.get("kind")
    if kind not in OBSTACLE_KINDS:
        raise _SpecError(f"{e.where}: 'kind' must be one of {list(OBSTACLE_KINDS)}, got {kind!r}")
    name = e.get("name", f"{kind}-{index}")
    if not isinstance(name, str) or not name:
        raise _SpecError(f"{e.where}: 'name' must be a non-empty string")
    e.where = f"{e.where} ({name})"
    frame: _Frame | None = None
    try:
        if "boxes" in e.d:
            raw = e.get("boxes")
            if not isinstance(raw, list) or not raw:
                raise _SpecError(f"{e.where}: 'boxes' must be a non-empty list")
            boxes = []
            for j, bd in enumerate(raw):
                be = _Entry(bd, f"{e.where} boxes[{j}]")
                keys = ("cx", "cy", "yaw", "sx", "sy", "z0", "z1")
                boxes.append(Box(*(be.num(k) for k in keys)))
                be.done()
            boxes_t = tuple(boxes)
        elif kind == "wall":
            a, b = e.point("from"), e.point("to")
            t = e.num("thickness", 0.1)
            bx = wall_box(a, b, t, e.num("height", 2.4))
            boxes_t = (bx,)
            frame = _Frame(float(a[0]), float(a[1]), bx.yaw, 0.0, bx.sx, -t / 2, t / 2)
        else:
            x, y, yaw = e.num("x"), e.num("y"), e.num("yaw", 0.0)
            if kind == "box":
                sx, sy = e.num("sx"), e.num("sy")
                boxes_t = (Box(x, y, yaw, sx, sy, e.num("z0", 0.0), e.num("height")),)
            else:
                boxes_t, sx, sy = _furniture_boxes(e, kind, x, y, yaw)
            frame = _Frame(x, y, yaw, -sx / 2, sx / 2, -sy / 2, sy / 2)
        e.done()
        return Obstacle(name, kind, boxes_t), frame
    except ValueError as err:
        raise _SpecError(f"{e.where}: {err}") from None


# Default (width, depth) of the furniture kinds; None: required.
_FURNITURE_SIZE = {
    "table": (None, None),
    "desk": (None, None),
    "chair": (0.45, 0.45),
    "office-chair": (0.46, 0.46),
}


def _furniture_boxes(
    e: _Entry, kind: str, x: float, y: float, yaw: float
) -> tuple[tuple[Box, ...], float, float]:
    """The boxes of a table, desk, chair or office chair in compact form, and its
    outline's extent along its local x (depth) and y (width)."""
    dw, dd = _FURNITURE_SIZE[kind]
    w, dp = e.num("width", dw), e.num("depth", dd)
    if kind == "table":
        return table_boxes(x, y, yaw, w, dp, e.num("height", 0.75)), dp, w
    if kind == "desk":
        modesty = e.get("modesty", True)
        if not isinstance(modesty, bool):
            raise _SpecError(f"{e.where}: 'modesty' must be true or false")
        return desk_boxes(x, y, yaw, w, dp, e.num("height", 0.75), modesty), dp, w
    if kind == "office-chair":
        heights = (e.num("seat_height", 0.47), e.num("back_height", 0.95))
        return office_chair_boxes(x, y, yaw, w, dp, *heights, e.num("base_radius", 0.33)), dp, w
    heights = (e.num("seat_height", 0.45), e.num("back_height", 0.85))
    return chair_boxes(x, y, yaw, w, dp, *heights), dp, w


def _parse_tag(e: _Entry, frames: dict[str, _Frame | None]) -> TagPose:
    tag_id = e.get("id")
    if isinstance(tag_id, bool) or not isinstance(tag_id, int) or tag_id < 0:
        raise _SpecError(f"{e.where}: 'id' must be an integer >= 0, got {tag_id!r}")
    e.where = f"{e.where} (id {tag_id})"
    if "on" not in e.d:
        t = TagPose(tag_id, e.num("x"), e.num("y"), e.num("z"), e.num("yaw"))
        e.done()
        return t
    on = e.get("on")
    if on not in frames:
        raise _SpecError(f"{e.where}: 'on' names no obstacle: {on!r}")
    f = frames[on]
    if f is None:
        raise _SpecError(f"{e.where}: obstacle {on!r} is given as raw boxes; give x, y, z, yaw")
    face = e.get("face")
    at, z = e.num("at", 0.0), e.num("z")
    faces = {
        "front": (f.x1, at, 0.0),
        "back": (f.x0, at, math.pi),
        "left": (at, f.y1, math.pi / 2),
        "right": (at, f.y0, -math.pi / 2),
    }
    if face not in faces:
        raise _SpecError(f"{e.where}: 'face' must be one of {list(faces)}, got {face!r}")
    lx, ly, ang = faces[face]
    e.done()
    c, s = math.cos(f.yaw), math.sin(f.yaw)
    yaw = math.remainder(f.yaw + ang, 2 * math.pi)
    return TagPose(tag_id, f.x + c * lx - s * ly, f.y + s * lx + c * ly, z, yaw)


def _parse_route(v: Any) -> np.ndarray:
    if isinstance(v, list):
        pts = np.array(v, dtype=float) if v and all(isinstance(r, list) for r in v) else None
        if pts is None or pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            raise _SpecError("'route' must be a list of >= 2 [x, y] points")
        return _dense_route(pts, 0.5)
    e = _Entry(v, "route")
    pts = e.get("points")
    if not isinstance(pts, list) or not all(
        isinstance(r, list) and all(_is_num(c) for c in r) for r in pts
    ):
        raise _SpecError("route: 'points' must be a list of [x, y] or [x, y, radius]")
    radius, spacing = e.num("corner_radius", 0.0), e.num("spacing", 0.5)
    e.done()
    try:
        return smooth_route(pts, radius, spacing)
    except ValueError as err:
        raise _SpecError(f"route: {err}") from None


def _parse_world(d: Any) -> World:
    e = _Entry(d, "world")
    e.get("format")
    version = e.get("version", _FORMAT_VERSION)
    if version != _FORMAT_VERSION:
        raise _SpecError(f"unsupported world format version {version!r}")
    name = e.get("name")
    if not isinstance(name, str) or not name:
        raise _SpecError("'name' must be a non-empty string")
    bounds = e.get("bounds")
    if not (isinstance(bounds, list) and len(bounds) == 4 and all(_is_num(b) for b in bounds)):
        raise _SpecError(f"'bounds' must be [xmin, xmax, ymin, ymax], got {bounds!r}")
    sp = e.get("start_pose")
    if isinstance(sp, dict):
        se = _Entry(sp, "start_pose")
        start = (se.num("x"), se.num("y"), se.num("theta"))
        se.done()
    elif isinstance(sp, list) and len(sp) == 3 and all(_is_num(v) for v in sp):
        start = tuple(float(v) for v in sp)
    else:
        raise _SpecError(f"'start_pose' must be [x, y, theta] or an object, got {sp!r}")
    if "route" not in e.d:
        raise _SpecError("missing key 'route'")
    route = _parse_route(e.get("route"))
    obs_raw = e.get("obstacles", [])
    tags_raw = e.get("tags", [])
    if not isinstance(obs_raw, list) or not isinstance(tags_raw, list):
        raise _SpecError("'obstacles' and 'tags' must be lists")
    obstacles, frames = [], {}
    for i, od in enumerate(obs_raw):
        o, fr = _parse_obstacle(_Entry(od, f"obstacles[{i}]"), i)
        obstacles.append(o)
        frames[o.name] = fr
    tags = []
    attached = []
    for i, td in enumerate(tags_raw):
        te = _Entry(td, f"tags[{i}]")
        attached.append(isinstance(td, dict) and "on" in td)
        tags.append(_parse_tag(te, frames))
    user = e.get("user", {})
    if not isinstance(user, dict):
        raise _SpecError(f"'user' must be an object of user settings, got {user!r}")
    e.done()
    world = World(name, tuple(bounds), tuple(obstacles), tuple(tags), route, start, user)  # type: ignore[arg-type]
    for t, att, host in zip(tags, attached, world.tag_host_boxes, strict=True):
        if att and host < 0:
            raise _SpecError(
                f"tag {t.tag_id} at ({t.x:.3f}, {t.y:.3f}, {t.z:.3f}) is not on a box face"
            )
    return world


# ---------------------------------------------------------------------------------------
# Built-in courses and files
# ---------------------------------------------------------------------------------------
def _course_dir() -> Any:
    return resources.files("hardware.sim").joinpath("courses")


def available_courses() -> list[str]:
    """Names of the built-in courses (JSON files in hardware/sim/courses)."""
    return sorted(
        p.name[: -len(".json")] for p in _course_dir().iterdir() if p.name.endswith(".json")
    )


def load_world(name_or_path: str | Path) -> World:
    """A built-in course by name, or a course / saved world JSON file by path."""
    s = str(name_or_path)
    if isinstance(name_or_path, Path) or s.endswith(".json") or "/" in s or "\\" in s:
        path = Path(s)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as e:
            raise ConfigError(f"{path}: cannot read world file ({e.strerror})") from None
        source = str(path)
    else:
        names = available_courses()
        if s not in names:
            raise UnknownNameError("course", s, names)
        text = _course_dir().joinpath(s + ".json").read_text(encoding="utf-8")
        source = f"built-in course {s!r}"
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"{source}: not valid JSON ({e.msg} at line {e.lineno})") from None
    return World.from_dict(d, source=source)
