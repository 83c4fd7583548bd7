"""2-D scan matching between keyframe scans: correlative search + point-to-line ICP.

Scans become planar point sets in the walker frame: a `LaserScan` through the mapper's
own beam geometry (`mapping.scan_points.scan_to_observation`, with the laser's mount
offset and a usable range), a `DepthFrame` through the mapper's depth projection
(`mapping.depth_points.project_depth_frame`): its obstacle band flattened to the floor
plane, snapped to the voxel lattice. Points are thinned to one per `voxel_m` cell (the
centroid), so near and far surfaces weigh alike.

A *reference* (one scan, or several scans placed in one frame: a local submap) is
prepared once: a k-d tree (`scipy.spatial.cKDTree`), a surface normal per point from
the principal axes of its neighbours (points on a line), for ICP its points sorted into
cells as wide as the correspondence gate (`Reference.buckets`: its compiled loop,
slam.scan_kernels.icp_steps, finds the nearest point within the gate there), and, for
the correlative search, a likelihood field: exp(−d²/2σ²) of the distance d to the
nearest reference point on a `grid_m` grid (mapping.distance, exact).

`match(reference, query, guess, window)` finds the pose of the query scan's frame in the
reference frame:

1. correlative search (Olson 2009, brute force on one coarse level): every heading in
   guess ± window_θ (steps of `angle_step_rad`) and every translation in guess ±
   window_xy (steps of `coarse_step_m`) scores the mean likelihood of the rotated and
   shifted query points; the field is max-filtered over one translation step first, so
   a coarse cell scores the best of the fine translations it stands for. The best few
   distinct poses (`refine_candidates`) go to
2. ICP, point-to-line (point-to-point where the reference point has no reliable
   normal): nearest neighbours within `max_correspondence_m`, Huber weights
   (`huber_m`), Gauss-Newton on (x, y, θ) until a step is below `icp_tolerance`;
3. the refined candidate with the most support (below) wins. An inlier is a query point whose
   nearest reference point is within `max_correspondence_m` and whose point-to-line
   (or point-to-point) distance is within `inlier_m`. `inlier_fraction` is inliers /
   query points: the quality score callers threshold to reject a match.
   `conflict_fraction`: share of query points that land in space the reference saw
   free (see `Reference`). Candidates are ranked by support = Σ over inliers of
   1 − (distance / inlier_m)² minus the number of conflicts.
   `ambiguity`: best support of the other refined candidates that converged beyond 3
   standard deviations (Mahalanobis, under the winner's covariance) and beyond two
   coarse steps (or three heading steps) of the winner, divided by the winner's (0:
   unambiguous; near 1: a different alignment fits as well, e.g. a repeated room).
   `constraint`: smallest / largest eigenvalue of the inliers' translational
   information (0: all surfaces parallel, e.g. two corridor walls, and the position
   along them is not measured; `weak_axis` is that direction).

Covariance: the Gauss-Newton estimate σ²·H⁻¹ at the solution (H = JᵀJ of the inlier
residuals, σ² their mean square per degree of freedom), scaled by `covariance_scale`
and with `sigma_floor` (x, y, θ) added in quadrature. The Hessian estimate is known to
be optimistic (it ignores data-association and discretisation error; Censi 2007), so
the floor dominates on well-structured scans. Along a degenerate direction (a
featureless corridor) H is nearly singular, but noisy normals fake some constraint, so
a match whose `constraint` is below `degenerate_constraint` gets `degenerate_sigma_m`
added along its weak axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from hardware.calibration import WalkerCalibration
from hardware.geometry import transform_points, wrap_angle
from hardware.messages import DepthFrame, LaserScan
from hardware.small_linalg import dot, eigh2, eigvalsh3, gram, inv, matvec
from mapping.depth_points import DepthConfig, project_depth_frame
from mapping.distance import squared_distances
from mapping.scan_points import ScanConfig, scan_to_observation
from slam.scan_kernels import buckets, grid_scores, icp_steps

FREE_BIN_RAD = math.radians(0.5)  # angular bins of a scan's free-space polygon

__all__ = [
    "MatchResult",
    "Reference",
    "Scan",
    "ScanMatchConfig",
    "correlative_search",
    "depth_points",
    "icp",
    "laser_points",
    "match",
    "place",
    "relative_guess",
    "voxel_downsample",
]


@dataclass(frozen=True)
class ScanMatchConfig:
    """Scan-matcher settings (lengths in metres, angles in radians).

    voxel_m: one point (the centroid) per cell of this size, for query and reference.
    normal_neighbours, normal_radius_m: a reference point's normal comes from its
    nearest neighbours within the radius (at least 3 of them); it is used (point-to-line)
    when the neighbours lie on a line: smallest / largest spread below max_planarity.
    max_correspondence_m: ICP pairs a query point with its nearest reference point only
    within this distance; huber_m: residuals beyond it are down-weighted.
    inlier_m: an inlier's point-to-line (or point-to-point) distance at the solution.
    icp_iterations: at most this many Gauss-Newton steps; icp_tolerance: converged when
    a step moves less than this (m, rad); a match that has not converged is rejected.
    100: with re-association after every step ICP creeps along walls by a few mm per
    step for dozens of steps (30 left 39 of edmonton's 339 sequential matches
    unconverged, and rejected; with 100 none; BENCHMARKS.md).
    grid_m, field_sigma_m: the correlative search's likelihood field; free_penalty: the
    score of a query point in seen-free space (farther than free_margin_m from every
    reference point);
    coarse_step_m, angle_step_rad: its translation and heading steps; refine_candidates:
    how many of its best distinct poses ICP refines; multires_offsets, multires_blocks:
    a window wider than multires_offsets coarse steps either way is searched on two
    levels, refining the multires_blocks best blocks (`correlative_search`).
    sigma_floor, covariance_scale, degenerate_constraint, degenerate_sigma_m: the
    match covariance (module docstring).
    min_points: fewer query or reference points than this: no match.
    """

    voxel_m: float = 0.05
    normal_neighbours: int = 8
    normal_radius_m: float = 0.5
    max_planarity: float = 0.1
    max_correspondence_m: float = 0.3
    huber_m: float = 0.05
    inlier_m: float = 0.05
    icp_iterations: int = 100
    icp_tolerance: tuple[float, float] = (5e-4, 5e-5)
    grid_m: float = 0.05
    field_sigma_m: float = 0.1
    free_penalty: float = 1.0
    free_margin_m: float = 0.15
    coarse_step_m: float = 0.1
    angle_step_rad: float = math.radians(1.0)
    refine_candidates: int = 3
    multires_offsets: int = 15
    multires_blocks: int = 50
    sigma_floor: tuple[float, float, float] = (0.02, 0.02, math.radians(0.5))
    covariance_scale: float = 1.0
    degenerate_constraint: float = 0.02
    degenerate_sigma_m: float = 1.0
    min_points: int = 20

    def __post_init__(self) -> None:
        for name in ("voxel_m", "grid_m", "field_sigma_m", "coarse_step_m", "angle_step_rad"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.inlier_m <= self.max_correspondence_m:
            raise ValueError("need 0 < inlier_m <= max_correspondence_m")
        if self.refine_candidates < 1 or self.icp_iterations < 1:
            raise ValueError("refine_candidates and icp_iterations must be >= 1")


# why a match is rejected (Acceptance.failures): ICP did not converge, too few inliers,
# too many points in the reference's free space, a rival pose nearly as good, too little
# constraint, a covariance that is not finite
REJECTIONS = ("unconverged", "inliers", "conflict", "ambiguity", "constraint", "covariance")


@dataclass(frozen=True, eq=False)
class MatchResult:
    """Pose (x, y, θ) of the query frame in the reference frame, its 3×3 covariance and
    the quality of the fit (see the module docstring)."""

    pose: np.ndarray
    covariance: np.ndarray
    inlier_fraction: float
    inliers: int
    points: int
    rmse_m: float
    iterations: int
    converged: bool
    conflict_fraction: float = 0.0
    constraint: float = 0.0
    weak_axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0]))
    support: float = 0.0
    score: float = math.nan  # correlative score of the winner's start
    ambiguity: float = 0.0


@dataclass(frozen=True)
class Acceptance:
    """When a match is accepted (no `failures`): its inlier fraction at least
    min_inlier_fraction, conflict fraction and ambiguity at most max_conflict_fraction
    and max_ambiguity, `constraint` at least min_constraint (0: a corridor, its position
    along it unmeasured). The thresholds of every gate a match passes."""

    min_inlier_fraction: float = 0.3
    max_conflict_fraction: float = 0.2
    max_ambiguity: float = 0.9
    min_constraint: float = 0.0

    def accepts(self, res: MatchResult) -> bool:
        return not self.failures(res)

    def failures(self, res: MatchResult) -> tuple[str, ...]:
        """The tests `res` fails at these thresholds (none: accepted), each named by one
        of REJECTIONS: why it is rejected. A NaN fails its test."""
        failed = (
            not res.converged,
            not res.inlier_fraction >= self.min_inlier_fraction,
            not res.conflict_fraction <= self.max_conflict_fraction,
            not res.ambiguity <= self.max_ambiguity,
            not res.constraint >= self.min_constraint,
            not bool(np.all(np.isfinite(res.covariance))),
        )
        return tuple(name for name, f in zip(REJECTIONS, failed, strict=True) if f)


# ---------------------------------------------------------------------------------------
# points


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The centroid of the points in each voxel × voxel cell (N×2 → M×2, M ≤ N)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0 or voxel <= 0:
        return pts.copy()
    cells = np.floor(pts / voxel).astype(np.int64)
    _, inv, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    out = np.empty((len(counts), 2))
    out[:, 0] = np.bincount(inv, weights=pts[:, 0]) / counts
    out[:, 1] = np.bincount(inv, weights=pts[:, 1]) / counts
    return out


@dataclass(frozen=True, eq=False)
class Scan:
    """One scan on the floor plane, in its own (walker) frame: the surface points (N×2),
    the sensor position (2,) and the ends of the rays that show free space (M×2: every
    ray ran through free space from the sensor up to its end)."""

    points: np.ndarray
    origin: np.ndarray
    ends: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def moved(self, pose: np.ndarray) -> Scan:
        """The same scan expressed in the parent frame of `pose` (its pose there)."""
        return Scan(
            transform_points(pose, self.points),
            transform_points(pose, self.origin[None])[0],
            transform_points(pose, self.ends),
        )


def _scan_from(obs, voxel_m: float, min_range_m: float = 0.0) -> Scan:
    pts = np.asarray(obs.obstacles, dtype=np.float64).reshape(-1, 2)
    ends = np.asarray(obs.ray_ends, dtype=np.float64).reshape(-1, 2)
    origin = np.asarray(obs.sensor_xy, dtype=np.float64).reshape(2)
    if min_range_m > 0 and len(pts):
        pts = pts[np.hypot(*(pts - origin).T) > min_range_m]
    if voxel_m > 0:
        pts = voxel_downsample(pts, voxel_m)
    return Scan(pts, origin, ends)


def laser_points(
    scan: LaserScan,
    sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
    max_range_m: float | None = None,
    min_range_m: float = 0.0,
    voxel_m: float = 0.0,
) -> Scan:
    """The scan's returns (within max_range_m, beyond min_range_m) as walker-frame
    points, voxel-thinned when voxel_m > 0, with its free-space rays (returns beyond
    max_range_m clear space up to it; beams without a return clear nothing)."""
    obs = scan_to_observation(scan, sensor_offset, ScanConfig(max_range_m=max_range_m))
    return _scan_from(obs, voxel_m, min_range_m)


def depth_points(
    frame: DepthFrame,
    calibration: WalkerCalibration,
    config: DepthConfig | None = None,
    voxel_m: float = 0.0,
    min_range_m: float = 0.0,
) -> Scan:
    """The depth frame's obstacle band (mapping.depth_points: heights between the floor
    clearance and the band's top) flattened to the floor, snapped to the voxel_m
    lattice and thinned when voxel_m > 0, with the free-space ray ends the mapper uses."""
    obs = project_depth_frame(frame, calibration, config, quantum=voxel_m)
    return _scan_from(obs, voxel_m, min_range_m)


def _points(query: np.ndarray | Scan) -> np.ndarray:
    if isinstance(query, Scan):
        return query.points
    return np.asarray(query, dtype=float).reshape(-1, 2)


# ---------------------------------------------------------------------------------------
# reference


class Reference:
    """A point set prepared for matching against: k-d tree, normals, likelihood field.

    `source`: N×2 points, a `Scan`, or several scans (a local submap), all in the
    reference frame (`place` puts scans there). Points are voxel-thinned with
    config.voxel_m. Each scan's free space (the polygon of its sensor and its farthest
    ray end per 0.5° of bearing, filled with OpenCV) marks cells as *seen free*: a query
    point that lands there, farther than free_margin_m and ~1.2 field_sigma_m from every
    reference point, contradicts the reference (a *conflict*), while a point in space
    the reference never saw is neutral.
    """

    def __init__(
        self, source: np.ndarray | Scan | list[Scan], config: ScanMatchConfig | None = None
    ) -> None:
        self.config = cfg = config or ScanMatchConfig()
        scans = [source] if isinstance(source, Scan) else source
        if isinstance(scans, list):
            points = np.concatenate([sc.points for sc in scans]) if scans else np.zeros((0, 2))
            self._rays = [(sc.origin, sc.ends) for sc in scans if len(sc.ends)]
        else:
            points = np.asarray(source, dtype=float).reshape(-1, 2)
            self._rays = []
        self.points = voxel_downsample(points, cfg.voxel_m)
        self.tree = cKDTree(self.points) if len(self.points) else None
        self.normals, self.has_normal = self._normals()
        self._field: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None
        self._buckets: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._pooled: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.points)

    def _normals(self) -> tuple[np.ndarray, np.ndarray]:
        cfg, n = self.config, len(self.points)
        normals = np.zeros((n, 2))
        ok = np.zeros(n, dtype=bool)
        if n < 3 or self.tree is None:
            return normals, ok
        k = min(cfg.normal_neighbours, n)
        d, idx = self.tree.query(self.points, k=k, distance_upper_bound=cfg.normal_radius_m)
        d, idx = d.reshape(n, k), idx.reshape(n, k)
        valid = np.isfinite(d)
        w = valid.astype(float)
        cnt = w.sum(axis=1)
        nb = self.points[np.minimum(idx, n - 1)]  # (n, k, 2); invalid ones masked by w
        mean = (nb * w[..., None]).sum(axis=1) / cnt[:, None]
        c = (nb - mean[:, None, :]) * w[..., None]
        sxx = (c[..., 0] ** 2).sum(axis=1)
        syy = (c[..., 1] ** 2).sum(axis=1)
        sxy = (c[..., 0] * c[..., 1]).sum(axis=1)
        # eigen-decomposition of [[sxx, sxy], [sxy, syy]] in closed form
        tr, det = sxx + syy, sxx * syy - sxy * sxy
        disc = np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
        lmax, lmin = 0.5 * tr + disc, 0.5 * tr - disc
        # the normal is the eigenvector of lmin: the line direction has angle φ with
        # tan 2φ = 2 sxy / (sxx − syy); the normal is perpendicular to it
        phi = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        normals[:, 0], normals[:, 1] = -np.sin(phi), np.cos(phi)
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = (cnt >= 3) & (lmax > 0) & (lmin <= cfg.max_planarity * lmax)
        return normals, ok

    def buckets(self, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points sorted by grid cells of side `gate`, for ICP's nearest neighbours
        within the gate (slam.scan_kernels.buckets), built once per gate."""
        if gate not in self._buckets:
            self._buckets[gate] = buckets(self.points, gate)
        return self._buckets[gate]

    def field(self) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """(score grid (H×W), origin (x, y) of cell (0, 0), resolution, conflict mask).

        The score of a cell is the likelihood exp(−d²/2σ²) of the distance d to the
        nearest reference point, or −free_penalty where the cell was seen free and the
        likelihood is below ½ (the conflict mask). The grid has a border of zeros so
        clipped lookups outside it score nothing."""
        if self._field is None:
            cfg = self.config
            res = cfg.grid_m
            margin = 3 * cfg.field_sigma_m + 2 * res
            lo = self.points.min(axis=0) - margin
            hi = self.points.max(axis=0) + margin
            shape = (
                math.ceil((hi[1] - lo[1]) / res) + 1,
                math.ceil((hi[0] - lo[0]) / res) + 1,
            )
            occ = np.zeros(shape, dtype=bool)
            ij = np.floor((self.points - lo) / res).astype(int)
            occ[ij[:, 1], ij[:, 0]] = True
            dist = np.sqrt(squared_distances(occ)) * res  # = scipy's distance_transform_edt
            lik = np.exp(-0.5 * (dist / cfg.field_sigma_m) ** 2)
            free = np.zeros(shape, dtype=np.uint8)
            polys = [
                np.round((_free_polygon(o, e, FREE_BIN_RAD) - lo) / res * 16).astype(np.int32)
                for o, e in self._rays
            ]
            for poly in polys:  # one by one: overlapping contours of one call cancel out
                cv2.fillPoly(free, [poly], 1, lineType=cv2.LINE_8, shift=4)
            # a margin short of the rays' ends stays unknown (the surfaces' own noise)
            near_end = dist < cfg.free_margin_m
            conflict = free.astype(bool) & ~near_end & (lik < 0.5)
            score = np.where(conflict, -cfg.free_penalty, lik)
            for a in (score, conflict):
                a[[0, -1], :] = 0
                a[:, [0, -1]] = 0
            self._field = (score, lo, res, conflict)
        return self._field

    def pooled(self, size: int) -> np.ndarray:
        """The field's score max-filtered over size × size cells (outside: 0), built
        once per size: the correlative search's best score within a step or a block."""
        if size not in self._pooled:
            score = self.field()[0]
            self._pooled[size] = ndimage.maximum_filter(score, size=size, mode="constant")
        return self._pooled[size]

    def conflicts(self, q: np.ndarray) -> np.ndarray:
        """Which points (N×2, reference frame) land in seen-free space away from every
        reference point."""
        _, lo, res, conflict = self.field()
        ij = np.floor((q - lo) / res).astype(np.int64)
        h, w = conflict.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.zeros(len(q), dtype=bool)
        out[inside] = conflict[ij[inside, 1], ij[inside, 0]]
        return out


