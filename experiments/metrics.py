"""Accuracy metrics: trajectories against ground truth, maps against true obstacle outlines.

Plain functions on arrays; no plotting or printing (that is `experiments.report`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.path import Path as MplPath

from hardware.geometry import between
from hardware.messages import BrakeCommand, Collision
from slam.slip import slip_diagnostics
from slam.trajectory import Trajectory


@dataclass(frozen=True)
class TruthNames:
    """How the figures name a log's reference poses: ground truth, or what stands in
    for it (`truth_names`)."""

    path: str = "true path"  # its legend entry
    poses: str = "the true poses"  # "map from ..."
    against: str = "ground truth"  # "errors against ..."


GROUND_TRUTH = TruthNames()
# by the kind in a log's metadata "groundtruth" (hardware.datasets)
_STAND_INS = {
    "slam-corrected": TruthNames(
        "corrected path (SLAM output)", "the corrected poses",
        "the corrected poses (SLAM output, not ground truth)",
    ),
    "reference": TruthNames(
        "reference path", "the reference poses", "the reference poses (not ground truth)"
    ),
    "approximate": TruthNames(
        "true path (approximate)", "the approximate true poses", "approximate ground truth"
    ),
}  # fmt: skip


def truth_names(kind: str | None) -> TruthNames:
    """The names for reference poses of this kind (None: a simulation's exact poses)."""
    return _STAND_INS.get(kind or "", GROUND_TRUTH)


def groundtruth_kind(metadata: dict[str, Any]) -> str:
    """What a log's ground-truth poses are (metrics `groundtruth_kind`): its metadata
    "groundtruth" kind, or "simulated" (a simulation's exact poses, which say nothing)."""
    return str((metadata.get("groundtruth") or {}).get("kind", "simulated"))


COLLISION_KINDS = ("front", "side", "rear-wheel")


def associate(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Estimated poses interpolated at the ground-truth times inside the estimate's span.

    Returns (times, estimated poses, true poses).
    """
    if len(est) == 0 or len(gt) == 0:
        raise ValueError("cannot compare an empty trajectory")
    inside = (gt.t >= est.t[0]) & (gt.t <= est.t[-1])
    if not np.any(inside):
        raise ValueError("the estimate and the ground truth do not overlap in time")
    t = gt.t[inside]
    return t, est.interpolate(t), gt.poses[inside]


def align_se2(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (2×2) and translation t minimising Σ|R·src + t − dst|² (Kabsch, no scale)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    h = (src - mu_s).T @ (dst - mu_d)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return r, mu_d - r @ mu_s


def trajectory_alignment(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """The SE(2) alignment (R, t) of the estimate onto the ground truth used by `ate`."""
    _, e, g = associate(est, gt)
    return align_se2(e[:, :2], g[:, :2])


def ate(est: Trajectory, gt: Trajectory) -> dict[str, float]:
    """Absolute trajectory error (position RMSE), after SE(2) alignment and unaligned."""
    _, e, g = associate(est, gt)
    r, t = align_se2(e[:, :2], g[:, :2])
    aligned = e[:, :2] @ r.T + t
    return {
        "ate_rmse_m": float(np.sqrt(np.mean(np.sum((aligned - g[:, :2]) ** 2, axis=1)))),
        "ate_rmse_unaligned_m": float(np.sqrt(np.mean(np.sum((e[:, :2] - g[:, :2]) ** 2, axis=1)))),
        "final_position_error_m": float(np.hypot(*(e[-1, :2] - g[-1, :2]))),
    }


@dataclass(frozen=True)
class GpsScreen:
    """A GPS track screened for dropouts and jumps (`screen_gps`): which fixes are kept,
    and what was found."""

    kept: np.ndarray  # (n,) bool
    jumps: int  # fixes left out: they imply a speed above max_speed_mps
    dropouts: int  # gaps between consecutive fixes longer than max_gap_s
    dropout_s: float  # the time those gaps cover


def screen_gps(rows: np.ndarray, max_gap_s: float = 1.0, max_speed_mps: float = 10.0) -> GpsScreen:
    """GPS fixes (n, 3: t, x, y) in time order: a fix is a *jump* when reaching it from the
    last kept fix needs more than max_speed_mps (Victoria Park's car drives at most
    6.6 m/s by its odometry), and is left out; a *dropout* is a gap between consecutive
    fixes longer than max_gap_s (Victoria Park logs 5 fixes/s). Nothing is interpolated
    over either: the metrics use the kept fixes only, and report both counts."""
    rows = np.asarray(rows, dtype=float).reshape(-1, 3)
    kept = np.zeros(len(rows), dtype=bool)
    last = None
    for i, (t, x, y) in enumerate(rows):
        if last is not None:
            dt = t - last[0]
            if math.hypot(x - last[1], y - last[2]) > max_speed_mps * max(dt, 0.0):
                continue
        kept[i] = True
        last = (t, x, y)
    gaps = np.diff(rows[:, 0]) if len(rows) > 1 else np.empty(0)
    long = gaps > max_gap_s
    return GpsScreen(kept, int(len(rows) - kept.sum()), int(long.sum()), float(gaps[long].sum()))


@dataclass(frozen=True)
class GpsFit:
    """The GPS fixes within an estimate's time span, screened (`screen_gps`), and the SE(2)
    alignment (rotation, translation) of the estimate onto the kept ones (None when
    fewer than two are kept)."""

    fixes: np.ndarray  # (n, 3) t, x, y within the estimate's span
    screen: GpsScreen
    alignment: tuple[np.ndarray, np.ndarray] | None

    @property
    def kept(self) -> np.ndarray:
        return self.fixes[self.screen.kept]


def fit_gps(
    est: Trajectory, rows: np.ndarray, max_gap_s: float = 1.0, max_speed_mps: float = 10.0
) -> GpsFit:
    """The estimate against GPS fixes (n, 3: t, x, y): `GpsFit`."""
    rows = np.asarray(rows, dtype=float).reshape(-1, 3)
    inside = rows[(rows[:, 0] >= est.t[0]) & (rows[:, 0] <= est.t[-1])]
    screen = screen_gps(inside, max_gap_s, max_speed_mps)
    kept = inside[screen.kept]
    alignment = None
    if len(kept) >= 2:
        alignment = align_se2(est.interpolate(kept[:, 0])[:, :2], kept[:, 1:])
    return GpsFit(inside, screen, alignment)


def gps_errors(
    est: Trajectory, rows: np.ndarray, max_gap_s: float = 1.0, max_speed_mps: float = 10.0
) -> dict[str, float]:
    """Position errors of the estimate at the GPS fixes it spans (GPS has no heading, and
    its antenna's place on the vehicle may be unknown: position only), after `screen_gps`:
    RMSE after SE(2) alignment and unaligned, the aligned error's median, 90th percentile
    and maximum, and the fixes used, jumps left out and dropouts."""
    fit = fit_gps(est, rows, max_gap_s, max_speed_mps)
    fixes = fit.kept
    out = {
        "gps_fixes_used": len(fixes),
        "gps_jumps_left_out": fit.screen.jumps,
        "gps_dropouts": fit.screen.dropouts,
        "gps_dropout_s": fit.screen.dropout_s,
    }
    if fit.alignment is None:
        return {**out, "gps_rmse_m": math.nan, "gps_rmse_unaligned_m": math.nan}
    e = est.interpolate(fixes[:, 0])[:, :2]
    g = fixes[:, 1:]
    r, t = fit.alignment
    d = np.hypot(*(e @ r.T + t - g).T)
    out["gps_rmse_m"] = float(np.sqrt(np.mean(d * d)))
    out["gps_rmse_unaligned_m"] = float(np.sqrt(np.mean(np.sum((e - g) ** 2, axis=1))))
    out["gps_median_m"] = float(np.median(d))
    out["gps_p90_m"] = float(np.percentile(d, 90))
    out["gps_max_m"] = float(d.max())
    return out


def heading_errors(est: Trajectory, gt: Trajectory) -> dict[str, float]:
    """|θ_est − θ_true| (wrapped, unaligned: both start at the true start pose) at the
    ground-truth times: at the end, its maximum and median [deg]."""
    _, e, g = associate(est, gt)
    err = np.degrees(np.abs(np.remainder(e[:, 2] - g[:, 2] + np.pi, 2 * np.pi) - np.pi))
    return {
        "final_heading_error_deg": float(err[-1]),
        "heading_error_max_deg": float(err.max()),
        "heading_error_median_deg": float(np.median(err)),
    }


def rpe(est: Trajectory, gt: Trajectory, delta_s: float = 1.0) -> dict[str, float]:
    """Relative pose error over time steps of delta_s: RMSE of translation and rotation."""
    t, e, g = associate(est, gt)
    j = np.searchsorted(t, t + delta_s)
    ok = j < len(t)
    i, j = np.nonzero(ok)[0], j[ok]
    if len(i) == 0:
        return {"rpe_trans_m": math.nan, "rpe_rot_deg": math.nan}
    err = between(between(g[i], g[j]), between(e[i], e[j]))
    return {
        "rpe_trans_m": float(np.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))),
        "rpe_rot_deg": float(np.degrees(np.sqrt(np.mean(err[:, 2] ** 2)))),
    }


def distance_to_outlines(points: np.ndarray, polygons: Sequence[np.ndarray]) -> np.ndarray:
    """Distance from each point (N×2) to the nearest polygon (0 inside a polygon)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    best = np.full(len(pts), np.inf)
    if not polygons or len(pts) == 0:
        return best
    for poly in polygons:
        a = np.asarray(poly, float)
        b = np.roll(a, -1, axis=0)
        ab = b - a  # (S, 2)
        ap = pts[:, None, :] - a[None, :, :]  # (N, S, 2)
        u = np.clip(np.sum(ap * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0.0, 1.0)
        d = np.hypot(*(ap - u[..., None] * ab).transpose(2, 0, 1)).min(axis=1)
        d[MplPath(a).contains_points(pts)] = 0.0
        np.minimum(best, d, out=best)
    return best


def map_scores(
    occupied_xy: np.ndarray,
    cell_area_m2: float,
    polygons: Sequence[np.ndarray],
    tolerance_m: float = 0.1,
) -> dict[str, float]:
    """Map precision (share of occupied cells within tolerance of a true obstacle) and the
    phantom area (occupied area farther than tolerance from every obstacle: the dragging)."""
    n = len(occupied_xy)
    if n == 0:
        return {"map_precision": math.nan, "phantom_area_m2": 0.0, "occupied_area_m2": 0.0}
    d = distance_to_outlines(occupied_xy, polygons)
    phantom = int(np.count_nonzero(d > tolerance_m))
    return {
        "map_precision": float((n - phantom) / n),
        "phantom_area_m2": float(phantom * cell_area_m2),
        "occupied_area_m2": float(n * cell_area_m2),
    }


def collision_counts(collisions: Iterable[Collision]) -> dict[str, int]:
    counts = Counter(c.kind for c in collisions)
    out = {k: int(counts.get(k, 0)) for k in COLLISION_KINDS}
    out["total"] = sum(out.values())
    return out


def braking_impulse(commands: Sequence[BrakeCommand], torque_off_nm: float, t_end: float) -> float:
    """∫ (τ_L + τ_R − 2 τ_off) dt [N·m·s]: the braking applied above the brakes' residual
    drag, with each command held until the next (or t_end)."""
    if not commands:
        return 0.0
    t = np.array([c.t for c in commands] + [max(t_end, commands[-1].t)])
    tau = np.array([c.left_nm + c.right_nm - 2.0 * torque_off_nm for c in commands])
    return float(np.sum(np.maximum(tau, 0.0) * np.diff(t)))


def landmark_rmse(
    estimated: dict[int, np.ndarray],
    truth: dict[int, np.ndarray],
    alignment: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """RMSE of estimated landmark positions against the true ones (ids in both), in the
    map frame, or after `alignment` (R, t) — e.g. the trajectory's, from
    `trajectory_alignment`, so map and path are judged in the same frame."""
    common = sorted(set(estimated) & set(truth))
    if not common:
        return math.nan
    est = np.array([np.asarray(estimated[i], float) for i in common])
    if alignment is not None:
        est = est @ alignment[0].T + alignment[1]
    d = est - np.array([np.asarray(truth[i], float) for i in common])
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def slip_errors(k: np.ndarray, cov: np.ndarray, truth: dict[str, Any] | None) -> dict[str, Any]:
    """A slip estimate (k_left, k_right) with its σ, and, when the source knows the true
    slip (a simulated trial's metadata "slip"), the effective k it is judged against
    (hardware.sim.slip) and the relative error of each wheel (None for a wheel that was
    never braked)."""
    reported = slip_diagnostics(k, cov)
    out: dict[str, Any] = {"k": reported["slip_k"], "k_sigma": reported["slip_k_sigma"]}
    true_k = (truth or {}).get("k_effective")
    if true_k is not None:
        out["k_true_effective"] = true_k
        out["relative_error"] = [
            None if t is None or t == 0 else float(e / t - 1.0)
            for e, t in zip(out["k"], true_k, strict=True)
        ]
    return out


def relation_errors(est: Trajectory, relations: np.ndarray) -> dict[str, float]:
    """Kümmerle et al. (2009) relation metric: for each relation (t1, t2, x, y, yaw) — the
    true pose at t2 in the frame at t1 — the translational [m] and rotational [deg] error
    of the same relative pose from the estimate (interpolated at t1, t2); their mean and
    std (the published figures) and their distribution: median, 90th and 99th
    percentile, maximum. Relations outside the estimate's time span are left out
    (counted)."""
    rel = np.asarray(relations, dtype=float).reshape(-1, 5)
    inside = (rel[:, 0] >= est.t[0]) & (rel[:, 1] <= est.t[-1]) & (rel[:, 0] >= est.t[0])
    inside &= (rel[:, 1] >= est.t[0]) & (rel[:, 0] <= est.t[-1])
    r = rel[inside]
    out: dict[str, float] = {"relations_used": len(r), "relations_skipped": int(len(rel) - len(r))}
    if len(r):
        measured = between(est.interpolate(r[:, 0]), est.interpolate(r[:, 1]))
        err = between(r[:, 2:5], measured)
        errors = {"trans": (np.hypot(err[:, 0], err[:, 1]), "m")}
        errors["rot"] = (np.degrees(np.abs(err[:, 2])), "deg")
    else:
        errors = {"trans": (np.full(1, math.nan), "m"), "rot": (np.full(1, math.nan), "deg")}
    for name, (e, unit) in errors.items():
        out[f"relations_{name}_mean_{unit}"] = float(e.mean())
        out[f"relations_{name}_std_{unit}"] = float(e.std())
        for label, q in (("median", 50), ("p90", 90), ("p99", 99)):
            out[f"relations_{name}_{label}_{unit}"] = float(np.percentile(e, q))
        out[f"relations_{name}_max_{unit}"] = float(e.max())
    return out


def braking_impulse_per_wheel(
    commands: Sequence[BrakeCommand], torque_off_nm: float, t_end: float
) -> dict[str, float]:
    """∫ max(τ − τ_off, 0) dt [N·m·s] of each wheel and their sum, each command held until
    the next (or t_end): `braking_impulse` split by wheel."""
    if not commands:
        return {"left_nms": 0.0, "right_nms": 0.0, "total_nms": 0.0}
    dt = np.diff([c.t for c in commands] + [max(t_end, commands[-1].t)])
    left = np.maximum(np.array([c.left_nm for c in commands]) - torque_off_nm, 0.0)
    right = np.maximum(np.array([c.right_nm for c in commands]) - torque_off_nm, 0.0)
    out = {"left_nms": float(left @ dt), "right_nms": float(right @ dt)}
    out["total_nms"] = out["left_nms"] + out["right_nms"]
    return out


def braked_side(left_nm: np.ndarray, right_nm: np.ndarray, threshold_nm: float) -> np.ndarray:
    """+1 where the left brake exceeds the right by more than threshold (a left turn), −1
    where the right does, 0 otherwise (released, or both alike)."""
    diff = np.asarray(left_nm, float) - np.asarray(right_nm, float)
    return np.where(diff > threshold_nm, 1, np.where(diff < -threshold_nm, -1, 0))


def command_differences(
    reference: np.ndarray, other: np.ndarray, side_threshold_nm: float
) -> dict[str, float]:
    """How far one brake-command series is from another at the same ticks.

    Both are N×2 (left, right) torques [N·m]. Returns the mean |Δτ| per wheel, the RMS of
    Δτ over both wheels, the largest |Δτ|, and the share of ticks where both brake the same
    side (`braked_side`, released counts as a side) — over all ticks and over the ticks
    where either one brakes a side.
    """
    a, b = np.asarray(reference, float).reshape(-1, 2), np.asarray(other, float).reshape(-1, 2)
    n = len(a)
    if n == 0:
        return {"commands": 0}
    d = b - a
    sa = braked_side(a[:, 0], a[:, 1], side_threshold_nm)
    sb = braked_side(b[:, 0], b[:, 1], side_threshold_nm)
    either = (sa != 0) | (sb != 0)
    return {
        "commands": n,
        "mean_abs_diff_left_nm": float(np.mean(np.abs(d[:, 0]))),
        "mean_abs_diff_right_nm": float(np.mean(np.abs(d[:, 1]))),
        "rms_diff_nm": float(np.sqrt(np.mean(d**2))),
        "max_abs_diff_nm": float(np.max(np.abs(d))),
        "same_side_fraction": float(np.mean(sa == sb)),
        "same_side_fraction_braking": float(np.mean(sa[either] == sb[either]))
        if np.any(either)
        else math.nan,
    }
