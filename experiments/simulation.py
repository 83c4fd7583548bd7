"""One simulated closed-loop trial: the single implementation behind `walkerslam
simulate` (`experiments.run.simulate_trial`) and every run of a study
(`experiments.studies.trial.run_trial`).

`simulate(spec)` builds the simulator, the live localizer (its defaults, the trial's
proposed encoder noise, the spec's overrides), the controller behind the safety layer,
runs the closed loop and records it to a trial log when the spec names one.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import Any

from control.base import CONTROLLERS
from experiments.calibration_override import CalibrationOverride, applied
from experiments.config import checked, configure
from experiments.mitigations import Mitigated, check_calibration, resolve
from experiments.pipeline import FeedOrder, LoopConfig, Pipeline, run_closed_loop
from hardware.log import LogWriter
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.user import ConstantPush, UserProfile
from hardware.sim.world import World, load_world
from mapping.mapper import MapperConfig
from slam.base import LOCALIZERS, create

VERSION = metadata.version("walker-slam")  # from pyproject.toml, via the install


@dataclass(frozen=True)
class RunSpec:
    """Everything that defines one simulated trial.

    controller_overrides / localizer_overrides: (field, value) pairs replacing fields of
    the registered default config (after the trial's proposed settings).
    seed_localizer: a localizer with a `seed` field gets the trial seed unless
    overridden (the studies; `simulate` keeps the localizer's own default).
    user_profile: the simulated user's variation (route users). push_n: (left, right)
    constant handle forces instead of a route-following user. start_offset: (ahead,
    left, turn) of the start pose in the course's start frame [m, m, rad];
    initial_speed_mps: forward speed at t = 0. log_path: record the trial there (None:
    no log). labels: study bookkeeping (cell, trial index, sweep value...).
    mitigations: encoder-slip mitigations (`experiments.mitigations`) of the live
    localizer and map; the simulated walker carries the sensors they need (a gyro).
    """

    course: str
    controller: str
    localizer: str = "dead-reckoning"
    surface: str | float = "dusty"
    seed: int = 0
    duration_s: float = 300.0
    controller_overrides: tuple[tuple[str, Any], ...] = ()
    localizer_overrides: tuple[tuple[str, Any], ...] = ()
    seed_localizer: bool = True
    user_profile: UserProfile | None = None
    push_n: tuple[float, float] | None = None
    start_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    initial_speed_mps: float = 0.0
    log_path: str | None = None
    labels: dict[str, Any] = field(default_factory=dict)
    mitigations: tuple[str, ...] = ()


@dataclass
class Simulated:
    """What `simulate` ran: the simulator (its final state), the world, the pipeline
    (localizer, map, everything fed), the run's config, the wall time."""

    sim: Simulator
    world: World
    pipeline: Pipeline
    config: dict[str, Any]
    wall_s: float


def config_dict(cfg: Any) -> Any:
    """A config dataclass as JSON-able data (tuples as lists)."""
    if not (is_dataclass(cfg) and not isinstance(cfg, type)):
        return cfg
    d = asdict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def shifted_pose(pose: tuple[float, float, float], offset: tuple[float, float, float]):
    """`pose` moved by (ahead, left, turn) in its own frame."""
    x, y, th = pose
    a, b, dth = offset
    c, s = math.cos(th), math.sin(th)
    return (x + a * c - b * s, y + a * s + b * c, math.remainder(th + dth, 2 * math.pi))


def _world(spec: RunSpec) -> World:
    world = load_world(spec.course)
    if any(spec.start_offset):
        world = replace(world, start_pose=shifted_pose(world.start_pose, spec.start_offset))
    return world


def _localizer_config(spec: RunSpec, sim: Simulator, mitigated: Mitigated) -> Any:
    over = {**mitigated.localizer_settings, **dict(spec.localizer_overrides)}
    cfg = configure(LOCALIZERS, spec.localizer, sim.metadata, over).config
    if spec.seed_localizer and "seed" not in over and any(f.name == "seed" for f in fields(cfg)):
        cfg = replace(cfg, seed=spec.seed)
    return cfg


def _run_config(
    spec: RunSpec, world, ctl_cfg, loc, loop, sim_cfg, command: str, override: dict | None
) -> dict:
    return {
        "command": command,
        "walker_slam_version": VERSION,
        "course": spec.course,
        "initial_pose": list(world.start_pose),
        "controller": spec.controller,
        "controller_config": config_dict(ctl_cfg),
        "localizer": spec.localizer,
        "localizer_config": config_dict(loc.config),
        "loop": asdict(loop),
        "sim": sim_cfg.to_dict(),
        "user": (
            {"kind": "constant-push", "left_n": spec.push_n[0], "right_n": spec.push_n[1]}
            if spec.push_n is not None
            else {"kind": "route-follower"}
        ),
        "initial_speed_mps": spec.initial_speed_mps,
        "labels": dict(spec.labels),
        "mitigations": list(spec.mitigations),
        **({"calibration_override": override} if override is not None else {}),
    }


def _carrying(cfg: SimConfig, mitigated: Mitigated) -> SimConfig:
    """`cfg` with the simulated sensors the mitigations need switched on."""
    if "gyro" in mitigated.simulated and not cfg.gyro.enabled:
        cfg = replace(cfg, gyro=replace(cfg.gyro, enabled=True))
    return cfg


def simulate(
    spec: RunSpec,
    *,
    sim_config: SimConfig | None = None,
    loop: LoopConfig | None = None,
    progress: Callable[[float], None] | None = None,
    command: str = "simulate",
    calibration: CalibrationOverride | None = None,
) -> Simulated:
    """Run the trial `spec` (see the module docstring); sim_config: the simulator's other
    settings (e.g. the depth image size), its surface, seed, duration and user profile
    taken from the spec; calibration: a file whose wheel diameters and track the walker's
    software believes instead (the simulated walker's truth stays)."""
    world = _world(spec)
    ctl_cfg = configure(CONTROLLERS, spec.controller, None, spec.controller_overrides).config
    mitigated = resolve(spec.mitigations, spec.localizer)
    check_calibration(mitigated, calibration)
    sim_cfg = checked(
        lambda: _carrying(
            replace(
                sim_config or SimConfig(),
                surface=spec.surface,
                seed=spec.seed,
                duration_s=spec.duration_s,
                user_profile=spec.user_profile,
            ),
            mitigated,
        ),
        "simulation",
    )
    user = ConstantPush(*spec.push_n) if spec.push_n is not None else None
    believed, override = applied(calibration, sim_cfg.calibration())
    sim = Simulator(world, sim_cfg, user=user, calibration=believed)
    sim.state.v = float(spec.initial_speed_mps)
    cal = sim.calibration
    # the trial proposes its simulated encoders' noise to every later replay; the live
    # localizer takes it too, so a live run and its replay are the same run
    loc = create(
        spec.localizer, cal, _localizer_config(spec, sim, mitigated), initial_pose=world.start_pose
    )
    ctl = CONTROLLERS.create(spec.controller, cal, config=ctl_cfg)
    loop = loop or LoopConfig()
    config = _run_config(spec, world, ctl_cfg, loc, loop, sim_cfg, command, override)
    mapper = MapperConfig(hygiene=mitigated.hygiene) if mitigated.hygiene is not None else None
    pipeline = Pipeline(loc, cal, mapper, reference_map=False)
    t0 = time.perf_counter()
    if spec.log_path:
        path = Path(spec.log_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with LogWriter(path, cal, metadata={"config": config, **sim.metadata}) as log:
            run_closed_loop(sim, sim, pipeline, ctl, loop, record=FeedOrder(log), progress=progress)
            log.add_metadata("slip", sim.slip_summary())
    else:
        run_closed_loop(sim, sim, pipeline, ctl, loop, progress=progress)
    return Simulated(sim, world, pipeline, config, time.perf_counter() - t0)