def _free_polygon(origin: np.ndarray, ends: np.ndarray, bin_rad: float) -> np.ndarray:
    """The region a scan saw free as a polygon: the sensor, then per angular bin (as
    seen from the sensor) the farthest ray end, in angle order. For a laser scan with
    beams wider apart than bin_rad that is every beam's end."""
    d = ends - origin
    ang = np.arctan2(d[:, 1], d[:, 0])
    dist = np.hypot(d[:, 0], d[:, 1])
    b = np.floor(ang / bin_rad).astype(np.int64)
    order = np.lexsort((-dist, b))  # by bin, farthest first
    first = np.ones(len(order), dtype=bool)
    first[1:] = b[order][1:] != b[order][:-1]
    return np.vstack([origin[None], ends[order[first]]])


# ---------------------------------------------------------------------------------------
# ICP


def _associate(ref: Reference, q: np.ndarray, gate: float):
    d, idx = ref.tree.query(q, distance_upper_bound=gate)
    ok = np.isfinite(d)
    return d, np.where(ok, idx, 0), ok


def _residuals(
    ref: Reference, q: np.ndarray, t: np.ndarray, idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residuals r and Jacobian rows J (∂r/∂(x, y, θ)) of the query points q
    (already transformed; t the translation, for the rotation derivative) paired with
    the reference points idx: one point-to-line row where the reference point has a
    normal, two point-to-point rows where it has none."""
    line = ref.has_normal[idx]
    pt = ~line
    dq = np.column_stack([-(q[:, 1] - t[1]), q[:, 0] - t[0]])  # ∂q/∂θ
    p = ref.points[idx]
    n = ref.normals[idx[line]]
    r_line = np.einsum("ij,ij->i", n, q[line] - p[line])
    j_line = np.column_stack([n, np.einsum("ij,ij->i", n, dq[line])])
    e = q[pt] - p[pt]
    r_pt = e.ravel()
    j_pt = np.zeros((2 * len(e), 3))
    j_pt[0::2, 0] = 1.0
    j_pt[1::2, 1] = 1.0
    j_pt[0::2, 2] = dq[pt, 0]
    j_pt[1::2, 2] = dq[pt, 1]
    return np.concatenate([r_line, r_pt]), np.vstack([j_line, j_pt])


def icp(
    ref: Reference,
    query: np.ndarray,
    guess: np.ndarray,
    config: ScanMatchConfig | None = None,
) -> MatchResult:
    """Point-to-line ICP of `query` (N×2 points or a Scan, in its own frame) onto `ref`
    from `guess` (the query frame's pose in the reference frame)."""
    cfg = config or ref.config
    x = np.array(guess, dtype=float)
    query = _points(query)
    nan = np.full((3, 3), np.nan)
    if len(query) < cfg.min_points or len(ref) < cfg.min_points:
        return MatchResult(x, nan, 0.0, 0, len(query), math.nan, 0, False)
    it, converged = icp_steps(
        ref.points, ref.normals, ref.has_normal, *ref.buckets(cfg.max_correspondence_m),
        np.ascontiguousarray(query, dtype=float), x, cfg.max_correspondence_m, cfg.huber_m,
        cfg.icp_iterations, cfg.icp_tolerance[0], cfg.icp_tolerance[1], cfg.min_points,
    )  # fmt: skip
    return _evaluate(ref, query, x, cfg, it, converged)


def _evaluate(
    ref: Reference, query: np.ndarray, x: np.ndarray, cfg: ScanMatchConfig, it: int, conv: bool
) -> MatchResult:
    q = transform_points(x, query)
    _, idx, ok = _associate(ref, q, cfg.max_correspondence_m)
    has_n = ref.has_normal[idx]
    dist = np.where(
        has_n,
        np.abs(np.einsum("ij,ij->i", ref.normals[idx], q - ref.points[idx])),
        np.hypot(*(q - ref.points[idx]).T),
    )
    inl = ok & (dist <= cfg.inlier_m)
    n_in = int(inl.sum())
    cov = np.full((3, 3), np.nan)
    rmse = math.nan
    constraint, weak = 0.0, np.array([1.0, 0.0])
    if n_in >= max(cfg.min_points, 3):
        r, jac = _residuals(ref, q[inl], x[:2], idx[inl])
        rmse = float(np.sqrt(np.mean(r * r)))
        dof = max(len(r) - 3, 1)
        sigma2 = max(dot(r, r) / dof, 1e-8)
        h = gram(jac)
        lam, vec = eigh2(h[:2, :2])
        if lam[1] > 0:
            constraint, weak = float(max(lam[0], 0.0) / lam[1]), vec[:, 0]
        eig = eigvalsh3(h)
        if eig[0] > 0 and eig[2] < 1e12 * eig[0]:  # condition number below 1e12
            cov = cfg.covariance_scale * sigma2 * inv(h)
            cov = 0.5 * (cov + cov.T) + np.diag(np.square(cfg.sigma_floor))
            if constraint < cfg.degenerate_constraint:
                cov[:2, :2] += cfg.degenerate_sigma_m**2 * np.outer(weak, weak)
    conflict = ref.conflicts(q) & ~inl
    support = float(np.sum(1.0 - np.square(dist[inl] / cfg.inlier_m)) - conflict.sum())
    return MatchResult(
        x,
        cov,
        n_in / len(query),
        n_in,
        len(query),
        rmse,
        it,
        conv,
        conflict_fraction=float(conflict.mean()),
        constraint=constraint,
        weak_axis=weak,
        support=support,
    )


# ---------------------------------------------------------------------------------------
# correlative search


def correlative_search(
    ref: Reference,
    query: np.ndarray,
    guess: np.ndarray,
    window_xy: float,
    window_theta: float,
    config: ScanMatchConfig | None = None,
    count: int | None = None,
) -> list[tuple[np.ndarray, float]]:
    """The best `count` distinct poses (and their scores, the mean likelihood of the
    query points) within guess ± window_xy (x and y) and ± window_theta.

    A window of more than `multires_offsets` coarse steps either way is searched on two
    levels: blocks of k × k coarse steps scored on the field max-filtered over a block
    (an upper bound of every pose in it), then every coarse step of the
    `multires_blocks` best blocks (per heading and block)."""
    cfg = config or ref.config
    query = _points(query)
    count = cfg.refine_candidates if count is None else count
    lik, lo, res, _ = ref.field()
    step_cells = max(1, round(cfg.coarse_step_m / res))
    # best fine translation within half a coarse step either way
    pooled = ref.pooled(step_cells + 1 - (step_cells % 2))
    nt = math.floor(window_xy / (step_cells * res) + 1e-9)
    na = math.floor(window_theta / cfg.angle_step_rad + 1e-9)
    angles = guess[2] + np.arange(-na, na + 1) * cfg.angle_step_rad
    flat = pooled.ravel()
    cells = [
        np.floor((transform_points((guess[0], guess[1], th), query) - lo) / res).astype(np.int64)
        for th in angles
    ]
    if nt <= cfg.multires_offsets:
        offs = np.arange(-nt, nt + 1) * step_cells  # cell offsets
        scores = np.stack([grid_scores(flat, *pooled.shape, c, offs, offs) for c in cells])
        a_i, iy, ix = np.unravel_index(np.argsort(scores, axis=None)[::-1][:5000], scores.shape)
        found = zip(scores[a_i, iy, ix], a_i, offs[iy], offs[ix], strict=True)
    else:
        k = math.ceil(nt / cfg.multires_offsets)  # coarse steps per block side
        block = k * step_cells
        bound = ref.pooled(block + step_cells + 1).ravel()
        centres = np.arange(-math.ceil(nt / k), math.ceil(nt / k) + 1) * block
        upper = np.stack([grid_scores(bound, *lik.shape, c, centres, centres) for c in cells])
        best = np.argsort(upper, axis=None)[::-1][: cfg.multires_blocks]
        inner = np.arange(-(k // 2), k - k // 2) * step_cells
        parts = []
        for a_b, iy_b, ix_b in zip(*np.unravel_index(best, upper.shape), strict=True):
            ys, xs = centres[iy_b] + inner, centres[ix_b] + inner
            sc = grid_scores(flat, *pooled.shape, cells[a_b], xs, ys)
            yy, xx = np.meshgrid(ys, xs, indexing="ij")
            parts.append(
                np.column_stack([sc.ravel(), np.full(sc.size, a_b), yy.ravel(), xx.ravel()])
            )
        table = np.concatenate(parts)
        table = table[np.argsort(table[:, 0])[::-1][:5000]]
        found = zip(table[:, 0], table[:, 1].astype(int), table[:, 2], table[:, 3], strict=True)
    out: list[tuple[np.ndarray, float]] = []
    for score, a, oy, ox in found:
        pose = np.array([guess[0] + ox * res, guess[1] + oy * res, wrap_angle(angles[a])])
        if all(
            math.hypot(*(pose[:2] - o[:2])) > 2 * cfg.coarse_step_m
            or abs(wrap_angle(pose[2] - o[2])) > 3 * cfg.angle_step_rad
            for o, _ in out
        ):
            out.append((pose, float(score)))
            if len(out) >= count:
                break
    return out


def match(
    ref: Reference,
    query: np.ndarray,
    guess: np.ndarray,
    window_xy: float = 0.0,
    window_theta: float = 0.0,
    config: ScanMatchConfig | None = None,
    candidates: int | None = None,
) -> MatchResult:
    """Pose of the query frame in the reference frame: correlative search within the
    window around `guess` (skipped when both windows are 0), ICP from its best distinct
    poses (`candidates` of them, default the config's refine_candidates), the refined
    pose with the most inliers (see the module docstring)."""
    cfg = config or ref.config
    guess = np.asarray(guess, dtype=float)
    query = _points(query)
    if len(query) < cfg.min_points or len(ref) < cfg.min_points:
        return MatchResult(guess, np.full((3, 3), np.nan), 0.0, 0, len(query), math.nan, 0, False)
    if window_xy <= 0 and window_theta <= 0:
        starts = [(guess, math.nan)]
    else:
        starts = correlative_search(ref, query, guess, window_xy, window_theta, cfg, candidates)
    results = [(icp(ref, query, s, cfg), score) for s, score in starts]
    results.sort(
        key=lambda rs: (rs[0].support, -np.nan_to_num(rs[0].rmse_m, nan=1e9)), reverse=True
    )
    best, score = results[0]
    ambiguity = 0.0
    if best.support > 0 and np.all(np.isfinite(best.covariance)):
        info = inv(best.covariance)
        for other, _ in results[1:]:
            d = other.pose - best.pose
            d[2] = wrap_angle(d[2])
            distinct = dot(d, matvec(info, d)) > 9.0 and (
                math.hypot(d[0], d[1]) > 2 * cfg.coarse_step_m or abs(d[2]) > 3 * cfg.angle_step_rad
            )
            if other.converged and distinct:
                ambiguity = max(ambiguity, other.support / best.support)
    return replace(best, score=score, ambiguity=ambiguity)


def relative_guess(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of b in frame a (a⁻¹ ⊕ b), for an initial guess from two world poses."""
    c, s = math.cos(a[2]), math.sin(a[2])
    d = np.asarray(b[:2], float) - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(b[2] - a[2])])


def place(poses: np.ndarray, scans: list[Scan], frame: np.ndarray) -> list[Scan]:
    """Scans (each in its own frame, at world pose poses[i]) expressed in the frame at
    world pose `frame`: a local submap for `Reference`."""
    return [sc.moved(relative_guess(frame, p)) for p, sc in zip(poses, scans, strict=True)]
