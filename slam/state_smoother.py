"""Rauch–Tung–Striebel smoothing of a SLAM filter's whole state: EKF-SLAM's
(`smoother="rts-full"`) and FastSLAM's particles summarised by their moments.

The pose-only smoother (slam.rts) treats the landmark updates of different times as
independent. In SLAM they are not: a landmark mapped while the heading was wrong drags
every later pose that sees it, and the filter's final map — built from all the data —
is far better than the map each pose was filtered against (MRCLAM: the poses filtered
against the map of their time are 0.19 m off on robot 1, and 0.06 m off when relocalized
in the final map). Smoothing the whole state carries the final map back to every pose.

An *epoch* is what the filter does between two predictions: the updates of one time.
At its start the filter records (`begin`) the filtered state of the epoch before (x_e,
P_e, unchanged since its last update) and the prediction from it: the predicted top of
the state (the pose, or the pose and what moves with it: slip coefficients) x⁻, and
how the prediction relates to x_e, as either

- the pose rows of a linearised transition F (EKF-SLAM: `begin`; the rest of F is the
  identity: landmarks are static; x, y depend on θ through a, b, and on the slip
  coefficients through B) with the predicted top block, which the filter computed with
  its own process noise; or
- the moments themselves (FastSLAM: `begin_sampled`, from its particles: statistical
  linearisation), the cross-covariance C = Cov(x_e, top⁻) and the rows of the predicted
  covariance Cov(top⁻, x⁻) — the landmarks do not move, so these are all that differ
  from P_e. For the linear form, C = P_e Fᵀ's top columns and the rows (F P_e Fᵀ)'s,
  with the top block replaced by the predicted one.

Then, backwards from the last epoch (x^s = the filtered state),

    x⁻_{e+1} = x_e with its top replaced by the predicted one,  P⁻ = P_e with the top's
               rows and columns replaced,  G_e = C (P⁻)⁻¹ (C = P_e with the top columns
               replaced),
    x^s_e = x_e + G_e (x^s_{e+1}[:n_e] − x⁻_{e+1}),

where x^s_{e+1}[:n_e] leaves out the landmarks first seen in epoch e + 1 (the smoothed
marginal of the older ones). The heading differences are wrapped (and a tag landmark's
yaw, `landmark_dim=3`).

Between two epochs the walker moved on odometry alone: `bridge` takes each stretch's
filtered poses moved rigidly onto the smoothed pose of the epoch that starts it, their
covariance grown from zero there (`bridge_covariances`), and the pose-only smoother
(slam.rts.rts_smooth) then spreads the mismatch with the next epoch's smoothed pose
over the stretch by the odometry's uncertainty; an epoch's pose, known, stays. An
observation placed inside an odometry step (`align_observations`) makes an epoch that
leads to the step recorded after it (`epoch_step`): the rest of that step's odometry
moved its corrected pose there, while the step before it still has the pose from before
the correction (anchored there, the path would step back by the correction).

Memory: one n × n covariance per epoch (n = 3 + 2 · landmarks): MRCLAM's robots, 15
landmarks and ~2500 epochs, ~22 MB; Victoria Park's hundreds of trees would take
gigabytes (its whole log went past 512 MB at step 9745). So the epochs are kept within a
budget (`budget_bytes`): past it they are dropped, `exceeded` holds the step of the
epoch that would have gone over, and the filter falls back to its other smoother for
the whole run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from hardware.geometry import between, compose, wrap_angle
from slam.rts import arc_steps


@dataclass
class _Epoch:
    step: int  # the trajectory's step the epoch's updates corrected
    top_mean: np.ndarray  # the predicted top of the state (pose, or pose and k)
    # linear (EKF-SLAM): the prediction's pose rows of F and the predicted top block
    a: float = 0.0  # ∂x/∂θ and ∂y/∂θ of the prediction into this epoch
    b: float = 0.0
    bk: np.ndarray | None = None  # ∂(x, y, θ)/∂k (3 × 2) with slip estimation
    top_cov: np.ndarray | None = None
    # sampled (FastSLAM): Cov(x_e, top⁻) (n_e × t) and Cov(top⁻, x⁻) (t × n_e)
    cross: np.ndarray | None = None
    pred_rows: np.ndarray | None = None
    x: np.ndarray | None = None  # the filtered state at the epoch's end (set later)
    p: np.ndarray | None = None


class StateSmoother:
    """The epochs of a run and their full-state RTS smoothing (module docstring). top:
    the size of the block the odometry moves (3, or 5 with slip); landmark_dim: 2 (u, v)
    or 3 (u, v and a tag's yaw, wrapped like the heading)."""

    def __init__(self, top: int, budget_bytes: float, landmark_dim: int = 2) -> None:
        self.top = top
        self.budget_bytes = budget_bytes
        self.landmark_dim = landmark_dim
        self.epochs: list[_Epoch] = []
        self.kept_bytes = 0
        self.exceeded: int | None = None  # the step at which the budget ran out

    def begin(self, step, x, p, a, b, bk, top_mean, top_cov) -> None:
        """A new epoch at `step`: (x, p) is the filtered state the prediction started
        from (the last epoch's, or the initial state), a, b, bk the prediction's pose rows
        of F, top_mean / top_cov the predicted top block (all copied)."""
        bk = None if bk is None else np.array(bk, dtype=float)
        top_cov = np.array(top_cov, dtype=float)
        self._add(x, p, _Epoch(step, np.array(top_mean, float), a, b, bk, top_cov))

    def begin_sampled(self, step, x, p, top_mean, cross, pred_rows) -> None:
        """A new epoch at `step` from moments: (x, p) the filtered state the prediction
        started from, top_mean the predicted top, cross = Cov(x, top⁻) (n × top) and
        pred_rows = Cov(top⁻, x⁻) (top × n; its first block the predicted top's)."""
        cross, rows = np.array(cross, dtype=float), np.array(pred_rows, dtype=float)
        self._add(x, p, _Epoch(step, np.array(top_mean, float), cross=cross, pred_rows=rows))

    def _add(self, x, p, epoch: _Epoch) -> None:
        if self.exceeded is not None:
            return
        if self.epochs:
            self.kept_bytes += x.nbytes + p.nbytes
            if epoch.cross is not None:
                self.kept_bytes += epoch.cross.nbytes + epoch.pred_rows.nbytes
            if self.kept_bytes > self.budget_bytes:
                self.exceeded, self.epochs = epoch.step, []
                return
            self.epochs[-1].x, self.epochs[-1].p = x.copy(), p.copy()
        self.epochs.append(epoch)

    def smoothed(
        self, x_last: np.ndarray, p_last: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(steps (E,), smoothed poses (E, 3), filtered poses (E, 3)) of the epochs; x_last,
        p_last: the filter's state now (the last epoch's end)."""
        if not self.epochs:
            return np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3))
        ep = self.epochs
        xs = [e.x for e in ep[:-1]] + [x_last]
        ps = [e.p for e in ep[:-1]] + [p_last]
        poses = np.empty((len(ep), 3))
        filtered = np.array([x[:3] for x in xs])
        nxt = np.asarray(x_last, dtype=float).copy()
        poses[-1] = nxt[:3]
        for i in range(len(ep) - 2, -1, -1):
            nxt = self._back(xs[i], ps[i], ep[i + 1], nxt)
            poses[i] = nxt[:3]
        return np.array([e.step for e in ep]), poses, filtered

    def _back(self, x: np.ndarray, p: np.ndarray, move: _Epoch, nxt: np.ndarray) -> np.ndarray:
        """One backward step: the smoothed state of an epoch from its filtered (x, p),
        the prediction `move` into the next epoch and that epoch's smoothed state."""
        n, t = len(x), self.top
        cross, rows = self._prediction(p, move)
        p_pred = p.copy()
        p_pred[:t] = rows
        p_pred[:, :t] = rows.T
        p_pred[np.diag_indices(n)] += 1e-12 * np.trace(p_pred) / n + 1e-18
        c = p.copy()
        c[:, :t] = cross
        x_pred = x.copy()
        x_pred[:t] = move.top_mean
        angles = self._angles(n)
        d = nxt[:n] - x_pred
        d[angles] = wrap_angle(d[angles])
        out = x + c @ np.linalg.solve(p_pred, d)  # G d, G = C (P⁻)⁻¹
        out[angles] = wrap_angle(out[angles])
        return out

    def _prediction(self, p: np.ndarray, move: _Epoch) -> tuple[np.ndarray, np.ndarray]:
        """(C's top columns, P⁻'s top rows) of the prediction into `move`."""
        if move.cross is not None:
            return move.cross, move.pred_rows
        n, t = len(p), self.top
        f_top = np.zeros((3, n))  # the pose rows of F − I
        f_top[0, 2], f_top[1, 2] = move.a, move.b
        if move.bk is not None:
            f_top[:, 3:5] = move.bk
        fp = p[:t].copy()  # the top rows of F P
        fp[:3] += f_top @ p
        rows = fp.copy()  # the top rows of F P Fᵀ
        rows[:, :3] += fp @ f_top.T
        rows[:, :t] = move.top_cov
        return fp.T, rows

    def _angles(self, n: int) -> np.ndarray:
        """The state's angles: the heading, and a tag landmark's yaw."""
        if self.landmark_dim != 3:
            return np.array([2])
        return np.r_[2, np.arange(self.top + 2, n, 3)]


def epoch_step(recorded: int, between: bool) -> int:
    """The trajectory step an epoch's updates lead to, `recorded` steps so far: the last
    one, or (between: an observation made after it, align_observations) the next."""
    return recorded if between else max(recorded - 1, 0)


class StepOdometry:
    """The odometry of each recorded step, for the smoothers: the increments (ds, dθ and
    their 2×2 covariance q) since the step before, summed over the messages, or the parts
    of one split around an observation, that made it."""

    def __init__(self) -> None:
        self._open = [0.0, 0.0, 0.0, 0.0, 0.0]  # ds, dθ, q00, q01, q11
        self._steps: list[list[float]] = []

    def __len__(self) -> int:
        return len(self._steps)

    def add(self, ds: float, dtheta: float, q: np.ndarray) -> None:
        """Add an increment to the step being recorded."""
        add = (ds, dtheta, float(q[0, 0]), float(q[0, 1]), float(q[1, 1]))
        self._open = [a + b for a, b in zip(self._open, add, strict=True)]

    def close(self, new_step: bool) -> None:
        """The step was recorded: a new one, or the last one again (the same time)."""
        if new_step or not self._steps:
            self._steps.append(self._open)
        else:
            self._steps[-1] = [a + b for a, b in zip(self._steps[-1], self._open, strict=True)]
        self._open = [0.0, 0.0, 0.0, 0.0, 0.0]

    def deltas(self) -> tuple[np.ndarray, np.ndarray]:
        """(deltas (K, 3), their covariances (K, 3, 3)) of the steps (slam.rts.arc_steps)."""
        inc = np.array(self._steps, dtype=float).reshape(-1, 5)
        return arc_steps(inc[:, 0], inc[:, 1], inc[:, [2, 3, 3, 4]].reshape(-1, 2, 2))


def bridge(
    filtered: np.ndarray,
    covs: np.ndarray,
    deltas: np.ndarray,
    delta_covs: np.ndarray,
    steps: np.ndarray,
    smoothed: np.ndarray,
    filtered_at: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The means and covariances to run the pose-only smoother on (module docstring):
    from each epoch's step on (steps (E,) ascending, its smoothed pose and its own
    filtered one), the filtered poses (K, 3) moved rigidly by smoothed ⊖ filtered_at,
    and the covariances grown from zero there along the odometry deltas (K, 3) and
    their covariances (K, 3, 3) of slam.rts.arc_steps; before the first epoch, the
    filtered poses and covariances."""
    means = np.array(filtered, dtype=float)
    out_covs = np.array(covs, dtype=float)
    if len(steps) == 0:
        return means, out_covs
    # the last epoch at each step
    last = np.r_[steps[1:] != steps[:-1], True]
    steps, smoothed, filtered_at = steps[last], smoothed[last], filtered_at[last]
    seg = np.searchsorted(steps, np.arange(len(means)), side="right") - 1
    inside = seg >= 0
    k = seg[inside]
    means[inside] = compose(smoothed[k], between(filtered_at[k], means[inside]))
    anchor = np.zeros(len(means), dtype=np.bool_)
    anchor[steps] = True
    d, q = np.asarray(deltas, dtype=float), np.asarray(delta_covs, dtype=float)
    bridge_covariances(means, d, q, anchor, out_covs)
    return means, out_covs


@njit(cache=True)
def bridge_covariances(means, deltas, delta_covs, anchor, covs) -> None:
    """In place: covs[j] = 0 at an anchor step, else F covs[j−1] Fᵀ + R q_j Rᵀ, F the
    Jacobian of means[j−1] ⊕ deltas[j] by the pose, R the rotation by means[j−1]'s
    heading, q_j = delta_covs[j]; the steps before the first anchor keep theirs."""
    started = False
    rq = np.empty((3, 3))  # R q, per step
    for j in range(len(means)):
        if anchor[j]:
            started = True
            covs[j, :, :] = 0.0
            continue
        if not started:
            continue
        th = means[j - 1, 2]
        c, s = math.cos(th), math.sin(th)
        dx, dy = deltas[j, 0], deltas[j, 1]
        fa = -s * dx - c * dy
        fb = c * dx - s * dy
        prev, cov, q = covs[j - 1], covs[j], delta_covs[j]
        # F P Fᵀ with F = I + e0 fa e2ᵀ + e1 fb e2ᵀ, plus R q Rᵀ, written out element by
        # element (numba's `@` brings BLAS, and an array assigned to a slice takes ~5 s
        # to compile)
        for col in range(3):
            cov[0, col] = prev[0, col] + fa * prev[2, col]
            cov[1, col] = prev[1, col] + fb * prev[2, col]
            cov[2, col] = prev[2, col]
        for row in range(3):
            cov[row, 0] += cov[row, 2] * fa
            cov[row, 1] += cov[row, 2] * fb
        for col in range(3):
            rq[0, col] = c * q[0, col] - s * q[1, col]
            rq[1, col] = s * q[0, col] + c * q[1, col]
            rq[2, col] = q[2, col]
        for row in range(3):
            cov[row, 0] += rq[row, 0] * c - rq[row, 1] * s
            cov[row, 1] += rq[row, 0] * s + rq[row, 1] * c
            cov[row, 2] += rq[row, 2]
