"""The simulated walker as a source of messages and a sink of brake commands.

The simulator is a timed source and a command sink (`hardware.source`):
`Simulator.poll(t)` integrates the dynamics at the physics rate up to t and returns the
sensor messages that fell due (encoder ticks, depth frames, tag detections, ground truth,
collisions); `Simulator.send(cmd)` sets the brake command (quantised to the board's PWM
as the real brakes are); `messages()` runs it open loop to the end. The closed loop
(localizer, mapper, controller) is run by `experiments.pipeline`, exactly as with live
hardware.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from hardware.calibration import WalkerCalibration, wheel_diameters
from hardware.messages import (
    BrakeCommand,
    CameraIntrinsics,
    Collision,
    DepthFrame,
    EncoderTicks,
    GroundTruthPose,
    GyroRate,
    Message,
    TagDetections,
)
from hardware.sim.depth_camera import DepthCameraConfig, SimDepthCamera
from hardware.sim.dynamics import Brakes, WalkerParams, WalkerState, step
from hardware.sim.gyro import GyroSimConfig, SimGyro
from hardware.sim.slip import (
    Encoders,
    SlipModel,
    SlipTruth,
    proposed_localizer_settings,
    wheel_slip_coefficients,
)
from hardware.sim.tag_camera import SimTagCamera, TagCameraConfig
from hardware.sim.user import ConstantPush, RouteFollower, UserParams, UserProfile
from hardware.sim.world import COLLISION_BAND_M, World
from hardware.source import PROPOSED_SETTINGS

# Walker parts in the walker frame (x forward, y left; rear-axle origin), from thesis
# Table 3.1 (a Dolomite Legacy rollator): 0.745 m long; the frame is 0.56 m wide at the
# rear struts and narrows to 0.50 m at the front castors (front wheel track 0.45 m plus
# the castors); the rear wheels (204 mm, contact track 0.68 m) stick out 6.5 cm beyond
# the frame on each side (0.69 m overall), which the thesis blames for the rear-wheel
# collisions that dominate its Table 6.3.
FRAME_POLYGON = np.array([[-0.10, -0.28], [0.64, -0.25], [0.64, 0.25], [-0.10, 0.28]])
LEFT_WHEEL_POLYGON = np.array([[-0.102, 0.28], [0.102, 0.28], [0.102, 0.345], [-0.102, 0.345]])
RIGHT_WHEEL_POLYGON = LEFT_WHEEL_POLYGON * np.array([1.0, -1.0])
WALKER_PARTS = (
    ("frame", FRAME_POLYGON),
    ("left-wheel", LEFT_WHEEL_POLYGON[::-1]),
    ("right-wheel", RIGHT_WHEEL_POLYGON),
)
# The heights each part occupies: the frame (tubing, castors, the laptop platform, the
# handles at 0.91 m) spans the whole band; a rear wheel reaches only its own diameter, so
# it passes under a table top or a chair seat and catches on their legs.
PART_BANDS_M = {
    "frame": COLLISION_BAND_M,
    "left-wheel": (0.0, 0.21),
    "right-wheel": (0.0, 0.21),
}
# A contact with an obstacle starts a new contact episode only after this long clear of it.
COLLISION_REARM_S = 3.0
# A collision, as the thesis counted them (§6.4), is "an event in which contact with the
# environment significantly altered or impeded the movement of the user"; "minor scrapes
# against obstacles were not counted". A contact episode becomes a collision when the
# contact removes at least SIGNIFICANT_BUMP_MPS of its point's velocity into the obstacle
# in one step (a bump: the walker is jolted or deflected), or when it holds the walker
# below HELD_SPEED_MPS for HELD_S in all (the motion is impeded). A contact that does
# neither (a glancing scrape, sliding along an edge) is a scrape (`Simulator.scrapes`).
SIGNIFICANT_BUMP_MPS = 0.1
HELD_SPEED_MPS = 0.05
HELD_S = 0.5
# Farthest point of the walker from the rear-axle centre: bounds how far any part of it
# can move for a given (v, φ̇).
WALKER_REACH_M = float(max(np.hypot(*p.T).max() for _, p in WALKER_PARTS))
# Clearance looked for around the walker after a contact-free step.
CLEARANCE_HORIZON_M = 0.3


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated trial besides the world.

    Rates must divide physics_rate_hz. The software's calibration is the true walker
    plus the *_error_m values (the thesis code used a 203 mm wheel; it measures 204 mm).
    wheel_diameter_ratio_error: the true walker's right wheel is (1 + this) times its
    left wheel in diameter (their mean is walker.wheel_diameter_m), while the software
    believes them equal; 0: equal wheels, as before the option existed.
    user_profile: this trial's user (route offset and wander, push, impairment; see
    `UserProfile`) applied to `user` and the world's route; None: `user` on the route.
    gyro: the simulated yaw-rate gyro (`hardware.sim.gyro`), off by default; its draws
    come from a seed stream of their own, so switching it on changes no other sensor.
    slip_scale: (left, right) factors of the surface's slip coefficient per wheel
    (`hardware.sim.slip`); (1, 1): both wheels slip alike.
    start_still_s: the user stands still at the start for this long before walking (a
    real trial's start: the walker at rest while the experimenter starts the recording,
    which is when a gyro can learn its turn-on bias free of encoder noise); 0: they walk
    at once, as before the option existed.
    """

    surface: str | float = "dusty"
    seed: int = 0
    duration_s: float = 300.0
    physics_rate_hz: int = 200
    encoder_rate_hz: int = 50
    depth_rate_hz: int = 10
    tag_rate_hz: int = 10
    groundtruth_rate_hz: int = 50
    depth_width: int = 160
    depth_height: int = 120
    wheel_diameter_error_m: float = -0.001
    track_error_m: float = 0.0
    wheel_diameter_ratio_error: float = 0.0
    walker: WalkerParams = field(default_factory=WalkerParams)
    user: UserParams = field(default_factory=UserParams)
    user_profile: UserProfile | None = None
    depth: DepthCameraConfig = field(default_factory=DepthCameraConfig)
    tags: TagCameraConfig = field(default_factory=TagCameraConfig)
    gyro: GyroSimConfig = field(default_factory=GyroSimConfig)
    slip_scale: tuple[float, float] = (1.0, 1.0)
    start_still_s: float = 0.0

    def __post_init__(self) -> None:
        wheel_slip_coefficients(self.surface, self.slip_scale)
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"duration must be > 0 s, got {self.duration_s}")
        if not (math.isfinite(self.start_still_s) and 0 <= self.start_still_s < self.duration_s):
            raise ValueError(
                f"start_still_s must be >= 0 and shorter than the trial, got {self.start_still_s}"
            )
        for name in ("encoder_rate_hz", "depth_rate_hz", "tag_rate_hz", "groundtruth_rate_hz"):
            rate = getattr(self, name)
            if rate <= 0 or self.physics_rate_hz % rate:
                raise ValueError(
                    f"{name}={rate} must divide physics_rate_hz={self.physics_rate_hz}"
                )
        if self.physics_rate_hz % self.gyro.rate_hz:
            raise ValueError(
                f"gyro.rate_hz={self.gyro.rate_hz} must divide physics_rate_hz="
                f"{self.physics_rate_hz}"
            )
        if self.physics_rate_hz < 200:
            raise ValueError("physics_rate_hz must be >= 200")
        if not (
            math.isfinite(self.wheel_diameter_ratio_error) and self.wheel_diameter_ratio_error > -1
        ):
            raise ValueError(
                f"wheel_diameter_ratio_error must be > -1, got {self.wheel_diameter_ratio_error}"
            )

    def to_dict(self) -> dict:
        return asdict(self)

    def true_wheel_diameters_m(self) -> tuple[float, float]:
        """(left, right) diameters of the true walker's wheels."""
        return wheel_diameters(self.walker.wheel_diameter_m, 1.0 + self.wheel_diameter_ratio_error)

    def calibration(self) -> WalkerCalibration:
        """What the walker's software believes (encoders, track, cameras)."""
        w = self.walker
        base = WalkerCalibration()
        hfov = 2 * math.atan(base.depth_intrinsics.width / 2 / base.depth_intrinsics.fx)
        vfov = 2 * math.atan(base.depth_intrinsics.height / 2 / base.depth_intrinsics.fy)
        return replace(
            base,
            wheel_diameter_m=w.wheel_diameter_m + self.wheel_diameter_error_m,
            track_m=2 * w.half_track_m + self.track_error_m,
            depth_intrinsics=CameraIntrinsics.from_fov(
                self.depth_width, self.depth_height, hfov, vfov
            ),
        )


