"""The numbers the README quotes for `make demo` are what a fresh demo run gives, so they
cannot drift from the code again (they did: 126 s, 0.38, 9.0 m², 1.70 m were stale)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def quoted() -> dict[str, str]:
    """The demo's numbers as the README's 'What it shows' paragraph words them."""
    text = " ".join(README.read_text().split())  # one line, single spaces
    patterns = {
        "duration": r"`make demo` \(seed 0, ([\d.]+) s on `thesis-course`",
        "precision": r"dead-reckoned poses have precision ([\d.]+) and",
        "phantom": r"precision [\d.]+ and ([\d.]+) m² of phantom obstacles",
        "final": r"Dead reckoning ends ([\d.]+) m from the truth",
        "ate": r"\(ATE ([\d.]+) m after SE\(2\) alignment",
        "ate_unaligned": r"alignment, ([\d.]+) m without",
        "heading_max": r"heading error reaches (\d+)°",
        "heading_median": r"\(median (\d+)°\)",
        "view_count": r"leaves ([\d.]+) m² of phantom obstacles instead of",
        "view_count_versus": r"phantom obstacles instead of ([\d.]+) m²",
        "collisions": (
            r"The trial has (\d+) collisions \(front (\d+), side (\d+), rear-wheel (\d+)\)"
        ),
    }
    out = {}
    for key, pat in patterns.items():
        m = re.search(pat, text)
        assert m, f"the README no longer words the demo's {key} as the test expects: {pat}"
        out[key] = m.groups() if key == "collisions" else m.group(1)
    return out


def same(value: float, words: str) -> bool:
    """`value` rounds to the README's `words` at the README's precision."""
    decimals = len(words.split(".")[1]) if "." in words else 0
    return round(value, decimals) == float(words)


@pytest.mark.slow
def test_the_readme_quotes_a_fresh_demo_run(tmp_path):
    from experiments.run import replay_log, simulate_trial
    from mapping.grid import GridConfig
    from mapping.mapper import MapperConfig

    q = quoted()
    log = tmp_path / "trial.mcap"
    sim = simulate_trial(
        "thesis-course", log, controller="open-loop", surface="dusty", seed=0, duration_s=300
    )
    kw = {"figures": False, "reference_map": False}  # (the README quotes no reference-map number)
    dr = replay_log(log, tmp_path / "dr", localizer="dead-reckoning", **kw)
    m = dr.metrics
    vc = replay_log(
        log,
        tmp_path / "vc",
        mapper_config=MapperConfig(grid=GridConfig(model="view-count")),
        drag_metrics=False,
        **kw,
    ).metrics
    est, gt = dr.pipeline.localizer.trajectory(), dr.pipeline.recorded.groundtruth_trajectory()
    err = np.degrees(np.abs(np.remainder(est.interpolate(gt.t)[:, 2] - gt.poses[:, 2] + np.pi,
                                         2 * np.pi) - np.pi))  # fmt: skip
    fresh = {
        "duration": sim.sim_time_s,
        "precision": m["map_precision"],
        "phantom": m["phantom_area_m2"],
        "final": m["final_position_error_m"],
        "ate": m["ate_rmse_m"],
        "ate_unaligned": m["ate_rmse_unaligned_m"],
        "heading_max": float(err.max()),
        "heading_median": float(np.median(err)),
        "view_count": vc["phantom_area_m2"],
        "view_count_versus": m["phantom_area_m2"],
    }
    wrong = {k: (q[k], round(v, 4)) for k, v in fresh.items() if not same(v, q[k])}
    assert not wrong, f"README says / a fresh demo gives: {wrong}"
    c = m["collisions"]
    got = (c["total"], c["front"], c["side"], c["rear-wheel"])
    assert got == tuple(int(v) for v in q["collisions"]), got
