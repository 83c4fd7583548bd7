"""The scan half of the `gtsam` smoother: scans kept as keyframes, matched to the ones
before them, loop closures around the estimate and by place recognition, and a final
pass when the source ends. slam.gtsam_smoother.GtsamSmoother owns a `ScanGraph`, which
adds its factors to the smoother's graph, iSAM2 and keyframes; its settings are the smoother's
`scan` (SequentialScans) and `loop` (LoopClosures), and its counts appear in the
smoother's diagnostics.

Scan matching (`gtsam.scan_matching=True`, off by default). Laser scans (`LaserScan`, with
the laser's mount `laser_offset` on the walker) and depth frames (`DepthFrame`: the
obstacle band flattened to the floor, `mapping.depth_points`) become 2-D point sets in
the walker frame (`slam.scan_matching`), matched with `scan_match` (laser) or
`depth_match` (depth frames: 2 cm points paired within 5 cm, where a laser's 30 cm
pairing pulls a depth frame's match onto the nearest other surface by several cm and
degrees; BENCHMARKS.md). A scan is kept when the walker has moved
`scan.keyframe_distance_m` or turned `scan.keyframe_angle_rad` (odometry) since the
last kept scan, or when the odometry since then has a gap (a motion it did not measure:
`slam.motion.Increment.unknown`); a keyframe then starts at the scan's own time, so each
kept scan sits exactly on its keyframe (one scan per keyframe, no odometry offset between
them). A gap's covariance (`noise.unknown_sigma`: a full turn) goes unscaled into the
odometry factor over it, and the next sequential match searches
`scan.gate.unknown_window` (3.5 m, a full turn; wider windows go through the two-level
search of `slam.scan_matching.correlative_search`) against the previous kept scan alone.
Each kept scan is matched

- sequentially against the previous `scan.submap_size` kept scans, placed in the frame
  of the previous one by the current estimate (a local submap), starting from the
  odometry and searching ± `scan.gate.window_sigmas` odometry standard deviations (clipped to
  `scan.gate.window_xy_m`, `scan.gate.window_theta_rad`) → `BetweenFactorPose2` previous → current
  with the match's covariance (robust: `scan.gate.robust`, `scan.gate.robust_k`), in addition to
  the odometry factors; accepted when its inlier fraction ≥ `scan.gate.min_inlier_fraction`,
  conflict fraction ≤ `scan.gate.max_conflict_fraction` and ambiguity ≤
  `scan.gate.max_ambiguity` (`slam.scan_matching.MatchResult`); a rejected one is counted
  in the diagnostics by each test it fails (`scan_rejected_conflict`, ...:
  slam.scan_matching.REJECTIONS; outdoors on freiburg-campus most fail the conflict test);
- for loop closures against older kept scans (at least `loop.min_separation` kept scans
  back) within `loop.search_radius_m` plus the search window of the current estimate.
  The `loop.max_candidates` nearest (one per stretch of neighbouring scans) are tried,
  each against a submap of 2·`loop.submap_half` + 1 scans: the candidate and, of the
  scans within ± `loop.submap_span` of it, those that saw most of what the new scan sees
  (slam.scan_overlap: the share of its 1 m cells they cover, at the estimate; on a
  revisit driven the other way the scans that faced the same walls, where the
  candidate's neighbours faced the other way); searching ± `loop.gate.window_sigmas`
  standard deviations of the *relative* pose
  (from iSAM2's joint marginal of the two keyframes; clipped to `loop.gate.window_xy_m`,
  `loop.gate.window_theta_rad`). A match that passes the `loop.gate` thresholds and whose
  disagreement with the estimate passes a chi-squared gate (`loop.gate_chi2` on the
  relative covariance plus the match's; 16.27 = 99.9 % for 3 degrees of freedom)
  becomes a `BetweenFactorPose2` with a robust noise model (`loop.gate.robust`,
  `loop.gate.robust_k`); after loop closures iSAM2 runs `loop.extra_updates` more updates.
  Besides them, the `loop.overlap_candidates` old scans that cover the most of the new
  scan's footprint (at least `loop.min_overlap`, within `loop.overlap_radius_m`) are
  matched the same way, wherever they stand; such a match only enters the graph with
  others that agree (slam.loop_consensus), as the estimate chose it by what it sees.
  Both are off by default (`loop.submap_span` = `loop.submap_half`,
  `loop.overlap_candidates` 0): on a hall driven there and back they close the way
  back (tests/slam/test_scan_overlap.py), but on the nine laser logs they were no
  better than the spread (BENCHMARKS.md, "Laser logs: loop submaps of the scans that
  saw the same walls");
- for loop closures found by place recognition (`loop.place`, laser scans), when the
  position is too uncertain for that search (its window clipped at its largest): the
  old kept scans whose polar keys (slam.place_recognition: the returns within 80 m in
  range rings × bearing sectors, compared at the best turn) are most like the new
  scan's are matched around their own poses (± 3 m, a full turn), and an accepted
  match is verified by fitting the new scan's last few kept scans to the candidate's
  wider neighbourhood before it becomes a factor. On freiburg-campus, an outdoor loop
  whose drift reaches 60 m before its first revisit, this took ATE from 45 m to 1.7 m,
  and with polar keys (and no loop search beyond `loop.max_search_uncertainty_m`) to
  0.55 m (BENCHMARKS.md).
- and, when the source has ended (`finish`: the pipeline calls it after a log's last
  message and when a live run stops), in a final pass (`loop.final`) against the old
  kept scans that cover the most of each kept scan's footprint, placed by the final
  estimate and searched only a narrow window around it: a hall seen again from a few
  metres away, beyond the loop search's radius, is tied to where it was seen first
  (lanes driven up and down a hall: 0.163 → 0.023 m unaligned in
  tests/slam/test_scan_overlap.py; on the laser logs BENCHMARKS.md, "Laser logs: a
  final pass over the scans that saw the same walls").

Huber is the default robust kernel for both kinds: it is convex, so a correct loop
closure whose residual is large at first (the drift it corrects is many of its own
standard deviations) still pulls with a bounded force and closes the loop over the
next updates, whereas a redescending kernel (Cauchy) would all but ignore it in an
incremental solver; wrong matches are kept out mainly by the verification and the gate.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from hardware.calibration import WalkerCalibration
from hardware.choices import coerce
from hardware.geometry import compose, rotation, wrap_angle
from hardware.messages import DepthFrame, LaserScan
from hardware.small_linalg import congruence, dot, eigh2, solve
from slam.gtsam_factors import RobustKernel, robust_noise
from slam.loop_consensus import HeldMatch, HeldMatches, LoopConsensus, correction
from slam.motion import carry_increment
from slam.place_recognition import PlaceKeys, polar_key
from slam.scan_matching import (
    REJECTIONS,
    Acceptance,
    MatchResult,
    Reference,
    Scan,
    depth_points,
    laser_points,
    match,
    place,
    relative_guess,
)
from slam.scan_overlap import chosen_by_overlap, footprint, overlap


@dataclass(frozen=True)
class MatchGate(Acceptance):
    """How a scan match is searched for and accepted (module docstring): searched ±
    window_sigmas standard deviations of the prior (odometry, or the joint marginal for a
    loop), clipped to window_xy_m and window_theta_rad (min, max); accepted at the
    thresholds of slam.scan_matching.Acceptance; its factor robust with `robust`
    ("huber", "cauchy", "none") at robust_k."""

    window_sigmas: float = 3.0
    window_xy_m: tuple[float, float] = (0.1, 0.5)
    window_theta_rad: tuple[float, float] = (0.05, 0.35)
    robust: RobustKernel = RobustKernel.HUBER
    robust_k: float = 1.345

    def __post_init__(self) -> None:
        coerce(self, robust=RobustKernel)


@dataclass(frozen=True)
class SequentialGate(MatchGate):
    """A sequential match's MatchGate, and its search across an odometry gap.
    unknown_window (xy m, θ rad): the search window instead when the odometry did not
    measure part of the motion since the last kept scan (a gap:
    slam.motion.Increment.unknown): 3.5 m, chosen on orebro, the one log made of gaps
    (its scans are up to 3.3 m apart; 1 m until 2026-12-05: BENCHMARKS.md), held out on
    seattle's one gap. unknown_candidates: the correlative search's best poses that ICP
    refines in such a window (the matcher's refine_candidates elsewhere): over a few
    metres the coarse score ranks a corridor's wrong stretch above the right pose
    (seattle's gap at a 0.045 m voxel: the right one seventh), ICP tells them apart."""

    unknown_window: tuple[float, float] = (3.5, math.pi)
    unknown_candidates: int = 10

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.unknown_candidates < 1:
            raise ValueError(f"unknown_candidates must be >= 1, got {self.unknown_candidates}")


@dataclass(frozen=True)
class SequentialScans:
    """Sequential scan matching: max_range_m / min_range_m: laser returns used as points
    (SICK LMS: reliable to ~20 m; the walker's own frame can be cut with a minimum);
    keyframe_distance_m / keyframe_angle_rad: when a scan is kept; submap_size: the
    kept scans a new one is matched to (10, chosen on the edmonton, acapulco, fhw and
    csail logs against GMapping's poses, from 3, 10, 20: 3 let edmonton and acapulco
    drift by metres; checked on freiburg-101, seattle, belgioioso and Intel, which it
    improves or keeps: BENCHMARKS.md); across an odometry gap the previous kept scan
    alone (the older ones are placed relative to it only by earlier gap matches, each a
    guess of a full-turn search: on orebro 231 of 236 sequential matches right against
    the previous scan alone, 190 against ten); gate: the match's search and acceptance."""

    max_range_m: float = 20.0
    min_range_m: float = 0.0
    keyframe_distance_m: float = 0.3
    keyframe_angle_rad: float = 0.2
    submap_size: int = 10
    gate: SequentialGate = field(default_factory=SequentialGate)

    def __post_init__(self) -> None:
        if self.submap_size < 1:
            raise ValueError(f"submap_size must be >= 1, got {self.submap_size}")


@dataclass(frozen=True)
class PlaceRecognition:
    """Loop closures found by place recognition (slam.place_recognition), for laser
    scans, when the position is too uncertain for the search around the estimate (the
    loop search's window clipped at its largest): every `every` kept scans, the
    `candidates` old kept scans with the most similar polar keys (`rings` × `sectors`
    bins of the returns within `range_m`) that lie at least `min_path_m` back along the
    path are matched, searching ± window_m and a full turn around the candidate's own pose,
    through `gate`; a match it accepts is verified: the new scan's last `verify_scans`
    kept scans, placed by the estimate, must fit the candidate's ± `verify_half`
    neighbours from the found pose (ICP, the same gate) to within 0.2 m and 3°. An
    accepted one becomes a loop-closure factor, followed by `updates` iSAM2 updates (30:
    a robust factor pulls a revisit 120 m and 90° off back only slowly; the kidnapped
    walker of tests/slam/test_place_recognition.py was still 81° off after 10) —
    unless its heading is more than `heading_sigmas` standard deviations from the
    graph's (their joint marginal): such a match is held, and added only when a place
    match of a later search (within `doubt_searches` searches) moves the newest scan to
    within 0.2 m and 3° of where it does. A corridor matched the wrong way round fits,
    and verifies, as well as the right way (csail, 2026-12-05: a match 180° and 7.5 m
    off, 178° from the graph's heading at σ 1.8–7°, took the ATE from 0.14 to 7–17 m);
    but odometry that slipped through an unseen turn is what place recognition is for
    (that kidnapped walker turned 90° where the graph's σ is 17°), so the full turn is
    still searched and a second match decides.
    Chosen on freiburg-campus (BENCHMARKS.md): with the gate's inlier fraction 0.7 and
    constraint 0.1, 45 of 45 matches accepted from the three nearest keys were right
    (0.5 and 0: 63 of 65; measured with the ring keys that polar keys replaced)."""

    enabled: bool = True
    every: int = 10
    candidates: int = 3
    min_path_m: float = 20.0
    window_m: float = 3.0
    rings: int = 20
    sectors: int = 72
    range_m: float = 80.0
    verify_scans: int = 5
    verify_half: int = 5
    heading_sigmas: float = 3.0
    doubt_searches: int = 3
    gate: MatchGate = field(
        default_factory=lambda: MatchGate(
            min_inlier_fraction=0.7, max_conflict_fraction=0.1, min_constraint=0.1
        )
    )
    updates: int = 30

    def __post_init__(self) -> None:
        for name in ("every", "candidates", "rings", "sectors", "verify_scans"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (self.window_m > 0 and self.range_m > 0):
            raise ValueError("window_m and range_m must be > 0")
        if not (self.heading_sigmas > 0 and self.doubt_searches >= 1):
            raise ValueError("need heading_sigmas > 0 and doubt_searches >= 1")


FINAL_SUBMAPS = 16  # a final pass's submaps kept for the next scans (~11 MB each at 20 m)


@dataclass(frozen=True)
class FinalPass:
    """When the source has ended (`GtsamSmoother.finish`): every kept scan is matched
    again against the `candidates` older kept scans (at least loop.min_separation back,
    one per stretch of neighbouring scans) that cover the most of its footprint (at
    least loop.min_overlap, within loop.overlap_radius_m; slam.scan_overlap), each with
    its ± loop.submap_half neighbours as the submap, placed by the final estimate and
    searched only ± window_xy_m and ± window_theta_rad around it; a match `gate` accepts
    becomes a loop-closure factor (robust as loop.gate says), and iSAM2 runs `updates`
    updates. Repeated `passes` times (a pair once matched is not matched again; 0: no
    final pass). By the end the estimate is good, so the window is narrow and a match
    cannot jump to a look-alike, and the scans of a hall seen again from a few metres
    away — lanes driven up and down it, beyond the loop search's radius — are tied to
    each other (BENCHMARKS.md, "Laser logs: a final pass over the scans that saw the
    same walls"). Laser scans only: on the walker's depth frames (a 57° view a few
    metres deep, whose 1 m footprints overlap by chance) it made the thesis course's
    demo trial worse, 0.177 → 0.269 m ATE with `scan_matching` on."""

    passes: int = 2
    candidates: int = 2
    window_xy_m: float = 0.3
    window_theta_rad: float = 0.05
    gate: Acceptance = field(
        default_factory=lambda: Acceptance(min_inlier_fraction=0.4, max_conflict_fraction=0.1)
    )
    updates: int = 5

    def __post_init__(self) -> None:
        if self.passes < 0 or self.candidates < 1 or self.updates < 1:
            raise ValueError(
                "need passes >= 0, candidates >= 1 and updates >= 1, got "
                f"{self.passes}, {self.candidates}, {self.updates}"
            )
        if not (self.window_xy_m >= 0 and self.window_theta_rad >= 0):
            raise ValueError("window_xy_m and window_theta_rad must be >= 0")


@dataclass(frozen=True)
class LoopClosures:
    """Loop closures: enabled; a candidate is a kept scan within search_radius_m (plus
    the search window) at least min_separation keyframes back, at most max_candidates
    per scan, and besides them up to overlap_candidates old scans that cover at least
    min_overlap of the new scan's footprint (its overlap_cell_m cells, at the estimate;
    slam.scan_overlap; old scans within overlap_radius_m). Each is matched to a submap of
    2·submap_half + 1 scans: the candidate and, of the scans within ± submap_span of it,
    those that cover most of the new scan's footprint (submap_span = submap_half: its
    neighbours), through `gate`, and
    kept when its disagreement with the estimate passes gate_chi2 (0: no gate); a
    candidate is not searched at all while its relative position is uncertain beyond
    max_search_uncertainty_m (gate.window_sigmas σ): the window, at most
    gate.window_xy_m, would cover too little of where the scan may be, and a look-alike
    there is likelier than the place (freiburg-campus, 2026-12-05: a loop 51 m off at 3 σ
    = 64 m took the ATE to 26 m; the right ones on csail and acapulco were searched at
    3 σ ≤ 4.8 m): place recognition, which verifies and doubts, searches then. After
    loop closures iSAM2 runs extra_updates more updates; place: loops found by place
    recognition when the position is too uncertain for this search; consensus: matches
    both gates turn away, and those of overlap candidates, added together when several
    agree (slam.loop_consensus)."""

    enabled: bool = True
    search_radius_m: float = 2.0
    min_separation: int = 10
    max_candidates: int = 3
    submap_half: int = 2
    submap_span: int = 2
    overlap_candidates: int = 0
    min_overlap: float = 0.3
    overlap_cell_m: float = 1.0
    overlap_radius_m: float = 20.0
    gate: MatchGate = field(
        default_factory=lambda: MatchGate(
            window_xy_m=(0.3, 1.5),
            window_theta_rad=(0.1, 0.5),
            min_inlier_fraction=0.5,
            max_conflict_fraction=0.1,
        )
    )
    gate_chi2: float = 16.27
    max_search_uncertainty_m: float = 10.0
    extra_updates: int = 2
    place: PlaceRecognition = field(default_factory=PlaceRecognition)
    consensus: LoopConsensus = field(default_factory=LoopConsensus)
    final: FinalPass = field(default_factory=FinalPass)

    @property
    def by_overlap(self) -> bool:
        """Whether the loop search chooses submaps or candidates by overlap."""
        return self.submap_span > self.submap_half or self.overlap_candidates > 0

    def __post_init__(self) -> None:
        if self.min_separation < 1:
            raise ValueError(f"min_separation must be >= 1, got {self.min_separation}")
        if not 0 <= self.submap_half <= self.submap_span:
            raise ValueError(
                f"need 0 <= submap_half <= submap_span, got {self.submap_half}, {self.submap_span}"
            )
        if self.overlap_candidates < 0:
            raise ValueError(f"overlap_candidates must be >= 0, got {self.overlap_candidates}")
        if not self.max_search_uncertainty_m > 0:
            raise ValueError(
                f"max_search_uncertainty_m must be > 0, got {self.max_search_uncertainty_m}"
            )
        if not 0 <= self.min_overlap <= 1:
            raise ValueError(f"min_overlap must be in [0, 1], got {self.min_overlap}")
        if not (self.overlap_cell_m > 0 and self.overlap_radius_m > 0):
            raise ValueError("overlap_cell_m and overlap_radius_m must be > 0")


@dataclass(eq=False)
class _ScanKeyframe:
    """A kept scan: its keyframe index, time and points (walker frame)."""

    kf: int
    t: float
    scan: Scan
    place: int = -1  # its polar key's row in the smoother's PlaceKeys (laser scans), or -1
    cells: np.ndarray | None = None  # footprint (slam.scan_overlap)


def body_covariance(cov: np.ndarray, theta: float) -> np.ndarray:
    """The covariance of a match (x, y in the reference frame, θ) in the Pose2 tangent
    space (x, y in the matched pose's own frame, θ), as BetweenFactorPose2 expects."""
    out = congruence(rotation(theta, 3).T, cov)
    return 0.5 * (out + out.T)


def _places_agree(d: np.ndarray) -> bool:
    """Whether two placements of one scan differ by at most 0.2 m and 3° (d: the one in
    the other's frame): a place match's verification, and a held one's confirmation
    (PlaceRecognition)."""
    return math.hypot(d[0], d[1]) <= 0.2 and abs(d[2]) <= math.radians(3.0)


class KeyframeGraph(Protocol):
    """What ScanGraph uses of its smoother (slam.gtsam_smoother.GtsamSmoother): the
    keyframes, the graph and iSAM2 behind them, and the odometry's noise."""

    config: Any  # GtsamConfig: scan, loop, scan_match, depth_match, laser_offset, ...
    calibration: WalkerCalibration
    counts: dict

    @property
    def keyframe(self) -> int:
        """The latest keyframe's index (-1 before the first)."""

    @property
    def odometry_scale(self) -> np.ndarray:
        """The adaptive σ multipliers of the odometry (x, y, θ)."""

    def moved(self) -> bool:
        """Whether the walker moved since the latest keyframe (or may have)."""

    def new_keyframe(self, t: float, flush: bool = True) -> None:
        """A keyframe at t, at the odometry since the latest."""

    def poses(self) -> np.ndarray:
        """Every keyframe's current estimate (kf × 3)."""

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        """A factor for the next update."""

    def update(self, settle: int = 0) -> None:
        """The factors added since into iSAM2, then `settle` more iSAM2 updates."""

    def keyframe_covariance(self, k: int) -> np.ndarray:
        """Keyframe k's marginal covariance (body frame)."""

    def relative_covariance(self, a: int, b: int, rel: np.ndarray) -> np.ndarray:
        """Covariance of the relative pose a⁻¹·b."""

    def adapt_odometry(self, odo: np.ndarray, model: np.ndarray, res: MatchResult) -> None:
        """An accepted sequential match's say on the odometry's noise."""


class ScanGraph:
    """The scan half of GtsamSmoother (module docstring): the smoother owns one
    (`GtsamSmoother.scans`), hands it the odometry (`integrate`, `unmeasured`), its scans
    (`add`) and the end of the source (`finish`). It keeps the scans, their keys and the
    odometry since the last kept scan, and adds its factors through the smoother's part
    for it (KeyframeGraph). Its counts go into the smoother's."""

    def __init__(self, smoother: KeyframeGraph) -> None:
        self.smoother = smoother
        self.config = c = smoother.config
        self.counts = smoother.counts
        self._scans: list[_ScanKeyframe] = []
        self._since_place = 0  # place searches wanted since the last one (_place_closure)
        self._places = PlaceKeys()  # the kept laser scans' polar keys
        # place matches held for a heading far from the graph's: (search, HeldMatch)
        self._place_doubts: list[tuple[int, HeldMatch]] = []
        self._turned_away = HeldMatches(c.loop.consensus)  # loop matches held
        self._scan_delta = np.zeros(3)  # odometry since the last kept scan, and its cov
        self._scan_cov = np.zeros((3, 3))
        self._scan_gap = False  # the odometry since the last kept scan has a gap
        self._scan_kf0 = 0  # the keyframe of the last kept scan
        self._final_matched: set[tuple[int, int]] = set()  # (old, new) kept scans
        self._matcher = c.scan_match  # depth_match once a depth frame is kept
        self._laser = True  # the kept frames are laser scans (the first one decides)
        if c.scan_matching:
            self.counts.update(
                scans_kept=0,
                scan_factors=0,
                scan_rejected=0,
                **{f"scan_rejected_{why}": 0 for why in REJECTIONS},
                loop_candidates=0,
                loop_closures=0,
                loop_rejected=0,
                loop_gated=0,
                loop_too_uncertain=0,
                loop_held=0,
                place_searches=0,
                place_candidates=0,
                place_closures=0,
                place_doubted=0,
                loop_consensus=0,
                final_candidates=0,
                final_matches=0,
                scan_matching_s=0.0,
            )

    def _scan_points(self, msg: LaserScan | DepthFrame) -> Scan:
        """The frame's points, thinned by its sensor's matcher settings (which the first
        kept frame's sensor chooses for the run)."""
        c = self.config
        if not self._scans:
            self._laser = isinstance(msg, LaserScan)
            self._matcher = c.scan_match if self._laser else c.depth_match
        voxel = self._matcher.voxel_m
        if isinstance(msg, LaserScan):
            return laser_points(msg, c.laser_offset, c.scan.max_range_m, c.scan.min_range_m, voxel)
        return depth_points(
            msg, self.smoother.calibration, voxel_m=voxel, min_range_m=c.scan.min_range_m
        )

    def integrate(self, ds: float, dth: float, q: np.ndarray, added: np.ndarray | None) -> None:
        """An odometry increment into the motion since the last kept scan, as the smoother
        carries its own (slam.motion.carry_increment)."""
        self._scan_delta, self._scan_cov, _, _ = carry_increment(
            self._scan_delta, self._scan_cov, ds, dth, q, added
        )

    def unmeasured(self) -> None:
        """A motion the odometry did not measure: the next sequential match searches
        scan.gate.unknown_window."""
        self._scan_gap = True

    def add(self, msg: LaserScan | DepthFrame) -> None:
        """A laser scan or depth frame: kept as a keyframe when the walker has moved
        enough since the last kept one, matched to those before it and for loop
        closures (module docstring)."""
        c = self.config
        if self.smoother.keyframe < 0:
            return
        if self._scans and not (
            math.hypot(self._scan_delta[0], self._scan_delta[1]) >= c.scan.keyframe_distance_m
            or abs(self._scan_delta[2]) >= c.scan.keyframe_angle_rad
            or self._scan_gap  # the odometry cannot tell whether it moved
        ):
            return
        t0 = time.perf_counter()
        pts = self._scan_points(msg)
        if len(pts) < self._matcher.min_points:
            self.counts["scan_matching_s"] += time.perf_counter() - t0
            return
        if self.smoother.moved():
            self.smoother.new_keyframe(msg.t)
        prev = self._scans[-1] if self._scans else None
        odo = (
            self._scan_delta,
            self._scan_cov,
            max(self.smoother.keyframe - self._scan_kf0, 1),
            self._scan_gap,
        )
        self._scan_gap = False
        row = -1
        if isinstance(msg, LaserScan) and c.loop.place.enabled:
            pl = c.loop.place
            row = self._places.add(polar_key(msg, pl.rings, pl.sectors, pl.range_m))
        cells = footprint(pts.points, c.loop.overlap_cell_m) if c.loop.by_overlap else None
        self._scans.append(_ScanKeyframe(self.smoother.keyframe, msg.t, pts, row, cells))
        self._scan_delta = np.zeros(3)
        self._scan_cov = np.zeros((3, 3))
        self._scan_kf0 = self.smoother.keyframe
        self.counts["scans_kept"] += 1
        if prev is not None and prev.kf != self.smoother.keyframe:
            poses = self.smoother.poses()
            self._sequential(poses, *odo)
            if c.loop.enabled and len(self._scans) > c.loop.min_separation:
                self._loop_closures(self.smoother.poses())
        self.counts["scan_matching_s"] += time.perf_counter() - t0

    def _submap(self, poses: np.ndarray, indices: Sequence[int], frame_kf: int) -> Reference:
        scans = [self._scans[i] for i in indices]
        placed = place(poses[[s.kf for s in scans]], [s.scan for s in scans], poses[frame_kf])
        return Reference(placed, self._matcher)

    def _add_match(self, a: int, b: int, res: MatchResult, robust: str, k: float) -> None:
        cov = body_covariance(res.covariance, res.pose[2])
        noise = robust_noise(robust, k, gtsam.noiseModel.Gaussian.Covariance(cov))
        self.smoother.add_factor(
            gtsam.BetweenFactorPose2(X(a), X(b), gtsam.Pose2(*res.pose), noise)
        )

    def _sequential(
        self, poses: np.ndarray, odo: np.ndarray, odo_cov: np.ndarray, keyframes: int, gap: bool
    ) -> None:
        c = self.config
        n = len(self._scans)
        prev, cur = self._scans[-2], self._scans[-1]
        size = 1 if gap else c.scan.submap_size  # (SequentialScans)
        ref = self._submap(poses, range(max(0, n - 1 - size), n - 1), prev.kf)
        model = odo_cov + keyframes * np.diag(np.square(c.odometry_sigma_floor))
        sd = np.sqrt(np.maximum(np.diag(model), 0.0)) * self.smoother.odometry_scale
        wxy = float(
            np.clip(c.scan.gate.window_sigmas * max(sd[0], sd[1]), *c.scan.gate.window_xy_m)
        )
        wth = float(np.clip(c.scan.gate.window_sigmas * sd[2], *c.scan.gate.window_theta_rad))
        count = None
        if gap:
            wxy, wth = c.scan.gate.unknown_window
            count = c.scan.gate.unknown_candidates
        guess = relative_guess(poses[prev.kf], poses[cur.kf])
        res = match(ref, cur.scan, guess, wxy, wth, self._matcher, count)
        failed = c.scan.gate.failures(res)
        if not failed:
            self._add_match(prev.kf, cur.kf, res, c.scan.gate.robust, c.scan.gate.robust_k)
            self.counts["scan_factors"] += 1
            self.smoother.update()
            adapt = c.odometry_adaptive and not gap  # (a gap's odometry says nothing)
            if adapt and res.constraint >= self._matcher.degenerate_constraint:
                self.smoother.adapt_odometry(odo, model, res)
        else:
            self.counts["scan_rejected"] += 1
            for why in failed:
                self.counts[f"scan_rejected_{why}"] += 1

    def _loop_closures(self, poses: np.ndarray) -> None:
        """Match the newest kept scan against the nearest old ones; add the accepted
        matches as factors and update."""
        loop = self.config.loop
        here = poses[self._scans[-1].kf]
        marginal = self.smoother.keyframe_covariance(self._scans[-1].kf)
        sxy = math.sqrt(max(float(eigh2(marginal[:2, :2])[0][-1]), 0.0))
        chosen, dist = self._loop_candidates(poses, here, sxy)
        shares = self._overlaps(poses, len(self._scans) - 1, dist)
        by_overlap = self._overlap_candidates(shares, chosen, loop.overlap_candidates)
        added = sum(self._try_loop(poses, here, i, float(dist[i]), shares) for i in chosen)
        added += sum(self._try_loop(poses, here, i, None, shares) for i in by_overlap)
        if not added:  # those turned away may agree with the ones held before them
            for h in self._turned_away.consensus(len(self._scans) - 1, here):
                self._add_match(h.old_kf, h.new_kf, h.result, loop.gate.robust, loop.gate.robust_k)
                self.counts["loop_consensus"] += 1
                added += 1
        updates = loop.extra_updates
        if not added and loop.gate.window_sigmas * sxy > loop.gate.window_xy_m[1]:
            # the search above cannot reach where the scan may be: recognise the place
            added = self._place_closure(poses)
            updates = loop.place.updates
        if added:
            self._turned_away.clear()  # measured against an estimate about to move
            self.smoother.update(updates)

    def finish(self) -> None:
        """The source has ended: the final pass (loop.final) over the kept laser scans."""
        c = self.config
        if not (c.scan_matching and c.loop.enabled and self._laser):
            return  # (depth frames: FinalPass)
        if len(self._scans) <= c.loop.min_separation:
            return
        for sc in self._scans:  # the loop search made them only if it chose by overlap
            if sc.cells is None:
                sc.cells = footprint(sc.scan.points, c.loop.overlap_cell_m)
        for _ in range(c.loop.final.passes):
            if not self._final_pass():
                break

    def _final_pass(self) -> int:
        """Match every kept scan against the old ones that saw the most of what it sees,
        at the current estimate (FinalPass); add the accepted matches and update.
        Returns how many were added."""
        loop = self.config.loop
        final = loop.final
        poses = self.smoother.poses()
        kfs = np.array([sc.kf for sc in self._scans])

        @lru_cache(maxsize=FINAL_SUBMAPS)  # a candidate's submap serves the scans after it
        def submap(j: int, members: range) -> Reference:
            return self._submap(poses, members, self._scans[j].kf)

        added = 0
        for i in range(loop.min_separation + 1, len(self._scans)):
            cur = self._scans[i]
            old = kfs[: i - loop.min_separation]
            dist = np.hypot(*(poses[old, :2] - poses[cur.kf, :2]).T)
            shares = self._overlaps(poses, i, dist)
            for j in self._overlap_candidates(shares, [], final.candidates):
                if (j, i) in self._final_matched:
                    continue
                cand = self._scans[j]
                ref = submap(j, self._neighbours(j, loop.submap_half, i))
                guess = relative_guess(poses[cand.kf], poses[cur.kf])
                res = match(
                    ref, cur.scan, guess, final.window_xy_m, final.window_theta_rad, self._matcher
                )
                self.counts["final_candidates"] += 1
                if final.gate.accepts(res):
                    self._add_match(cand.kf, cur.kf, res, loop.gate.robust, loop.gate.robust_k)
                    self._final_matched.add((j, i))
                    added += 1
        self.counts["final_matches"] += added
        if added:
            self.smoother.update(final.updates)
        return added

    def _loop_candidates(
        self, poses: np.ndarray, here: np.ndarray, sxy: float
    ) -> tuple[list[int], np.ndarray]:
        """The kept scans to try (nearest first, one per submap, at most max_candidates):
        near enough for the absolute uncertainty sxy [m] (an upper bound of the relative
        one); with every old scan's distance."""
        loop = self.config.loop
        reach = loop.search_radius_m + min(loop.gate.window_sigmas * sxy, loop.gate.window_xy_m[1])
        old = np.arange(len(self._scans) - loop.min_separation)
        kfs = np.array([self._scans[i].kf for i in old])
        dist = np.hypot(*(poses[kfs, :2] - here[:2]).T)
        near = old[dist <= reach]
        chosen: list[int] = []
        for i in near[np.argsort(dist[near])].tolist():
            if all(abs(i - j) > 2 * loop.submap_half for j in chosen):
                chosen.append(i)
                if len(chosen) >= loop.max_candidates:
                    break
        return chosen, dist

    def _overlaps(self, poses: np.ndarray, i: int, dist: np.ndarray) -> np.ndarray:
        """Per old kept scan (dist's positions: their distances from kept scan i): the
        share of scan i's footprint it covers at the estimate; 0 beyond
        loop.overlap_radius_m."""
        loop = self.config.loop
        shares = np.zeros(len(dist))
        if self._scans[i].cells is None:
            return shares  # nothing asks for them
        near = np.flatnonzero(dist <= loop.overlap_radius_m)
        old = [self._scans[j] for j in near]
        cur = self._scans[i]
        shares[near] = overlap(
            poses[cur.kf], cur.cells, poses[[sc.kf for sc in old]].reshape(-1, 3),
            [sc.cells for sc in old], loop.overlap_cell_m,
        )  # fmt: skip
        return shares

    def _overlap_candidates(self, shares: np.ndarray, chosen: list[int], count: int) -> list[int]:
        """Up to `count` old scans that cover the most of a scan's footprint (at least
        loop.min_overlap), one per stretch of neighbouring scans, none in the stretch of
        a candidate already chosen."""
        loop = self.config.loop
        picked: list[int] = []
        for i in np.argsort(-shares, kind="stable").tolist():
            if len(picked) >= count or shares[i] < loop.min_overlap:
                break
            if all(abs(i - j) > 2 * loop.submap_half for j in chosen + picked):
                picked.append(i)
        return picked

    def _neighbours(self, i: int, half: int, newest: int | None = None) -> range:
        """Kept scan i and its `half` neighbours either side, none of the
        loop.min_separation before kept scan `newest` (default: the newest; a
        loop-closure candidate's submap)."""
        newest = len(self._scans) - 1 if newest is None else newest
        last = newest + 1 - self.config.loop.min_separation
        return range(max(0, i - half), min(last, i + half + 1))

    def _place_closure(self, poses: np.ndarray) -> bool:
        """Every place.every calls: try the old kept scans whose polar keys are most
        like the newest scan's (and at least place.min_path_m back along the path); True
        when one was added as a loop closure (PlaceRecognition)."""
        loop = self.config.loop
        pl = loop.place
        cur = self._scans[-1]
        if not pl.enabled or cur.place < 0 or not self._places.saw_anything(cur.place):
            return False
        self._since_place += 1
        if self._since_place < pl.every:
            return False
        self._since_place = 0
        self.counts["place_searches"] += 1
        kfs = np.array([sc.kf for sc in self._scans])
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[kfs, :2], axis=0).T))])
        old = [
            i
            for i in range(len(self._scans) - loop.min_separation)
            if self._scans[i].place >= 0 and along[-1] - along[i] >= pl.min_path_m
        ]
        if not old:
            return False
        rows = [self._scans[i].place for i in old]
        return any(
            self._try_place(poses, old[r])
            for r in self._places.nearest(rows, cur.place, pl.candidates)
        )

    def _try_place(self, poses: np.ndarray, i: int) -> bool:
        """Match the newest scan against kept scan i's submap around i's own pose (±
        place.window_m, a full turn), verify it with the newest scans' local map against
        i's wider neighbourhood, and add it if both pass place.gate."""
        loop = self.config.loop
        pl = loop.place
        cand, cur = self._scans[i], self._scans[-1]
        ref = self._submap(poses, self._neighbours(i, loop.submap_half), cand.kf)
        res = match(ref, cur.scan, np.zeros(3), pl.window_m, math.pi, self._matcher)
        self.counts["place_candidates"] += 1
        if not pl.gate.accepts(res):
            return False
        recent = self._scans[-pl.verify_scans :]
        local = place(poses[[sc.kf for sc in recent]], [sc.scan for sc in recent], poses[cur.kf])
        wide = self._submap(poses, self._neighbours(i, pl.verify_half), cand.kf)
        check = match(
            wide, np.concatenate([sc.points for sc in local]), res.pose, 0.0, 0.0, self._matcher
        )
        d = relative_guess(res.pose, check.pose)
        if not (pl.gate.accepts(check) and _places_agree(d)):
            return False
        agreeing = self._place_doubt(poses, i, res)
        if agreeing is None:
            return False
        for h in agreeing:
            self._add_match(h.old_kf, h.new_kf, h.result, pl.gate.robust, pl.gate.robust_k)
            self.counts["place_closures"] += 1
        self._add_match(cand.kf, cur.kf, res, pl.gate.robust, pl.gate.robust_k)
        self.counts["place_closures"] += 1
        return True

    def _place_doubt(self, poses: np.ndarray, i: int, res: MatchResult) -> list[HeldMatch] | None:
        """A verified place match of kept scan i: [] when its heading agrees with the
        graph's (within place.heading_sigmas), the held matches of earlier searches that
        agree with it when it does not (they are added with it), or None: held until a
        later search's match agrees (PlaceRecognition)."""
        pl = self.config.loop.place
        cand, cur = self._scans[i], self._scans[-1]
        here = poses[cur.kf]
        rel = relative_guess(poses[cand.kf], here)
        sth = math.sqrt(
            max(float(self.smoother.relative_covariance(cand.kf, cur.kf, rel)[2, 2]), 0.0)
        )
        if abs(wrap_angle(res.pose[2] - rel[2])) <= pl.heading_sigmas * sth:
            return []
        search = self.counts["place_searches"]
        self._place_doubts = [
            (k, h) for k, h in self._place_doubts if search - k <= pl.doubt_searches
        ]
        fix = correction(poses[cand.kf], res.pose, here)
        moved = compose(fix, here)
        agreeing, kept = [], []
        for k, h in self._place_doubts:
            d = relative_guess(moved, compose(h.correction, here))
            if k < search and _places_agree(d):
                agreeing.append(h)
            else:
                kept.append((k, h))
        if agreeing:
            self._place_doubts = kept
            return agreeing
        self._place_doubts.append(
            (search, HeldMatch(i, len(self._scans) - 1, cand.kf, cur.kf, res, fix))
        )
        self.counts["place_doubted"] += 1
        return None

    def _try_loop(
        self, poses: np.ndarray, here: np.ndarray, i: int, dist: float | None,
        shares: np.ndarray,
    ) -> bool:  # fmt: skip
        """Match the newest scan against kept scan i's submap (the scans near i that
        cover most of its footprint: `shares`), searched within ± window_sigmas of
        their relative uncertainty; add the factor if the gate accepts it (and the
        chi-squared gate, when on, finds it consistent). dist: how far i is, None for a
        candidate chosen by overlap (not by distance)."""
        loop = self.config.loop
        cand, cur = self._scans[i], self._scans[-1]
        guess = relative_guess(poses[cand.kf], here)
        rel_cov = self.smoother.relative_covariance(cand.kf, cur.kf, guess)
        sxy = math.sqrt(max(float(eigh2(rel_cov[:2, :2])[0][-1]), 0.0))
        sth = math.sqrt(max(float(rel_cov[2, 2]), 0.0))
        if loop.gate.window_sigmas * sxy > loop.max_search_uncertainty_m:
            self.counts["loop_too_uncertain"] += 1
            return False
        wxy = float(np.clip(loop.gate.window_sigmas * sxy, *loop.gate.window_xy_m))
        wth = float(np.clip(loop.gate.window_sigmas * sth, *loop.gate.window_theta_rad))
        if dist is not None and dist > loop.search_radius_m + wxy:
            return False
        span = self._neighbours(i, loop.submap_span)
        members = chosen_by_overlap(
            shares[span.start : span.stop], i - span.start, loop.submap_span,
            2 * loop.submap_half + 1,
        )  # fmt: skip
        ref = self._submap(poses, [span.start + m for m in members], cand.kf)
        res = match(ref, cur.scan, guess, wxy, wth, self._matcher)
        self.counts["loop_candidates"] += 1
        g = loop.gate
        ok = g.accepts(res)
        if ok and loop.gate_chi2 > 0:
            d = relative_guess(guess, res.pose)
            s_ = rel_cov + body_covariance(res.covariance, res.pose[2])
            ok = dot(d, solve(s_, d)) <= loop.gate_chi2
            if not ok:
                self.counts["loop_gated"] += 1
        if not ok or dist is None:
            # a candidate chosen by overlap lies where the estimate says its walls are,
            # not near the estimate: its match alone is not enough, only with others
            # that agree (slam.loop_consensus)
            self.counts["loop_rejected" if not ok else "loop_held"] += 1
            if loop.consensus.gate.accepts(res):
                fix = correction(poses[cand.kf], res.pose, here)
                held = HeldMatch(i, len(self._scans) - 1, cand.kf, cur.kf, res, fix)
                self._turned_away.hold(held)
            return False
        self._add_match(cand.kf, cur.kf, res, g.robust, g.robust_k)
        self.counts["loop_closures"] += 1
        return True
