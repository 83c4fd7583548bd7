"""Data association for landmark observations without IDs (ID −1: trees in a laser scan,
corners extracted from one, a misread tag), shared by the landmark localizers.

A localizer that sees n observations at one time and has m landmarks in its map gives
each observation i and landmark j the innovation ν_ij = z_i − h(x, l_j) (bearing wrapped)
and its covariance S_ij; from those:

- **individual compatibility**: (i, j) is a candidate when ν_ijᵀ S_ij⁻¹ ν_ij is within
  the χ²(2) quantile `gate_prob`;
- **nearest neighbour** (`method="nn"`): the candidate pairs taken greedily in order of
  their Mahalanobis distance, each observation and each landmark at most once;
- **joint compatibility branch and bound** (`method="jcbb"`, Neira & Tardós 2001): the
  hypothesis (a landmark or none for every observation) with the most pairings whose
  stacked innovation passes the χ²(2k) quantile `gate_prob` under its *joint* covariance
  (a localizer's `joint_covariance(pairs)`: in EKF-SLAM H P Hᵀ + R over the pose and the
  landmarks involved, so the common error of the pose is counted once), the smallest
  joint distance among equals. Pairs that each fit alone but not together — clutter next
  to a landmark, a row of similar landmarks seen through a heading error — are told
  apart. The search visits at most `max_nodes` hypotheses (then the best so far is kept,
  counted by the caller).

An observation left without a landmark is either new — its Mahalanobis distance to every
landmark beyond the χ²(2) quantile `new_prob` — or ambiguous (dropped, counted). A new
one is **provisional** (`Provisional`): a world point with its covariance, not yet in
the map; an observation of the next times that falls within the gate of a provisional
point is another sighting of it; after `confirm_sightings` sightings it becomes a map
landmark, and one not confirmed within `provisional_max_age_s` is dropped (clutter, a
false detection, a passing person). The IDs of landmarks found this way count up from
FIRST_ASSOCIATED_ID, so that they never collide with known ones. `Discovery` is that
step for a localizer: new or ambiguous, provisional, confirmed with an ID.

**Inflation.** EKF-SLAM's joint covariance holds the error between the pose and a map
landmark; FastSLAM's does not (a particle's landmarks are conditioned on its one path,
and the paths that would cover the drift since a landmark was last seen are resampled
away: after a loop they are centimetres sure and decimetres off), nor does gtsam's (it
pairs on the current estimate, without marginals). Their gates divide the squared
Mahalanobis distance to a map landmark by `inflation` (4: the covariance taken twice
as wide in σ), which scales with the sensor and the map as they are: a metric allowance
(a metre, as first tried) served a park's trees tens of metres apart and paired a maze's
corners a metre apart wrongly (BENCHMARKS.md, issue 14). Provisional landmarks, seen
seconds ago, are gated as they are.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hardware.choices import Choice, coerce
from slam.kernel_math import greedy_pairs
from slam.measurement import chi2_quantile

FIRST_ASSOCIATED_ID = 1_000_000

Pair = tuple[int, int]  # (observation index, landmark index)


class AssociationMethod(Choice):
    """How observations without IDs are paired with landmarks (module docstring)."""

    NN = "nn"
    JCBB = "jcbb"


@dataclass(frozen=True)
class AssociationConfig:
    """Data association for observations without IDs (module docstring): method "jcbb"
    or "nn"; gate_prob: the individual and joint χ² quantile; new_prob: an unpaired
    observation farther than this χ²(2) quantile from every landmark is new (else
    ambiguous, dropped); confirm_sightings / provisional_max_age_s: when a provisional
    landmark joins the map or is dropped; max_nodes: JCBB's search budget per time;
    inflation: FastSLAM's and gtsam's gates to map landmarks (module docstring)."""

    method: AssociationMethod = AssociationMethod.JCBB
    gate_prob: float = 0.99
    new_prob: float = 0.9999
    confirm_sightings: int = 2
    provisional_max_age_s: float = 5.0
    max_nodes: int = 20_000
    inflation: float = 4.0

    def __post_init__(self) -> None:
        coerce(self, method=AssociationMethod)
        if not (0.0 < self.gate_prob < 1.0 and self.gate_prob <= self.new_prob < 1.0):
            raise ValueError(
                f"need 0 < gate_prob <= new_prob < 1, got {self.gate_prob}, {self.new_prob}"
            )
        if not self.inflation >= 1.0:
            raise ValueError(f"inflation must be >= 1, got {self.inflation}")
        if self.confirm_sightings < 1 or self.provisional_max_age_s < 0 or self.max_nodes < 1:
            raise ValueError(
                "confirm_sightings and max_nodes must be >= 1, provisional_max_age_s >= 0"
            )

    def gate(self, dof: int = 2) -> float:
        """The squared-Mahalanobis threshold for `dof` stacked dimensions."""
        return chi2_quantile(self.gate_prob, dof)

    def new_threshold(self) -> float:
        return chi2_quantile(self.new_prob, 2)


# 99.9 % quantiles of χ² with 2 and 3 degrees of freedom: the known-ID sighting gates
# of FastSLAM and gtsam.
CHI2_999 = {dof: chi2_quantile(0.999, dof) for dof in (2, 3)}


def mahalanobis2(nu: np.ndarray, s: np.ndarray) -> np.ndarray:
    """νᵀ S⁻¹ ν for stacks of 2-vectors (..., 2) and 2×2 matrices (..., 2, 2)."""
    a, b = s[..., 0, 0], s[..., 0, 1]
    c, d = s[..., 1, 0], s[..., 1, 1]
    det = a * d - b * c
    x, y = nu[..., 0], nu[..., 1]
    return (d * x * x - (b + c) * x * y + a * y * y) / det


def nearest_neighbour(d2: np.ndarray, gate: float) -> np.ndarray:
    """Greedy nearest neighbour on the (n, m) squared Mahalanobis distances: the pairs
    within `gate` in increasing distance, each observation and landmark used once.
    Returns the landmark of each observation (−1: none)."""
    n, m = d2.shape
    out = np.full(n, -1, dtype=np.int64)
    if d2.size:
        greedy_pairs(np.asarray(d2, dtype=float), float(gate), out, np.empty(m, dtype=bool))
    return out


@dataclass
class JcbbResult:
    """The hypothesis JCBB found: the landmark of each observation (−1: none), its joint
    squared Mahalanobis distance, the hypotheses visited and whether the budget ran out."""

    assignment: np.ndarray
    d2: float
    nodes: int
    exhausted: bool


def jcbb(
    d2: np.ndarray,
    nu: np.ndarray,
    joint_covariance: Callable[[Sequence[Pair]], np.ndarray],
    config: AssociationConfig,
) -> JcbbResult:
    """Joint compatibility branch and bound (module docstring). d2: (n, m) individual
    squared Mahalanobis distances; nu: (n, m, 2) innovations; joint_covariance(pairs):
    the (2k, 2k) covariance of the stacked innovations of the pairs, in their order."""
    n = d2.shape[0]
    gate = config.gate()
    candidates = [
        [int(j) for j in np.argsort(d2[i], kind="stable") if d2[i, j] <= gate] for i in range(n)
    ]
    best = JcbbResult(np.full(n, -1, dtype=int), 0.0, 0, False)
    best_pairs = 0
    current = np.full(n, -1, dtype=int)
    pairs: list[Pair] = []
    nodes = 0

    def joint_d2(trial: list[Pair]) -> float:
        v = np.concatenate([nu[i, j] for i, j in trial])
        s = joint_covariance(trial)
        try:
            return float(v @ np.linalg.solve(s, v))
        except np.linalg.LinAlgError:
            return math.inf

    def search(i: int, d2_now: float) -> None:
        nonlocal best, best_pairs, nodes
        if nodes >= config.max_nodes:
            best.exhausted = True
            return
        nodes += 1
        if i == n:
            k = len(pairs)
            if k > best_pairs or (k == best_pairs and d2_now < best.d2):
                best = JcbbResult(current.copy(), d2_now, nodes, best.exhausted)
                best_pairs = k
            return
        used = {j for _, j in pairs}
        for j in candidates[i]:
            if j in used:
                continue
            pairs.append((i, j))
            d = joint_d2(pairs)
            if d <= config.gate(2 * len(pairs)):
                current[i] = j
                search(i + 1, d)
                current[i] = -1
            pairs.pop()
        # the star branch (no landmark for i): only while it can still tie the best
        if len(pairs) + (n - i - 1) >= best_pairs:
            search(i + 1, d2_now)

    search(0, 0.0)
    best.nodes = nodes
    return best


@dataclass
class _Candidate:
    mean: np.ndarray  # (2,) world
    cov: np.ndarray  # (2, 2)
    sightings: int
    first_t: float


class Provisional:
    """Landmarks seen but not yet in the map (module docstring)."""

    def __init__(self, config: AssociationConfig) -> None:
        self.config = config
        self._items: list[_Candidate] = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def observe(self, t: float, points: np.ndarray, covs: np.ndarray) -> list[int]:
        """New observations at time t, as world points (k, 2) with covariances (k, 2, 2):
        each is another sighting of the provisional landmark whose gate it falls in
        (nearest first, one observation each) or starts one. Returns the indices of the
        observations that confirmed theirs (removed from here: the caller puts them in
        its map); unconfirmed ones older than provisional_max_age_s are dropped first."""
        c = self.config
        keep = [p for p in self._items if t - p.first_t <= c.provisional_max_age_s]
        self.dropped += len(self._items) - len(keep)
        self._items = keep
        k = len(points)
        match = np.full(k, -1, dtype=int)
        if k and self._items:
            means = np.array([p.mean for p in self._items])
            pcovs = np.array([p.cov for p in self._items])
            diff = points[:, None, :] - means[None, :, :]
            match = nearest_neighbour(mahalanobis2(diff, covs[:, None] + pcovs[None, :]), c.gate())
        confirmed: list[int] = []
        done: set[int] = set()
        new: list[_Candidate] = []
        for i in range(k):
            j = int(match[i])
            if j < 0:
                if c.confirm_sightings <= 1:
                    confirmed.append(i)
                else:
                    new.append(_Candidate(points[i].copy(), covs[i].copy(), 1, t))
                continue
            p = self._items[j]
            # the product of the two Gaussians: the point seen again
            info_p, info_i = np.linalg.inv(p.cov), np.linalg.inv(covs[i])
            p.cov = np.linalg.inv(info_p + info_i)
            p.mean = p.cov @ (info_p @ p.mean + info_i @ points[i])
            p.sightings += 1
            if p.sightings >= c.confirm_sightings:
                done.add(j)
                confirmed.append(i)
        self._items = [p for j, p in enumerate(self._items) if j not in done] + new
        return confirmed


class Discovery:
    """What becomes of the sightings a localizer could not pair (module docstring), the
    same for every localizer: a sighting farther than `new_prob` from every landmark is
    new and goes to the provisional landmarks, the others are ambiguous (dropped,
    counted); a confirmed provisional landmark takes the next ID from
    FIRST_ASSOCIATED_ID."""

    def __init__(self, config: AssociationConfig) -> None:
        self.config = config
        self.provisional = Provisional(config)
        self.next_id = FIRST_ASSOCIATED_ID
        self.ambiguous = 0

    def new(self, assignment: np.ndarray, d2_min: np.ndarray) -> np.ndarray:
        """Which of the sightings (their landmark, −1: none; their smallest squared
        Mahalanobis distance to any landmark) are new; the unpaired others are counted
        as ambiguous."""
        unpaired = assignment < 0
        new = unpaired & (d2_min > self.config.new_threshold())
        self.ambiguous += int(np.count_nonzero(unpaired & ~new))
        return new

    def confirm(self, t: float, points: np.ndarray, covs: np.ndarray) -> list[tuple[int, int]]:
        """New sightings at time t as world points (k, 2) with covariances (k, 2, 2), to
        the provisional landmarks (Provisional.observe): (index among them, new ID) of
        each that confirmed its landmark, for the caller to put in its map."""
        out = []
        for k in self.provisional.observe(t, points, covs):
            out.append((k, self.next_id))
            self.next_id += 1
        return out

    def diagnostics(self) -> dict[str, int]:
        return {
            "ambiguous": self.ambiguous,
            "provisional_pending": len(self.provisional),
            "provisional_dropped": self.provisional.dropped,
        }
