"""The MTRX5700 comparison (SIMULATED Player/Stage data): alpha-blend, ekf-slam, the
particle filter and gtsam fusing compass headings (σ 0.25 rad) and GPS-like fixes (σ
0.5 m), no landmarks, scored against the importer's reference — dead reckoning on the
noise-free velocities, time-scaled and started as fitted to the fixes and compass (a
near-truth reference with ≈ 0.05 m of its own uncertainty, NOT ground truth; see
hardware/datasets/mtrx5700.py). Measured 2026-12 (unaligned position RMSE):

    dead reckoning on the raw velocities        1.826 m
    alpha-blend α = 0.1 (the report's)          0.257 m   (α 0.5: 0.450, 0.9: 0.692, 1: 0.764)
    ekf-slam filtered / RTS-smoothed (default)  0.255 / 0.167 m
    particle-filter filtered / RTS (seed 0)     0.244 / 0.159 m
    gtsam (iSAM2)                               0.167 m
    the fixes themselves (2-D RMS)              0.747 m

The three smoothers agree with each other within 0.01-0.03 m; the filtered EKF and the
report's α = 0.1 blend are equally good here (the blend's α happens to suit this data).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from experiments.config import configure
from hardware.datasets import open_dataset
from hardware.messages import GroundTruthPose, PositionFix
from slam.base import LOCALIZERS, create
from slam.trajectory import Trajectory

pytestmark = pytest.mark.data


FOLDER = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "mtrx5700_stage_sim"


@pytest.fixture(scope="module")
def mtrx():
    if not FOLDER.exists():
        pytest.skip(f"dataset mtrx5700_stage_sim not found at {FOLDER}")
    ds = open_dataset("mtrx5700", FOLDER)
    truth = list(ds.messages([GroundTruthPose]))
    reference = Trajectory(
        np.array([m.t for m in truth]), np.array([(m.x, m.y, m.theta) for m in truth])
    )
    messages = [m for m in ds.messages() if not isinstance(m, GroundTruthPose)]
    return ds, messages, reference


def run(mtrx, name: str, **settings) -> Trajectory:
    """`name` with the importer's proposed settings (compass and fix fusion) and these."""
    ds, messages, _ = mtrx
    cfg = configure(LOCALIZERS, name, ds.metadata, settings).config
    loc = create(name, ds.calibration, cfg, initial_pose=ds.initial_pose)
    for m in messages:
        loc.process(m)
    return loc.trajectory()


def rmse(a: Trajectory, b: Trajectory, at: np.ndarray) -> float:
    d = a.interpolate(at)[:, :2] - b.interpolate(at)[:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def test_fusion_against_the_reference(mtrx):
    ds, _, ref = mtrx
    trajectories = {
        "dead-reckoning": run(mtrx, "dead-reckoning"),
        "alpha-blend": run(mtrx, "alpha-blend"),
        "ekf-slam": run(mtrx, "ekf-slam"),
        "ekf-slam filtered": run(mtrx, "ekf-slam", smoother="none"),
        "particle-filter": run(mtrx, "particle-filter"),
        "gtsam": run(mtrx, "gtsam"),
    }
    err = {name: rmse(traj, ref, ref.t) for name, traj in trajectories.items()}
    fixes = np.array([(m.t, m.x, m.y) for m in ds.messages([PositionFix])])
    gps = np.sqrt(np.mean(np.sum((fixes[:, 1:] - ref.interpolate(fixes[:, 0])[:, :2]) ** 2, 1)))
    assert gps == pytest.approx(0.75, abs=0.05)  # 0.5 m per axis
    assert err["dead-reckoning"] > 1.5  # the raw velocities are not the reference
    assert err["alpha-blend"] < 0.3
    for name in ("ekf-slam", "particle-filter", "gtsam"):
        assert err[name] < 0.5, name  # below the fixes' own noise per axis
        assert err[name] < 0.75 * err["alpha-blend"], name  # measured 0.16-0.17 vs 0.257
    # filtered (causal, as alpha-blend is), the EKF is as good as the report's blend
    assert err["ekf-slam filtered"] == pytest.approx(err["alpha-blend"], rel=0.1)
    # the smoothers agree with each other far better than with the reference
    smoothers = [trajectories[n] for n in ("ekf-slam", "particle-filter", "gtsam")]
    for i in range(3):
        for j in range(i + 1, 3):
            assert rmse(smoothers[i], smoothers[j], ref.t) < 0.05


def test_larger_alpha_is_more_erratic(mtrx):
    """The report's finding (§1.d): the closer α is to 1, the more of the fixes' and the
    compass's noise the path takes on."""
    _, _, ref = mtrx
    errors = [
        rmse(run(mtrx, "alpha-blend", alpha_position=a, alpha_heading=a), ref, ref.t)
        for a in (0.1, 0.5, 0.9, 1.0)
    ]
    assert errors == sorted(errors)
    assert errors[-1] > 2.5 * errors[0]
