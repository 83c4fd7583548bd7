"""The pipeline's own checks on its input."""

import numpy as np

from experiments.pipeline import Pipeline
from hardware.calibration import WalkerCalibration
from hardware.messages import EncoderTicks, GroundTruthPose
from slam.base import create


def _run(messages):
    cal = WalkerCalibration()
    pipe = Pipeline(create("dead-reckoning", cal), cal, reference_map=False)
    for m in messages:
        pipe.feed(m)
    return pipe


def test_a_message_older_than_its_streams_last_is_dropped_and_counted():
    """A live source (or the Python API) may deliver a stale message: it is dropped, not
    integrated as motion backwards in time, and counted per type; other streams and
    equal times are not affected."""
    ticks = [EncoderTicks(0.02 * k, 5 * k, 6 * k) for k in range(50)]
    stale = EncoderTicks(0.30, 2, 2)  # after t = 0.98: its time goes backwards
    truth = GroundTruthPose(0.5, 0.0, 0.0, 0.0)  # another stream, older than the ticks: kept
    clean = _run(ticks)
    mixed = _run([*ticks[:50], stale, truth, ticks[-1]])  # the last one again: same time
    assert mixed.recorded.out_of_order == {"EncoderTicks": 1}
    assert mixed.recorded.counts["GroundTruthPose"] == 1
    assert mixed.recorded.counts["EncoderTicks"] == 51
    np.testing.assert_array_equal(
        mixed.localizer.trajectory().poses, clean.localizer.trajectory().poses
    )
    assert clean.recorded.out_of_order == {}
