"""Message types and the timestamp merge of several sources."""

import numpy as np
import pytest

from hardware.messages import (
    CameraIntrinsics,
    DepthFrame,
    EncoderTicks,
    RangeBearings,
    VelocityOdometry,
    merge,
)


def test_merge_orders_by_time_and_keeps_source_order_on_ties():
    rng = np.random.default_rng(0)
    a = [EncoderTicks(float(t), i, 0) for i, t in enumerate(np.sort(rng.integers(0, 50, 40)))]
    b = [
        VelocityOdometry(float(t), float(i), 0.0)
        for i, t in enumerate(np.sort(rng.integers(0, 50, 30)))
    ]
    out = list(merge(a, b))
    assert len(out) == 70
    assert [m.t for m in out] == sorted(m.t for m in out)
    for t in {m.t for m in out}:
        at_t = [m for m in out if m.t == t]
        kinds = [isinstance(m, EncoderTicks) for m in at_t]
        assert kinds == sorted(kinds, reverse=True)  # source a first on ties
    assert [m for m in out if isinstance(m, EncoderTicks)] == a  # each source's order kept


def test_merge_is_lazy():
    def endless(step):
        t = 0.0
        while True:
            yield EncoderTicks(t, 0, 0)
            t += step

    it = merge(endless(0.1), endless(0.25))
    first = [next(it).t for _ in range(6)]
    assert first == pytest.approx([0.0, 0.0, 0.1, 0.2, 0.25, 0.3])


def test_depth_frame_checks_shape_and_dtype():
    k = CameraIntrinsics.from_fov(4, 3, 1.0, 0.8)
    DepthFrame(0.0, np.zeros((3, 4), np.uint16), k)
    with pytest.raises(ValueError, match="uint16"):
        DepthFrame(0.0, np.zeros((3, 4), np.float32), k)
    with pytest.raises(ValueError, match="does not match"):
        DepthFrame(0.0, np.zeros((4, 3), np.uint16), k)


def test_intrinsics_from_fov():
    k = CameraIntrinsics.from_fov(160, 120, np.radians(57), np.radians(43))
    assert 2 * np.degrees(np.arctan(80 / k.fx)) == pytest.approx(57)
    assert k.matrix[0, 2] == pytest.approx(79.5)


def test_range_bearings_hold_one_entry_per_landmark():
    ids = [3, -1]
    m = RangeBearings.of(1.5, ids, [2.0, 4.5], (0.1, -0.2))
    ids[0] = 9  # a copy: the message does not change with its source
    assert len(m) == 2 and m.landmark_ids.tolist() == [3, -1] and m.landmark_ids.dtype == np.int64
    assert not m.ranges_m.flags.writeable
    with pytest.raises(ValueError, match=r"RangeBearings at t=1.5: 2 ids, 1 ranges and 2 bearings"):
        RangeBearings.of(1.5, [3, 4], [2.0], [0.1, 0.2])
