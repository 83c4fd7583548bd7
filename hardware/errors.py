"""The project's errors: one root, `WalkerSlamError`, with a class per kind below it.

Every error that a user's input can cause — a bad log or dataset file, a bad option or
config value, an unknown name, a device that cannot be used — is a `WalkerSlamError`
whose message is one line naming the file or the value and what is wrong. The CLI
prints those (and an `OSError` about a user's file) as `error: …` and exits 2; anything
else is a bug and keeps its traceback. The kinds also subclass `ValueError`, so code
written against the earlier `ValueError`s still catches them.
"""

from __future__ import annotations


class WalkerSlamError(ValueError):
    """Root of walker-slam's errors; str() is one line naming what is wrong."""


class LogError(WalkerSlamError):
    """A trial log that cannot be read or written (hardware.log)."""


class DatasetError(WalkerSlamError):
    """A dataset file or option that cannot be used (hardware.datasets)."""


class ConfigError(WalkerSlamError):
    """A config value, a --set, an option or a combination of options that is invalid."""


class UnknownNameError(WalkerSlamError):
    """A name that is not registered (a localizer, controller, course, dataset format,
    device); the message lists the valid names."""

    def __init__(self, kind: str, name: str, valid: list[str]) -> None:
        super().__init__(f"unknown {kind} '{name}'; valid: {', '.join(valid)}")
        self.valid = valid


class DeviceError(WalkerSlamError):
    """A live device that cannot be used: missing, not answering, the wrong firmware,
    failed during a run (hardware.arduino, hardware.depth, hardware.tags, hardware.live)."""


class CalibrationError(WalkerSlamError):
    """A calibration run that cannot be used: no laps of a square found, only one
    direction, an estimate that does not settle (slam.umbmark, experiments.calibrate)."""
