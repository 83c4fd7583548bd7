"""experiments.warm_up: a live run's kernels are compiled before its devices open."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# In a fresh interpreter (this one may have compiled them in other tests): which of the
# kernels a live EKF-SLAM run with the gyro calls on its first frames and tags have
# compiled signatures before and after the warm-up.
PROBE = """
import json
from experiments.live import LIVE_LOOP
from experiments.warm_up import warm_up
from mapping import kernels as m
from slam import ekf_kernels as e

names = ["depth_pixel_cells", "range_bearing_update"]
kernels = [getattr(m, names[0]), getattr(e, names[1])]
before = [len(k.signatures) for k in kernels]
took = warm_up("ekf-slam", "open-loop", {"noise.gyro.enabled": True}, {}, (), LIVE_LOOP, True)
print(json.dumps({"names": names, "before": before,
                  "after": [len(k.signatures) for k in kernels], "took": took}))
"""


@pytest.mark.slow
def test_warm_up_compiles_the_mapper_and_localizer_kernels_in_a_fresh_process():
    out = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, check=True
    ).stdout
    res = json.loads(out.strip().splitlines()[-1])
    assert res["before"] == [0, 0], res
    assert all(n >= 1 for n in res["after"]), res
    assert res["took"] > 0.0


def test_a_mitigation_that_needs_the_walkers_calibration_file_warms_up_without_it():
    """The file calibrates the live walker, not the course's simulated one: the warm-up
    leaves such a mitigation out (it changes the odometry's numbers, not the code)."""
    from experiments.live import LIVE_LOOP
    from experiments.warm_up import warm_up

    took = warm_up("dead-reckoning", "open-loop", {}, {}, ("calibration",), LIVE_LOOP, False)
    assert took > 0.0
