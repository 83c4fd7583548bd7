"""Warming up a live run: before the devices open, the chosen localizer, mapper and
controller run for a few seconds of the built-in simulated course, so that the numba
kernels they use are compiled (or loaded from numba's cache) then, not on the live
path. Compiling holds the interpreter lock for seconds on the first run after an
install: in the loop, the driver threads could not read the serial port meanwhile (the
board's reports overflowed and were lost) and the brakes had no new command. Kernels
are compiled per argument type, not per size, so the simulated course's small depth
frames compile what a Kinect's 640×480 ones need."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

from experiments.mitigations import resolve
from experiments.pipeline import LoopConfig
from experiments.simulation import RunSpec, simulate
from hardware.sim.simulator import SimConfig

# long enough for the course's first tags to come into view (their update kernels)
WARM_UP_S = 2.0


def warm_up(
    localizer: str,
    controller: str,
    localizer_overrides: dict[str, Any],
    controller_overrides: dict[str, Any],
    mitigations: tuple[str, ...],
    loop: LoopConfig,
    gyro: bool,
) -> float:
    """Run the live run's localizer (its --set and mitigations), controller and loop on
    WARM_UP_S of the simulated course, its map rebuilt on the way; the wall time it
    took [s]."""
    # a mitigation that only needs the walker's calibration file (its odometry) changes no
    # kernel, and the course's simulated walker is not the one the file calibrates
    needs_file = resolve(mitigations, localizer).needs_calibration
    spec = RunSpec(
        course="thesis-course",
        controller=controller,
        localizer=localizer,
        duration_s=WARM_UP_S,
        controller_overrides=tuple(controller_overrides.items()),
        localizer_overrides=tuple(localizer_overrides.items()),
        mitigations=tuple(m for m in mitigations if m not in needs_file),
    )
    sim = SimConfig()
    if gyro:
        sim = replace(sim, gyro=replace(sim.gyro, enabled=True))
    # in the calling thread (a background rebuild would compile in another), rebuilt
    # once on the way
    loop = replace(loop, rebuild_in_background=False, map_rebuild_s=WARM_UP_S / 2)
    t0 = time.perf_counter()
    simulate(spec, sim_config=sim, loop=loop, command="warm-up")
    return time.perf_counter() - t0
