"""Gyro fusion in the odometry model: exact integration of interleaved streams, the bias
and scale estimate (converges; turning, braking and standstill handled), the heading
correction, the fallback, and nothing changed while it is off."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand, EncoderTicks, GyroRate, Message, merge
from slam.base import create
from slam.dead_reckoning import DeadReckoningConfig
from slam.gyro import GyroFusion, GyroIntegrator
from slam.motion import MotionNoise, OdometryModel, uses_gyro

CAL = WalkerCalibration()
N = GyroFusion().noise_density_rad_s_sqrt_hz
KNOWN = GyroFusion(  # nothing to estimate
    enabled=True, bias_sigma_rad_s=0.0, bias_walk_rad_s_sqrt_s=0.0, scale_sigma=0.0
)


def gyro_model(fusion: GyroFusion = KNOWN, **noise) -> OdometryModel:
    return OdometryModel(CAL, MotionNoise(gyro=fusion, **noise))


def rate_profile(t):
    """ω(t) = 0.2 + 0.5 sin(1.3 t) and its integral."""
    return 0.2 + 0.5 * np.sin(1.3 * t), 0.2 * t + 0.5 / 1.3 * (1 - np.cos(1.3 * t))


@pytest.mark.parametrize("gyro_first", [True, False])
def test_interleaved_streams_integrate_exactly(gyro_first):
    """Gyro samples at 100 Hz (each the mean rate over its interval), ticks at irregular
    times in between and on the same instants, in either order: at every tick the turns
    add up to Θ at the latest sample plus its rate carried on, and to the exact integral
    of the rate at a tick that ends on the last sample."""
    rng = np.random.default_rng(5)
    tg = np.arange(0, 301) * 0.01
    _, integral = rate_profile(tg)
    gyro = [GyroRate(float(tg[0]), 0.0)]
    gyro += [
        GyroRate(float(tg[i]), float((integral[i] - integral[i - 1]) / (tg[i] - tg[i - 1])))
        for i in range(1, len(tg))
    ]
    tt = np.concatenate([[0.0], np.cumsum(rng.uniform(0.013, 0.047, 100))])
    tt = np.concatenate([tt[tt < 3.0], [1.0, 2.0, 3.0]])  # some on sample instants
    ticks = [EncoderTicks(float(t), 0, 0) for t in np.unique(tt)]
    stream = merge(gyro, ticks) if gyro_first else merge(ticks, gyro)
    model = gyro_model()
    heading, latest = 0.0, None
    for msg in stream:
        if isinstance(msg, GyroRate):
            latest = msg
        inc = model.increment(msg)
        if inc is None:
            continue
        heading += inc.dtheta
        k = round(latest.t / 0.01)
        expected = integral[k] + latest.rate_rad_s * (msg.t - latest.t)
        assert heading == pytest.approx(expected, abs=1e-12)
        assert inc.ds == 0.0 and inc.cov[0, 1] == 0.0
    if gyro_first:  # the last tick ends on the last sample
        assert msg.t == 3.0 and heading == pytest.approx(integral[-1], abs=1e-12)


def test_integrator_holds_the_latest_rate_only_so_long():
    g = GyroIntegrator(max_hold_s=0.1)
    assert g.angle_at(0.0) is None
    g.add(GyroRate(1.0, 0.5))
    g.add(GyroRate(1.2, 1.0))
    assert g.angle_at(1.2) == pytest.approx(0.2)
    assert g.angle_at(1.1) == pytest.approx(0.1)  # within the sample's interval
    assert g.angle_at(1.25) == pytest.approx(0.25)  # carried on
    assert g.angle_at(1.31) is None


def walk(
    seconds: float,
    omega=lambda t: 0.4 * math.sin(0.5 * t),
    speed: float = 0.7,
    bias: float = 0.05,
    scale: float = 0.015,
    slip=None,
    brakes: bool = True,
    seed: int = 0,
) -> tuple[list[Message], float]:
    """A walker driven at `speed` and yaw rate `omega(t)` (1 kHz truth), its encoders
    (whole counts, the left wheel under-reporting by slip(t)) at 50 Hz, its gyro
    ((1 + scale)·ω̄ + bias + white noise) at 100 Hz, and a brake command at every change
    of slip(t) > 0 when `brakes`; also the true final heading."""
    rng = np.random.default_rng(seed)
    dt, b, m = 0.001, CAL.track_m, CAL.metres_per_count
    rolled, theta, since = [0.0, 0.0], 0.0, 0.0
    msgs: list[Message] = [GyroRate(0.0, bias), EncoderTicks(0.0, 0, 0)]
    braked = False
    for k in range(1, round(seconds / dt) + 1):
        t = k * dt
        w, s = omega(t - dt / 2), slip(t) if slip is not None else 0.0
        if brakes and (s > 0) != braked:
            braked = s > 0
            msgs.append(BrakeCommand(t - dt, 2.0 if braked else 0.0, 0.0))
        rolled[0] += (speed - w * b / 2) * dt * (1 - s)
        rolled[1] += (speed + w * b / 2) * dt
        theta += w * dt
        since += w * dt
        if k % 10 == 0:
            noise = N / math.sqrt(0.01) * rng.standard_normal()
            msgs.append(GyroRate(t, (1 + scale) * since / 0.01 + bias + noise))
            since = 0.0
        if k % 20 == 0:
            msgs.append(EncoderTicks(t, math.floor(rolled[0] / m), math.floor(rolled[1] / m)))
    return msgs, theta


def run_model(model: OdometryModel, msgs: list[Message]) -> float:
    heading = 0.0
    for msg in msgs:
        inc = model.increment(msg)
        if inc is not None:
            heading += inc.dtheta
    return heading


def test_bias_and_scale_converge_to_the_truth():
    msgs, _ = walk(120.0, bias=0.05, scale=0.015)
    model = gyro_model(GyroFusion(enabled=True))
    run_model(model, msgs)
    d = model.diagnostics()["gyro"]
    assert d["bias_rad_s"] == pytest.approx(0.05, abs=3e-4)
    assert d["scale_error"] == pytest.approx(0.015, abs=2e-3)
    assert d["bias_windows"] == 120 and d["encoder_fallbacks"] == 0
    assert d["bias_sigma_rad_s"] < 2e-3


def test_turning_is_not_taken_for_bias():
    """A walker that keeps turning left (0.1 to 0.7 rad/s): the estimate is the bias, not
    the mean rate, with or without the scale estimated (a constant rate would leave bias
    and scale apart only by their priors)."""
    msgs, _ = walk(60.0, omega=lambda t: 0.4 + 0.3 * math.sin(0.5 * t), bias=-0.03, scale=0.0)
    for fusion in (GyroFusion(enabled=True), GyroFusion(enabled=True, scale_sigma=0.0)):
        model = gyro_model(fusion)
        run_model(model, msgs)
        assert model.diagnostics()["gyro"]["bias_rad_s"] == pytest.approx(-0.03, abs=5e-4)


def test_a_standstill_measures_the_bias():
    msgs, _ = walk(10.0, omega=lambda t: 0.0, speed=0.0, bias=0.2, scale=0.02)
    model = gyro_model(GyroFusion(enabled=True, correct_heading=True))
    heading = run_model(model, msgs)
    assert model.diagnostics()["gyro"]["bias_rad_s"] == pytest.approx(0.2, abs=4 * N / 3)
    assert heading == pytest.approx(0.0, abs=1e-3)  # the first second's drift taken out


def slipping(t: float) -> float:
    """The left wheel braked (and slipping by 30 %) for 2 s of every 5."""
    return 0.3 if t % 5.0 < 2.0 else 0.0


def test_braked_stretches_are_not_used_for_the_bias():
    """The encoders under-report a braked wheel: the windows leave braking (and its
    settling) out, so the estimate stays right; told nothing of the brakes it would not."""
    with_brakes, _ = walk(90.0, slip=slipping, bias=0.05, scale=0.0)
    without, _ = walk(90.0, slip=slipping, bias=0.05, scale=0.0, brakes=False)
    good, fooled = gyro_model(GyroFusion(enabled=True)), gyro_model(GyroFusion(enabled=True))
    run_model(good, with_brakes)
    run_model(fooled, without)
    assert good.diagnostics()["gyro"]["bias_rad_s"] == pytest.approx(0.05, abs=5e-4)
    assert abs(fooled.diagnostics()["gyro"]["bias_rad_s"] - 0.05) > 0.02


def test_dead_reckoning_heading_with_the_gyro_survives_slip_and_a_large_bias():
    msgs, true_heading = walk(90.0, slip=slipping, bias=-0.12, scale=0.02)
    plain = create("dead-reckoning", CAL)
    fused = create(
        "dead-reckoning",
        CAL,
        replace(
            DeadReckoningConfig(),
            noise=replace(
                DeadReckoningConfig().noise,
                gyro=replace(DeadReckoningConfig().noise.gyro, enabled=True),
            ),
        ),
    )
    for msg in msgs:
        plain.process(msg)
        fused.process(msg)

    def error(loc) -> float:
        return abs(math.remainder(loc.estimate().pose[2] - true_heading, 2 * math.pi))

    assert error(plain) > math.radians(20)  # 30 % slip for 36 s of 90
    # the bias to 3e-4 rad/s (count quantisation over 1 s windows): 1.5° in 90 s
    assert error(fused) < math.radians(2.0)
    assert fused.diagnostics()["gyro"]["bias_rad_s"] == pytest.approx(-0.12, abs=5e-4)


def test_without_gyro_samples_the_encoders_turn_and_it_is_counted():
    msgs, _ = walk(5.0, slip=slipping)
    ticks = [m for m in msgs if not isinstance(m, GyroRate)]
    plain, fused = OdometryModel(CAL), gyro_model(GyroFusion(enabled=True))
    for msg in ticks:
        a, b = plain.increment(msg), fused.increment(msg)
        assert (a is None) == (b is None)
        if a is not None:
            assert (a.ds, a.dtheta) == (b.ds, b.dtheta) and np.array_equal(a.cov, b.cov)
    assert fused.diagnostics()["gyro"]["encoder_fallbacks"] == 250


def test_gyro_off_changes_nothing():
    """Default noise: gyro messages in the stream are ignored, increments bit-identical."""
    msgs, _ = walk(5.0, slip=slipping)
    ticks = [m for m in msgs if not isinstance(m, GyroRate)]
    a = [
        (i.t, i.ds, i.dtheta, i.cov.tobytes()) for i in map(OdometryModel(CAL).increment, msgs) if i
    ]
    b = [
        (i.t, i.ds, i.dtheta, i.cov.tobytes())
        for i in map(OdometryModel(CAL).increment, ticks)
        if i
    ]
    assert a == b and len(a) == 250
    assert OdometryModel(CAL).diagnostics() == {}
    assert not uses_gyro(DeadReckoningConfig()) and uses_gyro(
        replace(DeadReckoningConfig(), noise=MotionNoise(gyro=GyroFusion(enabled=True)))
    )


def test_the_turn_variance_is_the_gyros_and_shrinks_as_the_bias_is_learned():
    msgs, _ = walk(60.0, bias=0.05)
    model = gyro_model(GyroFusion(enabled=True))
    enc = OdometryModel(CAL, MotionNoise())
    first = last = None
    for msg in msgs:
        inc, ref = model.increment(msg), enc.increment(msg)
        if inc is None or abs(ref.dtheta) < 1e-3:
            continue
        assert inc.cov[0, 0] == ref.cov[0, 0] and inc.cov[0, 1] == inc.cov[1, 0] == 0.0
        first = first or (inc.cov[1, 1], ref.cov[1, 1])
        last = (inc.cov[1, 1], ref.cov[1, 1])
    assert first[0] > first[1]  # the bias unknown: less sure than the encoders
    assert last[0] < last[1] / 20  # learned: far surer


def test_bad_fusion_settings_are_rejected():
    with pytest.raises(ValueError, match="window_s"):
        GyroFusion(window_s=0.0)
    with pytest.raises(ValueError, match="scale_error"):
        GyroFusion(scale_error=-1.0)
    with pytest.raises(ValueError, match="bias_sigma_rad_s"):
        GyroFusion(bias_sigma_rad_s=math.nan)
