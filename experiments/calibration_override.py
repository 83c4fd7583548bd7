"""`--calibration FILE` of replay, compare, simulate and live --sim: the software's
odometry calibration from a file (e.g. written by `walkerslam calibrate`) instead of the
log's or the simulated walker's.

The file's wheel diameters and track replace the log's (`hardware.calibration.
ODOMETRY_FIELDS`); the cameras, brakes and encoder resolution stay the log's, since the
recorded frames and counts were made with them (a file for other encoders is an error).
Each run records the file and what it replaced in its config.json (`record`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hardware.calibration import (
    WalkerCalibration,
    load_calibration,
    odometry_fields,
    with_odometry,
)


@dataclass(frozen=True)
class CalibrationOverride:
    """A calibration file whose odometry replaces a log's."""

    path: str
    calibration: WalkerCalibration

    @classmethod
    def load(cls, path: str | Path | None) -> CalibrationOverride | None:
        """The file's calibration (a one-line ConfigError for a bad file); None: none."""
        if path is None:
            return None
        return cls(str(path), load_calibration(path))

    def apply(self, calibration: WalkerCalibration) -> WalkerCalibration:
        """`calibration` with this file's wheel diameters and track."""
        return with_odometry(calibration, self.calibration, self.path)

    def record(self, replaced: WalkerCalibration) -> dict[str, Any]:
        """What config.json says about it: the file, its values and those they replaced."""
        return {
            "file": self.path,
            "odometry": odometry_fields(self.calibration),
            "replaced": odometry_fields(replaced),
        }


def applied(
    override: CalibrationOverride | None, calibration: WalkerCalibration
) -> tuple[WalkerCalibration, dict[str, Any] | None]:
    """The calibration to run with and config.json's record of the override (None when
    there is none)."""
    if override is None:
        return calibration, None
    return override.apply(calibration), override.record(calibration)
