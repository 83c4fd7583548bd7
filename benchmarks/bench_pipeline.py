"""Simulator and replay speed on the built-in thesis-course at default settings.

- simulator: closed loop (dead reckoning + mapper + open-loop braking), × real time
- replay: dead reckoning + mapper over the recorded log, × real time

Usage: .venv/bin/python benchmarks/bench_pipeline.py [--duration S]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from experiments.run import replay_log, simulate_trial


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=60.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "trial.mcap"
        t0 = time.perf_counter()
        sim = simulate_trial(
            "thesis-course",
            log,
            controller="open-loop",
            surface="dusty",
            seed=0,
            duration_s=args.duration,
        )
        wall = time.perf_counter() - t0
        print(
            f"simulate thesis-course {sim.sim_time_s:.1f} s simulated in {wall:.2f} s wall: "
            f"{sim.sim_time_s / wall:.1f}x real time (target >= 20x)"
        )
        t0 = time.perf_counter()
        res = replay_log(log, Path(tmp) / "replay", localizer="dead-reckoning", figures=False)
        wall = time.perf_counter() - t0
        print(
            f"replay dead-reckoning + mapper: {res.duration_s:.1f} s of log in {wall:.2f} s wall: "
            f"{res.duration_s / wall:.1f}x real time (target >= 100x)"
        )


if __name__ == "__main__":
    main()
