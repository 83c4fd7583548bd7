"""GTSAM factor helpers both halves of the smoother use (slam.gtsam_smoother and
slam.scan_graph): the robust kernel a factor's noise is wrapped in, and the GPS-like
factor of a position fix. The slip factors are in slam.gtsam_slip."""

from __future__ import annotations

import gtsam
import numpy as np

from hardware.choices import Choice
from slam.absolute import offset_position, offset_position_jacobian


class RobustKernel(Choice):
    """The M-estimator of a robust factor (gtsam.noiseModel.mEstimator), or none."""

    HUBER = "huber"
    CAUCHY = "cauchy"
    NONE = "none"


def robust_noise(kind: str, k: float, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """base, robust with the M-estimator `kind` (RobustKernel) at k, or base itself."""
    if kind == "none":
        return base
    est = (
        gtsam.noiseModel.mEstimator.Huber.Create(k)
        if kind == "huber"
        else gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    )
    return gtsam.noiseModel.Robust.Create(est, base)


def position_factor(
    key: int, z: np.ndarray, offset: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """A GPS-like factor on Pose2 `key`: the map-frame position of the point `offset`
    (dx, dy) in the pose's frame is measured as z; error = position − z, with the
    Jacobian of slam.absolute.offset_position_jacobian (checked numerically in the
    tests). With offset 0 it is gtsam.PoseTranslationPrior2D."""
    z = np.array(z, dtype=float)
    offset = np.array(offset, dtype=float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        p = values.atPose2(this.keys()[0])
        pose = np.array([p.x(), p.y(), p.theta()])
        if jacobians is not None:
            jacobians[0] = offset_position_jacobian(pose, offset)
        return offset_position(pose, offset) - z

    return gtsam.CustomFactor(noise, [key], error)
