"""Localizer speed on a simulated thesis-course trial at defaults (one core): issue 3's
speed targets.

For each localizer, three real-time factors:
- filter: the sum of its `process()` calls over the decoded messages;
- replay: log decoding + the localizer (+ the occupancy mapper for the particle filter,
  whose scan likelihood reads it): the figure the targets below are checked against, as
  issue 2 already sets dead reckoning + mapper at >= 100x;
- with mapper: the replay loop as `walkerslam replay` runs it (decoding + localizer +
  mapper; smoothers' maps rebuilt at the end);
and the latency of each `process()` call (p50, p99, max).

targets: gtsam >= 50x, fastslam (100 particles) >= 20x, particle-filter (500 particles,
scan likelihood at 160x120) >= 20x, ekf-slam and dead-reckoning >= 200x real time;
p99 update latency <= 10 ms for every localizer; the particle filter <= 1 ms per depth
frame it scores (p50; the pipeline's projection not counted, issue 13).

Usage: .venv/bin/python benchmarks/bench_localizers.py [--duration S] [--localizers a,b]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments.pipeline import Pipeline
from experiments.run import simulate_trial
from hardware.log import read_log
from hardware.messages import DepthFrame, LaserScan
from slam import landmarks
from slam.base import LOCALIZERS, create

TARGET_X = {
    "dead-reckoning": 200,
    "ekf-slam": 200,
    "gtsam": 50,
    "fastslam": 20,
    "particle-filter": 20,
}


def configure(name: str):
    """The config the target names: defaults, but the particle filter scores scans and
    fastslam runs the 100 particles of issue 3's target (its default is 300)."""
    cfg = LOCALIZERS.spec(name).config_type()
    if name == "particle-filter":
        cfg = dataclasses.replace(cfg, use_scans=True)
    if name == "fastslam":
        cfg = dataclasses.replace(cfg, n_particles=100)
    return cfg


def make(name: str, trial):
    initial = trial.metadata.get("config", {}).get("initial_pose")
    return create(
        name,
        trial.calibration,
        configure(name),
        initial_pose=initial,
        landmark_map=landmarks.from_metadata(trial.metadata),
    )


def replay_speed(name: str, trial, duration: float, mapper: bool) -> float:
    loc = make(name, trial)
    t0 = time.perf_counter()
    if mapper:
        Pipeline(loc, trial.calibration, reference_map=False).run(trial.messages())
    else:
        for msg in trial.messages():
            loc.process(msg)
    return duration / (time.perf_counter() - t0)


def latencies(name: str, trial, messages) -> np.ndarray:
    """Seconds per `process()` call, with the mapper integrating frames as in a replay."""
    pipeline = Pipeline(make(name, trial), trial.calibration, reference_map=False)
    loc, out = pipeline.localizer, []
    for msg in messages:
        t0 = time.perf_counter()
        loc.process(msg)
        out.append(time.perf_counter() - t0)
        if isinstance(msg, DepthFrame | LaserScan):
            mapper = pipeline.mapper
            mapper.integrate_projection(mapper.project(msg), loc.estimate().pose)
    return np.array(out)


def frame_costs(name: str, trial, messages) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per depth frame given to the localizer as a replay gives it (the
    pipeline's projection, made once for the mapper too, outside the timing), and
    whether the frame was scored (a scan update)."""
    pipeline = Pipeline(make(name, trial), trial.calibration, reference_map=False)
    loc, cost, scored = pipeline.localizer, [], []
    for msg in messages:
        if not isinstance(msg, DepthFrame | LaserScan):
            loc.process(msg)
            continue
        projection = pipeline.mapper.project(msg)
        before = loc.diagnostics()["scan_updates"]
        t0 = time.perf_counter()
        loc.process_frame(msg, projection)
        cost.append(time.perf_counter() - t0)
        scored.append(loc.diagnostics()["scan_updates"] > before)
        pipeline.mapper.integrate_projection(projection, loc.estimate().pose)
    return np.array(cost), np.array(scored)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--localizers", default=",".join(TARGET_X))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "trial.mcap"
        simulate_trial(
            "thesis-course",
            log,
            controller="open-loop",
            surface="dusty",
            seed=0,
            duration_s=args.duration,
        )
        trial = read_log(log)
        t0, t1 = trial.time_range
        duration = t1 - t0
        messages = list(trial.messages())
        print(
            f"thesis-course, dusty, open-loop, seed 0: {duration:.0f} s, {len(messages)} messages"
        )
        for name in args.localizers.split(","):
            needs_map = name == "particle-filter"
            x = replay_speed(name, trial, duration, mapper=needs_map)
            full = x if needs_map else replay_speed(name, trial, duration, mapper=True)
            lat = latencies(name, trial, messages) * 1e3
            p50, p99, worst = [*np.percentile(lat, [50, 99]).tolist(), float(lat.max())]
            target = TARGET_X[name]
            print(
                f"{name:16s} filter {duration / (lat.sum() / 1e3):6.1f}x, replay {x:6.1f}x "
                f"real time (target >= {target}x{'' if x >= target else ', NOT MET'}), "
                f"with mapper {full:5.1f}x; process() p50 {p50:.3f} ms, "
                f"p99 {p99:.2f} ms (target <= 10 ms{'' if p99 <= 10 else ', NOT MET'}), "
                f"max {worst:.1f} ms",
                flush=True,
            )
            if name == "particle-filter":
                cost, scored = frame_costs(name, trial, messages)
                cost *= 1e3
                p50, p99 = np.percentile(cost[scored], [50, 99])
                every = np.percentile(cost, 99)
                met = p99 <= 1.0 and every <= 1.0
                print(
                    f"{'':16s} per depth frame: {scored.sum()} of {len(cost)} scored, p50 "
                    f"{p50:.3f} ms, p99 {p99:.3f} ms; every frame p99 {every:.3f} ms, max "
                    f"{cost.max():.3f} ms, mean {cost.mean():.3f} ms (target <= 1 ms at "
                    f"the p99{'' if met else ', NOT MET'})",
                    flush=True,
                )


if __name__ == "__main__":
    main()
