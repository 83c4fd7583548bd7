"""Simulator and replay speed on the built-in thesis-course at default settings (one core).

- simulator alone: dynamics at 200 Hz, slip, encoders, user, collisions, depth 160x120 and
  tag camera at 10 Hz, ground truth (no localizer, mapper or log)  target >= 20x real time
- simulate command: the above in closed loop with dead reckoning, the mapper, open-loop
  braking and the MCAP recorder
- replay: dead reckoning + mapper over the recorded log           target >= 100x real time
- replay as `walkerslam replay` does it: + reference map at true poses, drag metrics
  (experiments.drag), figures

Usage: .venv/bin/python benchmarks/bench_pipeline.py [--duration S]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from experiments.run import replay_log, simulate_trial
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import load_world


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=120.0)
    args = ap.parse_args()

    sim = Simulator(load_world("thesis-course"), SimConfig(seed=0, duration_s=args.duration))
    t0 = time.perf_counter()
    sim.poll(args.duration)
    wall = time.perf_counter() - t0
    print(
        f"simulator alone: {sim.t:.1f} s in {wall:.2f} s wall = {sim.t / wall:.1f}x real time "
        "(target >= 20x)"
    )

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "trial.mcap"
        res = simulate_trial(
            "thesis-course",
            log,
            controller="open-loop",
            surface="dusty",
            seed=0,
            duration_s=args.duration,
        )
        print(
            f"simulate (closed loop + recorder): {res.sim_time_s:.1f} s in {res.wall_time_s:.2f} s"
            f" wall = {res.sim_time_s / res.wall_time_s:.1f}x real time"
        )
        for label, kw in (
            (
                "replay dead-reckoning + mapper",
                dict(figures=False, reference_map=False, drag_metrics=False),
            ),
            ("replay as the CLI: + reference map, drag metrics, figures", dict()),
        ):
            t0 = time.perf_counter()
            rep = replay_log(log, Path(tmp) / "replay", localizer="dead-reckoning", **kw)
            wall = time.perf_counter() - t0
            print(
                f"{label}: {rep.duration_s:.1f} s of log in {wall:.2f} s wall = "
                f"{rep.duration_s / wall:.1f}x real time including opening the log and writing "
                f"outputs; the message loop alone {rep.metrics['realtime_factor']:.1f}x"
                + (" (target >= 100x)" if kw else "")
            )


if __name__ == "__main__":
    main()
