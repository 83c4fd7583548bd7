"""Encoder-slip mitigations by name: what each sets, where it applies, what it needs.

A mitigation is a named bundle of settings that counters wheel slip's effect on the map:
`--mitigation NAME[,NAME...]` of replay, compare, simulate and live (and the slip study)
applies the fields it sets on the chosen localizer's config (after the source's
proposals, before the user's `--set`), the map hygiene it sets on the mapper, and checks
that it applies — a mitigation that does not apply to the localizer, or needs messages
the source does not have (a gyro, a compass or position fix, depth frames or scans), or a
calibration file not given, is a one-line error naming why. `walkerslam list
mitigations` lists them. Members are entry points of group "walker_slam.mitigations"
(`hardware.registry`), so another package adds one without editing walker-slam:

    SPEC = Spec("my-fix", None, lambda: MY_FIX, MY_FIX.summary)

Built in (each documented on its object below): brake-aware-noise, slip-estimation,
gyro, absolute-fix, scan-correction, map-hygiene, calibration.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from hardware.errors import ConfigError
from hardware.messages import (
    LANDMARK_MESSAGES,
    BrakeCommand,
    CompassHeading,
    DepthFrame,
    GyroRate,
    LaserScan,
    PositionFix,
)
from hardware.registry import Registry, Spec
from mapping.hygiene import HygieneConfig

ALL = "*"  # the key of settings that every localizer takes


@dataclass(frozen=True)
class Mitigation:
    """A named mitigation.

    localizers: {localizer name: {config field path: value}} — the localizers it applies
    to and the fields it sets on each; the key "*" (ALL) applies to every localizer.
    hygiene: the map hygiene it sets on the mapper (`mapping.hygiene`), if any.
    needs: what the source must hold: groups of message types, at least one type of
    every group (empty: nothing).
    needs_calibration: it needs a calibration file (`--calibration FILE`).
    simulated: what a simulated walker must carry for it ({SimConfig part: True}, e.g.
    "gyro"), switched on by simulate and the studies.
    """

    name: str
    summary: str
    localizers: Mapping[str, Mapping[str, Any]]
    hygiene: HygieneConfig | None = None
    needs: tuple[tuple[type, ...], ...] = ()
    needs_calibration: bool = False
    simulated: tuple[str, ...] = ()
    notes: str = ""

    def settings(self, localizer: str) -> dict[str, Any]:
        """The fields it sets on `localizer`'s config; ConfigError when it does not apply."""
        if localizer in self.localizers:
            return dict(self.localizers[localizer])
        if ALL in self.localizers:
            return dict(self.localizers[ALL])
        raise ConfigError(
            f"mitigation '{self.name}' does not apply to localizer '{localizer}'; it "
            f"applies to: {', '.join(sorted(self.localizers))}"
        )


# Members: the entry points of group "walker_slam.mitigations" (pyproject.toml).
MITIGATIONS: Registry[Mitigation] = Registry("mitigation", "walker_slam.mitigations")


@dataclass(frozen=True)
class Mitigated:
    """What a set of mitigations does to one run: the localizer fields, the map hygiene,
    what the source must hold and the simulated sensors it needs."""

    names: tuple[str, ...] = ()
    localizer_settings: dict[str, Any] = field(default_factory=dict)
    hygiene: HygieneConfig | None = None
    needs: tuple[tuple[str, tuple[type, ...]], ...] = ()
    needs_calibration: tuple[str, ...] = ()
    simulated: tuple[str, ...] = ()

    def record(self) -> dict[str, Any]:
        """What config.json keeps of it."""
        return {
            "names": list(self.names),
            "localizer_settings": self.localizer_settings,
            "hygiene": None if self.hygiene is None else vars(self.hygiene),
        }


def set_name(names: Sequence[str]) -> str:
    """A set of mitigations' name in tables and file names: 'none' or 'a+b'."""
    return "+".join(names) if names else "none"


