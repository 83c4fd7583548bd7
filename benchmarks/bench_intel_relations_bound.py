"""What the Intel lab log in ../shared/data allows on the Kümmerle et al. relations.

The relations (intel.relations) are relative poses between scans of the *raw* Intel log
(13,631 scans); intel.gfs.log keeps 910 of them. A relation's end that falls between two
kept scans can only be placed by odometry from the scans either side. This script
measures the best any localizer can do with this log: an "oracle" trajectory that has
GMapping's corrected pose exactly at every kept scan and the log's odometry in between
(from the scan before, from the scan after, and the two blended linearly in time), scored
with the same relation metric (experiments.metrics.relation_errors) as every replay. It
also counts the relation ends that lie on a kept scan (within TOLERANCE_S: the offset
between the two logs' clocks varies by ±5 ms, ../shared/data/intel_lab/SOURCE.md).

With --trajectory T.tum (a replay's trajectory.tum on this log) it also scores that
trajectory on all relations and on those with both ends on a kept scan.

Usage: .venv/bin/python benchmarks/bench_intel_relations_bound.py [--trajectory T.tum]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
INTEL = REPO.parent / "shared" / "data" / "intel_lab"
TOLERANCE_S = 0.006


def oracle(scans, odometry, t: np.ndarray, mode: str) -> np.ndarray:
    """Poses at times t: each kept scan's corrected pose carried by the odometry to t
    from the scan before ("forward"), the scan after ("backward"), or both blended
    linearly in time ("blend")."""
    from hardware.geometry import between, compose, wrap_angle

    i = np.clip(np.searchsorted(scans.t, t, side="right") - 1, 0, len(scans.t) - 2)
    s0, s1 = scans.t[i], scans.t[i + 1]
    here = odometry.interpolate(t)
    fwd = compose(scans.poses[i], between(odometry.interpolate(s0), here))
    bwd = compose(scans.poses[i + 1], between(odometry.interpolate(s1), here))
    if mode == "forward":
        return fwd
    if mode == "backward":
        return bwd
    w = np.clip((t - s0) / np.maximum(s1 - s0, 1e-9), 0.0, 1.0)[:, None]
    d = bwd - fwd
    d[:, 2] = wrap_angle(d[:, 2])
    out = fwd + w * d
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--trajectory", type=Path, help="a replay's trajectory.tum on Intel")
    args = parser.parse_args()
    from experiments.metrics import relation_errors
    from experiments.run import replay_log
    from hardware.datasets import open_dataset
    from slam.trajectory import Trajectory

    log = INTEL / "intel.gfs.log.gz"
    if not log.exists():
        print(f"intel: {log} not found, skipped")
        return
    source = open_dataset("carmen", log, relations=INTEL / "intel.relations")
    rel = np.asarray(source.metadata["relations"]["rows"], dtype=float)
    with tempfile.TemporaryDirectory() as tmp:
        result = replay_log(
            source, tmp, localizer="dead-reckoning", figures=False, drag_metrics=False,
            reference_map=False,
        )  # fmt: skip
        odometry = Trajectory.read_tum(result.files["trajectory"])
        scans = Trajectory.read_tum(result.files["groundtruth"])
    ends = rel[:, :2].ravel()
    j = np.clip(np.searchsorted(scans.t, ends), 1, len(scans.t) - 1)
    on_scan = np.minimum(np.abs(scans.t[j] - ends), np.abs(scans.t[j - 1] - ends)) <= TOLERANCE_S
    both = on_scan.reshape(-1, 2).all(axis=1)
    print(
        f"intel: {len(scans.t)} kept scans, {len(rel)} relations; {on_scan.mean():.1%} of "
        f"their ends on a kept scan, {both.sum()} relations with both ends on one",
        flush=True,
    )
    dense = np.union1d(odometry.t, scans.t)
    dense = dense[(dense >= scans.t[0]) & (dense <= scans.t[-1])]
    for mode in ("forward", "backward", "blend"):
        m = relation_errors(Trajectory(dense, oracle(scans, odometry, dense, mode)), rel)
        print(
            f"oracle ({mode}): relations {m['relations_trans_mean_m']:.4f} ± "
            f"{m['relations_trans_std_m']:.4f} m (median {m['relations_trans_median_m']:.4f}), "
            f"{m['relations_rot_mean_deg']:.2f}° ({m['relations_used']} used)",
            flush=True,
        )
    if args.trajectory is not None:
        est = Trajectory.read_tum(args.trajectory)
        for label, rows in (("all relations", rel), ("both ends on a kept scan", rel[both])):
            m = relation_errors(est, rows)
            print(
                f"{args.trajectory} on {label}: {m['relations_trans_mean_m']:.4f} m "
                f"(median {m['relations_trans_median_m']:.4f}, {m['relations_used']} used)"
            )


if __name__ == "__main__":
    main()
