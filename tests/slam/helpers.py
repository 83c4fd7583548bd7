"""Shared by the slam tests: numerical Jacobians and replaying a trial log."""

import numpy as np

from experiments.pipeline import Pipeline
from hardware.log import read_log
from hardware.messages import EncoderTicks
from slam.base import create


def numerical_jacobian(f, x, wrap=(), eps=1e-7):
    """Central differences of f at x, one column per component of x; the output
    components listed in `wrap` are angles, their differences wrapped to (−π, π]."""
    cols = []
    for i in range(len(x)):
        d = np.zeros_like(x)
        d[i] = eps
        diff = np.asarray(f(x + d) - f(x - d), dtype=float)
        for k in wrap:
            diff[..., k] = (diff[..., k] + np.pi) % (2 * np.pi) - np.pi
        cols.append(diff / (2 * eps))
    return np.stack(cols, axis=-1)


def replay(log, name):
    """Run localizer `name` over a trial log through the pipeline (no reference map)."""
    trial = read_log(log)
    loc = create(name, trial.calibration, initial_pose=trial.metadata["config"]["initial_pose"])
    pipe = Pipeline(loc, trial.calibration, reference_map=False)
    pipe.run(trial.messages())
    return loc, pipe, trial


def wandering_ticks(rng, steps, left, right, dt=0.05):
    """Encoder messages at dt·k for k in `steps`, each wheel going on from its count by a
    random 0–19 (left) and 0–29 (right) counts: a walker that wanders and turns."""
    out = []
    for k in steps:
        left += int(rng.integers(0, 20))
        right += int(rng.integers(0, 30))
        out.append(EncoderTicks(dt * k, left, right))
    return out
