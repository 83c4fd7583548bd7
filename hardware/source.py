"""The source and sink contract: where messages come from and where brake commands go.

A **source** has the walker's calibration, its metadata ({name: dict}, strict JSON, as a
trial log stores it), an iterator of messages in time order, and `close()`. A trial
log (`hardware.log.TrialLog`), a public dataset (`hardware.datasets.Dataset`), the
simulator (`hardware.sim.simulator.Simulator`) and every live device (the serial board,
the depth and tag cameras) are sources; several merge by timestamp
(`hardware.messages.merge`, or `hardware.live.LiveSources` for devices that deliver in
real time).

A **timed source** also runs on a clock that the closed loop advances: `poll(until)`
returns the messages up to `until` on its clock, and `done` says it has ended. The
simulator steps its physics to `until`; a set of live devices waits until the host
clock reaches `until` and returns what arrived.

A **command sink** takes brake commands: the serial board live, the simulator in
simulation (`send` sets its brakes), a recorder in replay.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Protocol, runtime_checkable

from hardware.calibration import WalkerCalibration
from hardware.messages import BrakeCommand, Message

# The metadata record in which a source proposes localizer settings ({config field path:
# value}), e.g. a dataset's fitted noise levels or a simulated trial's encoder noise;
# replay applies them before the user's --set (experiments.config).
PROPOSED_SETTINGS = "localizer_settings"
# ... and the one in which it proposes the occupancy mapper's settings (e.g. a laser's
# usable range: CARMEN logs read to 80 m), applied where the caller left the default
PROPOSED_MAPPER_SETTINGS = "mapper_settings"


@runtime_checkable
class Source(Protocol):
    """Messages in time order, with the calibration and metadata they were taken with."""

    @property
    def calibration(self) -> WalkerCalibration: ...

    @property
    def metadata(self) -> dict[str, Any]: ...

    def messages(self) -> Iterator[Message]:
        """The messages in time order (a recorded source may be iterated again)."""
        ...

    def close(self) -> None:
        """Release the source; a live source's `messages()` iterator then ends."""
        ...


@runtime_checkable
class TimedSource(Source, Protocol):
    """A source the closed loop runs in time (the simulator, live devices)."""

    @property
    def t(self) -> float:
        """The source's clock [s]: everything up to it has been delivered."""
        ...

    @property
    def done(self) -> bool:
        """The source has ended (the simulated user finished, a live run was stopped)."""
        ...

    def poll(self, until: float, stop_at_frame: bool = False) -> list[Message]:
        """Advance the clock to `until` (or until done) and return the messages that fell
        due, in time order. stop_at_frame: return early, as soon as a depth frame or a
        laser scan is among them (a frame-triggered control loop)."""
        ...


@runtime_checkable
class CommandSink(Protocol):
    """Takes brake commands (torque per wheel, N·m)."""

    def send(self, cmd: BrakeCommand) -> None: ...

    def close(self) -> None:
        """Release: a live sink sends zero brake torque before it lets go."""
        ...