def parse(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """'gyro,map-hygiene' (or a list of such) → ('gyro', 'map-hygiene'); 'none' or
    nothing → (); unknown names are an error listing the valid ones."""
    items: list[str] = []
    for part in [text] if isinstance(text, str) else list(text or []):
        items += [p.strip() for p in part.replace("+", ",").split(",") if p.strip()]
    items = [i for i in items if i != "none"]
    for name in items:
        MITIGATIONS.spec(name)
    dup = sorted({n for n in items if items.count(n) > 1})
    if dup:
        raise ConfigError(f"mitigation given twice: {', '.join(dup)}")
    return tuple(items)


def resolve(names: Iterable[str], localizer: str) -> Mitigated:
    """The combined effect of `names` on `localizer`; ConfigError when one does not
    apply or two set one field differently."""
    names = tuple(names)
    settings: dict[str, Any] = {}
    owner: dict[str, str] = {}
    hygiene: dict[str, Any] = {}
    needs, calibration, simulated = [], [], []
    for name in names:
        m = MITIGATIONS.create(name)
        for path, value in m.settings(localizer).items():
            if path in settings and settings[path] != value:
                raise ConfigError(
                    f"mitigations '{owner[path]}' and '{name}' set {localizer}.{path} "
                    f"differently ({settings[path]!r}, {value!r})"
                )
            settings[path], owner[path] = value, name
        if m.hygiene is not None:
            hygiene.update({k: v for k, v in vars(m.hygiene).items() if v not in (None, False)})
        needs += [(name, group) for group in m.needs]
        if m.needs_calibration:
            calibration.append(name)
        simulated += [s for s in m.simulated if s not in simulated]
    return Mitigated(
        names,
        settings,
        HygieneConfig(**hygiene) if hygiene else None,
        tuple(needs),
        tuple(calibration),
        tuple(simulated),
    )


def check_source(mitigated: Mitigated, present: set[type], source: str) -> None:
    """ConfigError naming `source` when a mitigation needs messages it does not hold."""
    for name, types in mitigated.needs:
        if not any(t in present for t in types):
            what = " or ".join(t.__name__ for t in types)
            raise ConfigError(f"{source}: mitigation '{name}' needs {what} messages; it has none")


def check_calibration(mitigated: Mitigated, calibration_file: object) -> None:
    """ConfigError when a mitigation needs a calibration file and none was given."""
    if mitigated.needs_calibration and calibration_file is None:
        raise ConfigError(
            f"mitigation '{mitigated.needs_calibration[0]}' needs the walker's calibration: "
            "give --calibration FILE (from walkerslam calibrate)"
        )


# --- the built-in mitigations -----------------------------------------------------------

BRAKE_AWARE_NOISE = Mitigation(
    "brake-aware-noise",
    "inflate a braked wheel's odometry variance and remove its expected under-report "
    "(slam.motion.MotionNoise.brake_aware), tuned on the simulated dusty floor",
    {
        ALL: {
            "noise.brake_aware": True,
            "noise.brake_wheel_m": 0.02,
            "noise.bias_per_full_brake": 0.1,
        }
    },
    notes="bias_per_full_brake 0.1: chosen on dusty thesis-course trials (seeds 1-2 of "
    "{0, 0.04, 0.08, 0.09, 0.1, 0.12}, phantom area of dead reckoning), the simulated "
    "dusty floor's slip at full brake; it over-corrects a clean floor (k 0.02), where "
    "slip-estimation, which learns k, is the mitigation to use",
)

GYRO = Mitigation(
    "gyro",
    "the turn of every odometry increment from a yaw-rate gyro, its bias estimated "
    "online (slam.gyro)",
    {ALL: {"noise.gyro.enabled": True}},
    needs=((GyroRate,),),
    simulated=("gyro",),
)

ABSOLUTE_FIX = Mitigation(
    "absolute-fix",
    "fuse absolute heading (compass) and position fixes (slam.absolute)",
    {
        name: {"absolute.use_compass": True, "absolute.use_position": True}
        for name in ("ekf-slam", "particle-filter", "gtsam", "alpha-blend")
    },
    needs=((CompassHeading, PositionFix),),
)

SCAN_CORRECTION = Mitigation(
    "scan-correction",
    "correct the pose by matching depth frames or scans to the map, without tags",
    {
        "gtsam": {"scan_matching": True},
        "particle-filter": {"use_scans": True},
        "grid-rbpf": {},
    },
    needs=((DepthFrame, LaserScan),),
    notes="grid-rbpf matches every frame to its particles' maps already",
)

MAP_HYGIENE = Mitigation(
    "map-hygiene",
    "do not map during braked turns, and let stale cells fade (mapping.hygiene)",
    {ALL: {}},
    hygiene=HygieneConfig(decay_half_life_s=10.0, gate_braked_turn=True),
)

CALIBRATION = Mitigation(
    "calibration",
    "odometry from a UMBmark calibration (walkerslam calibrate), so systematic error is "
    "not mistaken for slip",
    {ALL: {}},
    needs_calibration=True,
)

SLIP_ESTIMATION = Mitigation(
    "slip-estimation",
    "each rear wheel's slip per unit brake level as estimated state, learnt from the tag "
    "observations, correcting the odometry between sightings (slam.slip)",
    {
        name: {
            "slip.estimate": True,
            "align_observations": True,
            "noise.brake_delay_s": 0.03,
            "noise.wheel_m": 1e-4,
        }
        for name in ("ekf-slam", "gtsam", "fastslam")
    },
    needs=((BrakeCommand,), LANDMARK_MESSAGES),
    notes="noise.wheel_m 1e-4: the encoders' own noise once slip is modelled (a slipping "
    "trial proposes more, to cover slip); brake_delay_s: the loop's latency",
)


def _spec(m: Mitigation) -> Spec[Mitigation]:
    return Spec(m.name, None, lambda: m, m.summary)


BRAKE_AWARE_NOISE_SPEC = _spec(BRAKE_AWARE_NOISE)
GYRO_SPEC = _spec(GYRO)
SLIP_ESTIMATION_SPEC = _spec(SLIP_ESTIMATION)
ABSOLUTE_FIX_SPEC = _spec(ABSOLUTE_FIX)
SCAN_CORRECTION_SPEC = _spec(SCAN_CORRECTION)
MAP_HYGIENE_SPEC = _spec(MAP_HYGIENE)
CALIBRATION_SPEC = _spec(CALIBRATION)
