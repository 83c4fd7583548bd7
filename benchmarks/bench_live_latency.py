"""Frame-to-brake-command latency of `walkerslam live --sim` (issue 10's target: p99 ≤
30 ms at 30 Hz with 640×480 depth frames).

The simulated walker runs in its own process on the other core (it stands for the
walker, another machine); the live process — driver, cameras' readers, localizer,
mapper, controller, safety layer, recorder — on this one. Latency: from a depth frame's
time (its capture, on the host clock) to the moment the brake command it triggered was
written to the board's serial port ("capture to command"), and the part of it after the
frame arrived in this process ("arrival to command": what walker-slam adds; before it are
the simulated camera's rendering, ~9 ms at 640×480, and the socket). The first
`--warmup` seconds (compilation of the mapper's kernels, the localizer's first frames)
are left out.

Usage: .venv/bin/python benchmarks/bench_live_latency.py [--duration 30] [--localizers ...]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np

from experiments.live import LiveOptions, SimWalker, run_live


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--localizers", default="dead-reckoning,ekf-slam,gtsam,fastslam")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--rate", type=int, default=30)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    cpus = sorted(os.sched_getaffinity(0))
    others = tuple(c for c in range(os.cpu_count() or 1) if c not in cpus) or None
    print(
        f"live --sim, depth {w}x{h} at {args.rate} Hz, {args.duration:.0f} s per localizer "
        f"(first {args.warmup:.0f} s left out); live process on CPUs {cpus}, "
        f"simulated walker on {list(others) if others else 'the same'}"
    )
    print(f"{'':24s} {'capture to command [ms]':>26s} {'arrival to command [ms]':>26s}")
    print(f"{'localizer':16s} {'frames':>7s} {'p50':>8s} {'p99':>8s} {'max':>8s} "
          f"{'p50':>8s} {'p99':>8s} {'max':>8s} {'dropped':>8s}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.localizers.split(","):
            res = run_live(
                LiveOptions(
                    localizer=name,
                    controller="open-loop",
                    record=str(Path(tmp) / f"{name}.mcap"),
                    duration_s=args.duration,
                    sim=SimWalker(
                        duration_s=args.duration + 60,
                        depth_size=(w, h),
                        depth_rate_hz=args.rate,
                        cpus=others,
                    ),
                )
            )
            t0 = min((s[0] for s in res.latency_samples), default=0.0)
            kept = np.array([s[1:] for s in res.latency_samples if s[0] - t0 >= args.warmup])
            cap, arr = kept[:, 0] * 1e3, kept[:, 1] * 1e3
            c50, c99 = np.percentile(cap, [50, 99])
            a50, a99 = np.percentile(arr, [50, 99])
            print(
                f"{name:16s} {len(kept):7d} {c50:8.1f} {c99:8.1f} {cap.max():8.1f} "
                f"{a50:8.1f} {a99:8.1f} {arr.max():8.1f} {res.dropped.get('sim', 0):8d}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
