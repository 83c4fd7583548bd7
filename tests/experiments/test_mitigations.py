"""Mitigations by name: what they set, where they apply, what they need, end to end."""

import json

import pytest

from experiments.config import configure
from experiments.mitigations import (
    ALL,
    MITIGATIONS,
    Mitigation,
    check_calibration,
    check_source,
    parse,
    resolve,
)
from experiments.run import replay_log, simulate_trial
from hardware.errors import ConfigError, UnknownNameError
from hardware.messages import DepthFrame, EncoderTicks, GyroRate
from hardware.sim.gyro import GyroSimConfig
from hardware.sim.simulator import SimConfig
from slam.base import LOCALIZERS
from tests.experiments.test_cli import walkerslam

NAMES = (
    "absolute-fix",
    "brake-aware-noise",
    "calibration",
    "gyro",
    "map-hygiene",
    "scan-correction",
    "slip-estimation",
)


def test_the_built_in_mitigations_are_registered() -> None:
    assert set(NAMES) <= set(MITIGATIONS.names())
    assert parse("gyro,map-hygiene") == ("gyro", "map-hygiene")
    assert parse("gyro+map-hygiene") == ("gyro", "map-hygiene")
    assert parse(["gyro", "map-hygiene"]) == ("gyro", "map-hygiene")
    assert parse("none") == parse(None) == ()
    with pytest.raises(UnknownNameError, match="unknown mitigation 'gyr'"):
        parse("gyr")
    with pytest.raises(ConfigError, match="twice"):
        parse("gyro,gyro")


@pytest.mark.parametrize("name", NAMES)
def test_every_field_a_mitigation_sets_exists_and_takes_its_value(name: str) -> None:
    """configure() checks the field paths and types: a renamed field fails here."""
    m = MITIGATIONS.create(name)
    targets = LOCALIZERS.names() if ALL in m.localizers else list(m.localizers)
    assert targets
    for loc in targets:
        settings = resolve([name], loc).localizer_settings
        cfg = configure(LOCALIZERS, loc, None, settings).config
        for path, value in settings.items():
            got = cfg
            for part in path.split("."):
                got = getattr(got, part)
            assert got == value, (loc, path)


def test_resolve_combines_refuses_and_records() -> None:
    both = resolve(["gyro", "map-hygiene"], "gtsam")
    assert both.localizer_settings == {"noise.gyro.enabled": True}
    assert both.hygiene is not None and both.hygiene.gate_braked_turn
    assert both.simulated == ("gyro",)
    assert both.record()["names"] == ["gyro", "map-hygiene"]
    with pytest.raises(ConfigError, match="'absolute-fix' does not apply to localizer 'fastslam'"):
        resolve(["absolute-fix"], "fastslam")
    with pytest.raises(ConfigError, match="needs GyroRate messages"):
        check_source(resolve(["gyro"], "ekf-slam"), {EncoderTicks, DepthFrame}, "x.mcap")
    check_source(resolve(["gyro"], "ekf-slam"), {EncoderTicks, GyroRate}, "x.mcap")
    with pytest.raises(ConfigError, match="--calibration FILE"):
        check_calibration(resolve(["calibration"], "gtsam"), None)


def test_a_mitigation_added_in_code_and_conflicting_settings() -> None:
    off = Mitigation("gyro-off", "no gyro", {ALL: {"noise.gyro.enabled": False}})
    MITIGATIONS.register("gyro-off", None, off.summary)(lambda: off)
    try:
        assert resolve(["gyro-off"], "dead-reckoning").localizer_settings == {
            "noise.gyro.enabled": False
        }
        with pytest.raises(ConfigError, match="'gyro' and 'gyro-off' set"):
            resolve(["gyro", "gyro-off"], "dead-reckoning")
    finally:
        MITIGATIONS._specs.pop("gyro-off")


@pytest.fixture(scope="module")
def gyro_trial(tmp_path_factory):
    path = tmp_path_factory.mktemp("mitigation") / "t.mcap"
    simulate_trial(
        "thesis-course",
        path,
        controller="open-loop",
        seed=3,
        duration_s=40.0,
        sim_config=SimConfig(gyro=GyroSimConfig(enabled=True)),
    )
    return path


def test_replay_applies_mitigations_and_records_them(gyro_trial, tmp_path) -> None:
    plain = replay_log(
        gyro_trial, tmp_path / "plain", figures=False, map_figure=False, reference_map=False
    )
    res = replay_log(
        gyro_trial, tmp_path / "m", figures=False, map_figure=False, reference_map=False,
        mitigations=("gyro", "map-hygiene"),
    )  # fmt: skip
    config = json.loads((res.out_dir / "config.json").read_text())
    assert config["mitigations"]["names"] == ["gyro", "map-hygiene"]
    assert config["localizer_config"]["noise"]["gyro"]["enabled"] is True
    assert config["mapper_config"]["hygiene"]["gate_braked_turn"] is True
    assert res.metrics["map_hygiene"]["gated_braked_turn"] > 0
    # the gyro takes the slip out of the heading: the final heading error falls
    assert res.metrics["final_heading_error_deg"] < plain.metrics["final_heading_error_deg"]
    # --set comes after the mitigation's fields
    over = replay_log(
        gyro_trial,
        tmp_path / "over",
        figures=False,
        map_figure=False,
        drag_metrics=False,
        reference_map=False,
        mitigations=("gyro",),
        localizer_overrides={"noise.gyro.enabled": False},
    )
    assert over.pipeline.localizer.config.noise.gyro.enabled is False


def test_the_cli_says_in_one_line_why_a_mitigation_cannot_run(gyro_trial, tmp_path) -> None:
    out = str(tmp_path / "o")
    wrong = walkerslam("replay", str(gyro_trial), "--mitigation", "absolute-fix", "--out", out)
    assert wrong.returncode == 2
    assert [ln for ln in wrong.stderr.splitlines() if ln.strip()] == [
        "error: mitigation 'absolute-fix' does not apply to localizer 'dead-reckoning'; it "
        "applies to: alpha-blend, ekf-slam, gtsam, particle-filter"
    ]
    lacking = walkerslam(
        "replay",
        str(gyro_trial),
        "--localizer",
        "ekf-slam",
        "--mitigation",
        "absolute-fix",
        "--out",
        str(tmp_path / "x"),
    )
    assert lacking.returncode == 2
    assert "needs CompassHeading or PositionFix messages; it has none" in lacking.stderr
    listed = walkerslam("list", "mitigations")
    assert listed.returncode == 0 and all(n in listed.stdout for n in NAMES)
