"""The per-particle-map filter (grid-rbpf) at its defaults: speed on the walker's depth
frames and on the Intel lab log, accuracy on Intel, and the Intel replay's peak memory.

- walker: a simulated thesis-course trial (dusty, open loop, seed 0, --duration s), the
  pipeline's replay loop (filter + shared mapper), real-time factor;
- intel: the whole 45-minute Intel log (../shared/data/intel_lab) through
  `experiments.run.replay_log` as `walkerslam replay --format carmen ... --localizer
  grid-rbpf` runs it: real-time factor, Kümmerle et al. relations error (mean ± std,
  translational and rotational, and the median) and the process's peak resident memory
  (run in its own process, so the walker part does not count).

targets (issue 13): >= 50x real time on the walker's frames, >= 30x on Intel with its
accuracy kept (0.067 m), Intel peak memory <= 2 GB.

The filter spreads its particles' matches and map updates over one thread per core it
may run on (`grid-rbpf.threads`); `make bench` pins every benchmark to one core, so it
measures one thread; --threads N sets the number (run it without taskset to use more
cores).

Usage: .venv/bin/python benchmarks/bench_grid_rbpf.py [--only walker|intel] [--duration S]
           [--threads N]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
INTEL = REPO.parent / "shared" / "data" / "intel_lab"


def walker(duration: float, threads: int) -> None:
    from experiments.config import configure
    from experiments.pipeline import Pipeline
    from experiments.run import simulate_trial
    from hardware.log import read_log
    from slam.base import LOCALIZERS, create

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "trial.mcap"
        simulate_trial(
            "thesis-course", log, controller="open-loop", surface="dusty", seed=0,
            duration_s=duration,
        )  # fmt: skip
        trial = read_log(log)
        messages = list(trial.messages())
    built = configure(LOCALIZERS, "grid-rbpf", trial.metadata, {"threads": threads})
    initial = trial.metadata.get("config", {}).get("initial_pose")
    loc = create("grid-rbpf", trial.calibration, built.config, initial_pose=initial)
    pipeline = Pipeline(loc, trial.calibration, reference_map=False)
    t0 = time.perf_counter()
    for msg in messages:
        pipeline.feed(msg)
    wall = time.perf_counter() - t0
    t_first, t_last = trial.time_range
    x = (t_last - t_first) / wall
    d = loc.diagnostics()
    print(
        f"walker frames: {t_last - t_first:.0f} s, {d['scan_updates']} frames scored x "
        f"{d['particles']} particles in {wall:.2f} s ({_threads(threads)}): {x:.1f}x real time "
        f"(target >= 50x{'' if x >= 50 else ', NOT MET'})",
        flush=True,
    )


def _threads(threads: int) -> str:
    n = threads or len(os.sched_getaffinity(0))
    return f"{n} thread{'s' if n > 1 else ''}"


def intel(threads: int) -> None:
    from experiments.run import replay_log
    from hardware.datasets import open_dataset

    log = INTEL / "intel.gfs.log.gz"
    if not log.exists():
        print(f"intel: {log} not found, skipped")
        return
    source = open_dataset("carmen", log, relations=INTEL / "intel.relations")
    with tempfile.TemporaryDirectory() as tmp:
        result = replay_log(
            source, tmp, localizer="grid-rbpf", localizer_overrides={"threads": threads},
            figures=False, drag_metrics=False,
        )  # fmt: skip
    m = result.metrics
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # kB on Linux
    x = m["realtime_factor"]
    print(
        f"intel: {m['duration_s']:.0f} s at {x:.1f}x real time ({_threads(threads)}; target >= 30x"
        f"{'' if x >= 30 else ', NOT MET'}); relations {m['relations_trans_mean_m']:.4f} "
        f"± {m['relations_trans_std_m']:.4f} m, {m['relations_rot_mean_deg']:.2f} ± "
        f"{m['relations_rot_std_deg']:.2f} deg; peak memory {peak_gb:.2f} GB (target <= 2 GB"
        f"{'' if peak_gb <= 2 else ', NOT MET'})",
        flush=True,
    )
    print(json.dumps({"localizer_diagnostics": m.get("localizer_diagnostics", {})}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", choices=["walker", "intel"])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--threads", type=int, default=0, help="0: one per usable core")
    args = ap.parse_args()
    if args.only == "walker":
        walker(args.duration, args.threads)
    elif args.only == "intel":
        intel(args.threads)
    else:  # each in its own process: the peak memory is the Intel replay's own
        for part in ("walker", "intel"):
            cmd = [sys.executable, __file__, "--only", part, "--duration", str(args.duration)]
            cmd += ["--threads", str(args.threads)]
            subprocess.run(cmd, check=True)


if __name__ == "__main__":
    main()