@dataclass
class _ContactEpisode:
    """Contact with one obstacle since it began: whether it became a collision yet and
    how long it has held the walker."""

    significant: bool = False
    held_s: float = 0.0


class Simulator:
    """A walker in a world, pushed by a user; see the module docstring.

    calibration: what the walker's software believes (default `config.calibration()`,
    the true walker plus the configured errors); the simulated sensors are the truth.
    """

    def __init__(
        self,
        world: World,
        config: SimConfig,
        user: RouteFollower | ConstantPush | None = None,
        calibration: WalkerCalibration | None = None,
    ):
        self.world = world
        self.config = config
        self.calibration = calibration or config.calibration()
        # one stream per part; the gyro's is the fifth and the user's sight the sixth,
        # so the first four are as before either was added
        seeds = np.random.SeedSequence(config.seed).spawn(6)
        rng_slip, rng_user, rng_depth, rng_tags, rng_gyro, rng_vision = (
            np.random.default_rng(s) for s in seeds
        )
        w = config.walker
        x0, y0, th0 = world.start_pose
        self.state = WalkerState(x=x0, y=y0, phi=th0)
        self.brakes = Brakes(w)
        self.slip = SlipModel(
            config.surface,
            w.brake_torque_max_nm / w.wheel_radius_m,
            rng_slip,
            wheel_scale=config.slip_scale,
        )
        self.slip_truth = SlipTruth()
        self._brake_level = (0.0, 0.0)  # of the last command, as the localizers read it
        # The encoders turn with the *true* wheels; counts_per_rev as calibrated.
        self.encoders = Encoders(config.true_wheel_diameters_m(), self.calibration.counts_per_rev)
        self.user = user or self._route_follower(rng_user, rng_vision)
        self.depth_camera = SimDepthCamera(world, self.calibration, config.depth, rng_depth)
        self.tag_camera = SimTagCamera(world, self.calibration, config.tags, rng_tags)
        self.gyro = SimGyro(config.gyro, rng_gyro) if config.gyro.enabled else None
        self.dt = 1.0 / config.physics_rate_hz
        self.steps = 0
        self._started = False  # the sensors at t = 0 were returned
        self._every = {
            name: config.physics_rate_hz // getattr(config, f"{name}_rate_hz")
            for name in ("encoder", "depth", "tag", "groundtruth")
        }
        self._every["gyro"] = config.physics_rate_hz // config.gyro.rate_hz
        self._last_contact: dict[str, float] = {}
        self._episodes: dict[str, _ContactEpisode] = {}
        self.scrapes = 0  # contact episodes that never became collisions
        # Distance the walker may still move before it could touch anything.
        self._free_travel_m = 0.0
        self.last_slip = (0.0, 0.0)

    def _route_follower(
        self, rng: np.random.Generator, rng_vision: np.random.Generator
    ) -> RouteFollower:
        """The simulated user of the config (its profile applied) on the world's route,
        seeing what the world shows above their sight's lowest height."""
        world, config = self.world, self.config
        params, route = replace(config.user, **world.user), world.route
        if config.user_profile is not None:
            params = config.user_profile.apply(params)
            route = config.user_profile.walk_route(route)
        sight = (
            world.footprint_polygons(params.vision.min_height_m, COLLISION_BAND_M[1])
            if params.vision is not None
            else None
        )
        return RouteFollower(
            route, self.state, config.walker, params, rng, sight, rng_vision, world.route
        )

    @property
    def t(self) -> float:
        return self.steps * self.dt

    @property
    def done(self) -> bool:
        return self.user.finished or self.t >= self.config.duration_s - 1e-9

    @property
    def metadata(self) -> dict[str, Any]:
        """The world with its true obstacles and tags, the simulation config, and the
        odometry noise of the simulated encoders that the trial proposes to localizers;
        with the gyro, its drawn turn-on bias and scale error ("gyro": the truth an
        estimate of them is scored against)."""
        meta = {
            "world": self.world.to_dict(),
            "sim": self.config.to_dict(),
            PROPOSED_SETTINGS: proposed_localizer_settings(self.config.surface),
        }
        if self.gyro is not None:
            meta["gyro"] = {
                "part": "InvenSense MPU-6050 (simulated)",
                "turn_on_bias_rad_s": self.gyro.turn_on_bias,
                "scale_error": self.gyro.scale_error,
            }
        return meta

    def slip_summary(self) -> dict[str, Any]:
        """The true slip of the run so far (`hardware.sim.slip`): each wheel's k at full
        brake force (k_surface × slip_scale), the effective k per unit commanded brake
        level that the localizers estimate (None for a wheel never braked), and the
        ground distance each wheel rolled braked. Written to a trial log's metadata
        "slip" when the run ends."""
        return {
            "k_wheel": list(self.slip.k_wheel),
            "k_effective": list(self.slip_truth.effective_k()),
            "braked_distance_m": list(self.slip_truth.braked_m),
        }

    def pose(self) -> np.ndarray:
        return np.array([self.state.x, self.state.y, self.state.phi])

    def send(self, cmd: BrakeCommand) -> None:
        """Set the brake command; torques pass through the board's PWM quantisation."""
        cal = self.calibration.brake
        self.brakes.set_command(cal.torque(cal.pwm(cmd.left_nm)), cal.torque(cal.pwm(cmd.right_nm)))
        self._brake_level = (cal.level(cmd.left_nm), cal.level(cmd.right_nm))

    def poll(self, until: float, stop_at_frame: bool = False) -> list[Message]:
        """Advance to `until` (or until done) and return the messages that fell due;
        stop_at_frame: stop after the physics step that produced a depth frame."""
        out: list[Message] = []
        if self.steps == 0 and not self._started:
            self._started = True
            out.extend(self._sensors(first=True))
            if stop_at_frame:
                return out  # the first depth frame is among them
        while self.t + 0.5 * self.dt < until and not self.done:
            self._physics_step(out)
            sensors = self._sensors()
            out.extend(sensors)
            if stop_at_frame and any(isinstance(m, DepthFrame) for m in sensors):
                break
        return out

    def messages(self, step_s: float = 0.1) -> Iterator[Message]:
        """Run open loop (the brakes as last sent) to the end, `step_s` at a time."""
        while not self.done:
            yield from self.poll(self.t + step_s)

    def close(self) -> None:
        """Nothing to release."""

    # -- internals --------------------------------------------------------------------
    def _physics_step(self, out: list[Message]) -> None:
        w, s, dt = self.config.walker, self.state, self.dt
        if self.t < self.config.start_still_s:
            handle_l, handle_r = 0.0, 0.0  # the user waits at the start
        else:
            handle_l, handle_r = self.user.forces(s, dt)
        self.brakes.step(dt)
        wl, wr = s.wheel_speeds(w.half_track_m)
        f_bl, f_br = self.brakes.ground_forces(wl, wr)
        phi = s.phi
        step(s, w, handle_l, handle_r, f_bl, f_br, dt)
        self.steps += 1
        if self.gyro is not None:
            self.gyro.turn(math.remainder(s.phi - phi, 2.0 * math.pi), dt)
        wl, wr = s.wheel_speeds(w.half_track_m)
        self.last_slip = self.slip.step(dt, (f_bl, f_br))
        self.encoders.roll(wl * dt, wr * dt, self.last_slip)
        self.slip_truth.add((wl * dt, wr * dt), self.last_slip, self._brake_level)
        self._collide(out)

    def _parts_in_world(self) -> list[tuple[str, np.ndarray]]:
        c, sn = math.cos(self.state.phi), math.sin(self.state.phi)
        rot = np.array([[c, -sn], [sn, c]])
        off = np.array([self.state.x, self.state.y])
        return [(name, poly @ rot.T + off) for name, poly in WALKER_PARTS]

    def _parts_by_band(self) -> dict[tuple[float, float], list[tuple[str, np.ndarray]]]:
        """The walker's parts in the world, grouped by the height band they occupy."""
        out: dict[tuple[float, float], list[tuple[str, np.ndarray]]] = {}
        for name, poly in self._parts_in_world():
            out.setdefault(PART_BANDS_M[name], []).append((name, poly))
        return out

    def _collide(self, out: list[Message]) -> None:
        s = self.state
        # Broad phase: no part can have moved farther than |v|dt + |φ̇|dt·reach, so while
        # the walker's clearance is not used up there is nothing to check.
        self._free_travel_m -= (abs(s.v) + abs(s.omega) * WALKER_REACH_M) * self.dt
        if self._free_travel_m > 0.0:
            self.user.touching(s, None, self.dt)
            return
        bands = self._parts_by_band()
        clearance = CLEARANCE_HORIZON_M
        for band, parts in bands.items():
            polys = self.world.polygon_set(*band)
            gap = polys.least_gap(np.array([p for _, p in parts]), CLEARANCE_HORIZON_M)
            clearance = min(clearance, gap)
        # (0: a part may touch an obstacle; the contacts tell)
        contacts = []
        if clearance == 0.0:
            contacts = [
                c for band, parts in bands.items() for c in self.world.contacts(parts, *band)
            ]
        if not contacts:
            self.user.touching(s, None, self.dt)
            self._free_travel_m = clearance
            return
        moved = np.zeros(2)
        contacts = sorted(contacts, key=lambda c: -c.depth)
        self.user.touching(s, np.asarray(contacts[0].point, float), self.dt)
        held: set[str] = set()
        for c in contacts:
            # Push the walker out of the obstacle (less what earlier pushes already did
            # along this normal: two parts touching one wall are pushed once), then remove
            # the contact point's velocity into it with the least-effort (mass/inertia-
            # weighted) change of (v, φ̇): an inelastic contact that respects the rear
            # axle's no-sideways constraint.
            normal = np.asarray(c.normal, float)
            push = max(c.depth - float(moved @ normal), 0.0)
            moved += push * normal
            s.x += push * normal[0]
            s.y += push * normal[1]
            point = np.asarray(c.point, float)
            bump = self._contact_impulse(point, normal)
            episode = self._episode(c.obstacle, point)
            if c.obstacle not in held and abs(s.v) < HELD_SPEED_MPS:
                held.add(c.obstacle)
                episode.held_s += self.dt
            if not episode.significant and (
                bump >= SIGNIFICANT_BUMP_MPS or episode.held_s >= HELD_S
            ):
                episode.significant = True
                self.scrapes -= 1
                out.append(
                    Collision(self.t, self._kind(c.part, c.normal), c.obstacle, *point.tolist())
                )
                self.user.on_collision(s, point)

    def _episode(self, obstacle: str, point: np.ndarray) -> _ContactEpisode:
        """The contact episode with `obstacle` this contact belongs to: a new one (felt by
        the user as a scrape until it proves significant) after COLLISION_REARM_S clear."""
        last = self._last_contact.get(obstacle, -math.inf)
        self._last_contact[obstacle] = self.t
        if self.t - last > COLLISION_REARM_S or obstacle not in self._episodes:
            self._episodes[obstacle] = _ContactEpisode()
            self.scrapes += 1
            self.user.on_scrape(self.state, point)
        return self._episodes[obstacle]

    def _contact_impulse(self, point: np.ndarray, normal: np.ndarray) -> float:
        """Remove the contact point's velocity into the obstacle; returns that speed."""
        s, w = self.state, self.config.walker
        heading = np.array([math.cos(s.phi), math.sin(s.phi)])
        r = point - np.array([s.x, s.y])
        # contact-point velocity along the normal: J · (v, φ̇)
        jac = np.array([heading @ normal, -r[1] * normal[0] + r[0] * normal[1]])
        approach = jac[0] * s.v + jac[1] * s.omega
        if approach >= 0.0:
            return 0.0
        inv_mass = np.array([1.0 / w.mass_kg, 1.0 / w.yaw_inertia])
        denom = float(jac @ (inv_mass * jac))
        if denom <= 1e-12:
            return 0.0
        impulse = -approach / denom
        s.v += impulse * inv_mass[0] * jac[0]
        s.omega += impulse * inv_mass[1] * jac[1]
        return float(-approach)

    def _kind(self, part: str, normal: np.ndarray) -> str:
        if part.endswith("wheel"):
            return "rear-wheel"
        c, sn = math.cos(self.state.phi), math.sin(self.state.phi)
        normal_forward = c * normal[0] + sn * normal[1]
        # Pushed back (normal against the heading) means the front struck the obstacle.
        return "front" if normal_forward < -0.7 else "side"

    def _sensors(self, first: bool = False) -> list[Message]:
        out: list[Message] = []
        t, k = self.t, self.steps
        e = self._every
        if first or k % e["groundtruth"] == 0:
            s = self.state
            out.append(GroundTruthPose(t, s.x, s.y, s.phi))
        # the gyro before the encoders of the same instant: a localizer integrates the
        # rate up to the ticks' time
        if self.gyro is not None and (first or k % e["gyro"] == 0):
            out.append(GyroRate(t, self.gyro.sample()))
        if first or k % e["encoder"] == 0:
            left, right = self.encoders.counts()
            out.append(EncoderTicks(t, left, right))
        if first or k % e["depth"] == 0:
            depth = self.depth_camera.render(self.pose())
            out.append(DepthFrame(t, depth, self.calibration.depth_intrinsics))
        if first or (k + e["tag"] // 2) % e["tag"] == 0:
            out.append(TagDetections(t, tuple(self.tag_camera.detect(self.pose()))))
        return out
