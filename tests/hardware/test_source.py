"""The source / sink contract: every source has one shape, the closed loop takes any timed
source and command sink, and a log written in feed order replays in that order."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from control.base import create as create_controller
from experiments.pipeline import FeedOrder, LoopConfig, Pipeline, run_closed_loop
from hardware.datasets import Dataset
from hardware.log import LogWriter, read_log
from hardware.messages import (
    BrakeCommand,
    DepthFrame,
    DeviceEvent,
    EncoderTicks,
    TagDetections,
)
from hardware.sim.simulator import SimConfig, Simulator
from hardware.sim.world import load_world
from hardware.source import CommandSink, Source, TimedSource
from slam.base import create


def short_sim(seconds=3.0, seed=0):
    return Simulator(load_world("thesis-course"), SimConfig(seed=seed, duration_s=seconds))


def test_log_dataset_and_simulator_are_sources(tmp_path):
    sim = short_sim(1.0)
    assert isinstance(sim, Source) and isinstance(sim, TimedSource)
    assert isinstance(sim, CommandSink)
    msgs = list(sim.messages())
    assert sim.done and msgs
    assert all(a.t <= b.t for a, b in itertools.pairwise(msgs))
    assert {"world", "sim", "localizer_settings"} <= set(sim.metadata)

    path = tmp_path / "t.mcap"
    with LogWriter(path, sim.calibration, metadata=sim.metadata) as log:
        for m in msgs:
            log.write(m)
    trial = read_log(path)
    assert isinstance(trial, Source) and not isinstance(trial, TimedSource)
    assert len(list(trial.messages())) == len(msgs)
    trial.close()

    ds = Dataset("d", sim.calibration, {"config": {"initial_pose": [0, 0, 0]}}, {})
    assert isinstance(ds, Source)


def test_feed_order_log_replays_in_the_order_fed(tmp_path):
    """A message delivered late (older than one of another stream already fed) keeps
    its own time but is logged when it was fed, and replays in that order."""
    sim = short_sim(0.2)
    path = tmp_path / "order.mcap"
    fed = [
        EncoderTicks(0.10, 1, 2),
        EncoderTicks(0.12, 3, 4),
        TagDetections(0.09, ()),  # late: captured before the ticks, delivered after
        DeviceEvent(0.13, "board", "disconnected", "port went away"),
        BrakeCommand(0.13, 0.5, 0.068, "controller"),
    ]
    with LogWriter(path, sim.calibration) as log:
        rec = FeedOrder(log)
        for m in fed:
            rec(m)
    back = list(read_log(path).messages())
    assert [type(m) for m in back] == [type(m) for m in fed]
    assert [m.t for m in back] == [m.t for m in fed]
    assert back[3] == fed[3]
    # without FeedOrder the log sorts by the messages' own times
    with LogWriter(tmp_path / "plain.mcap", sim.calibration) as log:
        for m in fed:
            log.write(m)
    assert next(m.t for m in read_log(tmp_path / "plain.mcap").messages()) == 0.09


def test_frame_trigger_commands_right_after_each_frame():
    sim = short_sim(4.0, seed=1)
    pipe = Pipeline(create("dead-reckoning", sim.calibration), sim.calibration, reference_map=False)
    frames, commands = [], []
    run_closed_loop(
        sim,
        sim,
        pipe,
        create_controller("open-loop", sim.calibration),
        LoopConfig(trigger="frame", latency_s=0.0),
        record=lambda m: frames.append(m.t) if isinstance(m, DepthFrame) else None,
        on_command=lambda cmd, frame: commands.append((cmd.t, None if frame is None else frame.t)),
    )
    triggered = [c for c, f in commands if f is not None]
    # one command per depth frame, stamped with the frame's time
    assert triggered == frames[: len(triggered)] and len(triggered) >= len(frames) - 1
    assert all(c == f for c, f in commands if f is not None)
    # the timer only fills in where no frame came within a period (none here: 10 Hz frames)
    assert len(commands) == len(triggered)


class Stalling:
    """The simulator, with its depth camera stalled after `after_s`."""

    def __init__(self, sim, after_s):
        self.sim, self.after_s = sim, after_s

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def poll(self, until, stop_at_frame=False):
        msgs = self.sim.poll(until, stop_at_frame and self.sim.t < self.after_s)
        return [m for m in msgs if not (isinstance(m, DepthFrame) and m.t > self.after_s)]


def test_frame_trigger_falls_back_to_the_timer_when_frames_stall():
    sim = short_sim(4.0, seed=1)
    pipe = Pipeline(create("dead-reckoning", sim.calibration), sim.calibration, reference_map=False)
    commands = []
    run_closed_loop(
        Stalling(sim, 2.0),
        sim,
        pipe,
        create_controller("open-loop", sim.calibration),
        LoopConfig(trigger="frame", latency_s=0.0),
        on_command=lambda cmd, frame: commands.append((cmd.t, frame)),
    )
    late = [t for t, f in commands if t > 2.05]
    assert late and all(f is None for t, f in commands if t > 2.05)
    assert np.allclose(np.diff(late), 0.1)  # the timer at rate_hz


def test_loop_config_rejects_bad_values():
    with pytest.raises(ValueError, match="trigger"):
        LoopConfig(trigger="sometimes")
    with pytest.raises(ValueError, match="rate_hz"):
        LoopConfig(rate_hz=0)
