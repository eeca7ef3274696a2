"""What every estimator that keeps its own satellite's state shares: a one-satellite
estimate (12 error states ``[a, Δβ, Δr, Δv]``, its gyro in dynamic-model-replacement mode,
as the full filter's own block), its prediction, its own star tracker and GPS update, and
the bookkeeping of the step it is at. ``ci`` and ``pairwise`` build on it, and so can a
plug-in (``examples/estimator-plugin``). :class:`ReplayingEstimator` adds the replay of late
deliveries (``filter.late: replay``) that ``ci`` and ``gbp`` share."""

from __future__ import annotations

import dataclasses
import math
from abc import abstractmethod
from typing import Any

import numpy as np

from ..agent import filter_params
from ..mekf import (
    BLOCK,
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    absolute_residual,
    apply_correction,
    predict,
)
from .base import Estimator, EstimatorParams, Received, StepInputs, StepReport
from .views import POSE

__all__ = ["OwnStateEstimator", "ReplayingEstimator", "Kept", "absolute_update"]


def absolute_update(e: SwarmEstimate, fp: FilterParams, absolute: AbsoluteMeasurement) -> tuple[SwarmEstimate, float, int]:
    """The own star tracker and GPS on a one-satellite estimate: a Kalman update in Joseph
    form on its 12 states (the measurement touches the pose only) with the multiplicative
    reset; returns the posterior, its NIS and degrees of freedom. The same as
    :func:`swarmcore.mekf.update` with no relative measurement, without its generality."""
    res = absolute_residual(e, fp, absolute)
    if res is None:
        return e, 0.0, 0
    y, Hp, R = res
    H = np.zeros((y.size, BLOCK))
    H[:, POSE] = Hp
    PHt = e.P @ H.T
    S = H @ PHt + R
    K = np.linalg.solve(S, PHt.T).T
    A = np.eye(BLOCK) - K @ H
    P = A @ e.P @ A.T + K @ R @ K.T
    return apply_correction(e, fp, K @ y, P), float(y @ np.linalg.solve(S, y)), int(y.size)


class OwnStateEstimator(Estimator):
    """An estimator whose state is its own satellite alone (a subclass adds what it keeps of
    its peers and implements ``transmit``, ``step`` and ``view``)."""

    def __init__(self, sc, own: int, params: EstimatorParams | None = None):
        super().__init__(sc, own, params)
        self.fp: FilterParams = dataclasses.replace(filter_params(sc, own), n=1, own=0)
        self.est: SwarmEstimate | None = None
        self._pending = True

    def start(self, prior: SwarmEstimate, step_pending: bool = True) -> None:
        if prior.n != 1:
            raise ValueError(f"{self.kind} estimator of satellite {self.own}: a prior of its own satellite only, not {prior.n}")
        self.est = prior
        self._pending = step_pending

    def prediction(self) -> SwarmEstimate | None:
        """With bearings (``sensors.relative.model: bearing``), its prior of the step (its own
        satellite alone, after :meth:`predict`): what the observer turns its lines of sight
        into I with (:func:`swarmcore.agent.inertial_bearings`). None otherwise (it makes no
        prediction of its targets: image pipelines are refused)."""
        if self.fp.relative_kind != "bearing" or self.est is None:
            return None
        return self.est

    @property
    def e(self) -> SwarmEstimate:
        if self.est is None:
            raise RuntimeError(f"estimator of satellite {self.own}: not started")
        return self.est

    @property
    def step_index(self) -> int:
        return self.e.step

    @property
    def prior_pending(self) -> bool:
        return self._pending

    def propagate(self, gyro_rate_B: np.ndarray | None) -> None:
        """One step of the own satellite's prediction (a subclass propagates what it keeps
        with it here)."""
        self.est = predict(self.e, self.fp, gyro_rate_B)

    def coast_to(self, k, gyro_of) -> None:
        if self._pending and self.e.step < k:
            self._pending = False
        while self.e.step < k - 1:
            self.propagate(gyro_of(self.e.step + 1))

    def predict(self, k, gyro_rate_B) -> None:
        if not self._pending and self.e.step == k - 1:
            self.propagate(gyro_rate_B)
            self._pending = True

    def begin_step(self, k: int, gyro_rate_B) -> None:
        """Predict to step ``k`` unless :meth:`predict` did; the estimate must then be of k."""
        if not self._pending:
            self.predict(k, gyro_rate_B)
        if self.e.step != k:
            raise ValueError(f"{self.kind} estimator of satellite {self.own}: step {k} with its estimate at step {self.e.step}")

    def update_absolute(self, absolute: AbsoluteMeasurement | None) -> tuple[float, int]:
        """Its own star tracker and GPS (:func:`absolute_update`); returns NIS and dof."""
        if absolute is None:
            return 0.0, 0
        self.est, nis, dof = absolute_update(self.e, self.fp, absolute)
        return nis, dof


@dataclasses.dataclass
class Kept:
    """What step s was given, kept for replaying it when a late delivery of s comes."""

    prior: Any  # the estimator's state at the start of step s (its prior: ReplayingEstimator.snapshot)
    absolute: AbsoluteMeasurement | None
    own: RelativeMeasurements
    heard: dict[int, Received]  # sender → its delivery of step s (on time, or arrived late)
    peers_batch: RelativeMeasurements | None = None  # the on-time peers' measurements in one batch (None: gather from heard)
    gyro_next: np.ndarray | None = None  # the gyro sample of s → s+1


class ReplayingEstimator(OwnStateEstimator):
    """An own-state estimator that replays late deliveries (``filter.late: replay``): it
    keeps what each of its last ``filter.history_s`` of steps was given (:class:`Kept`) and,
    when a delivery of an earlier step comes, files it under that step and re-runs the
    steps from there (:meth:`step_inputs`). A subclass implements ``_update(kept, count)``
    and, when it keeps more than its own estimate, :meth:`snapshot` / :meth:`restore`."""

    def __init__(self, sc, own: int, params: EstimatorParams | None = None):
        super().__init__(sc, own, params)
        f = sc.filter
        self.history_steps = math.ceil(f.history_s / sc.dt_s) if f.late == "replay" else 0
        self._kept: dict[int, Kept] = {}  # step → what it was given (replay)

    def snapshot(self) -> Any:
        """Its state at the start of a step, as a replay restarts from it."""
        return self.e

    def restore(self, prior: Any) -> None:
        self.est = prior

    @abstractmethod
    def _update(self, kept: Kept, count: bool) -> tuple[int, int, float, int]:
        """One step's update from what it was given; returns accepted, rejected, NIS and its
        degrees of freedom. ``count``: the live pass (not a replay)."""

    def predict(self, k, gyro_rate_B) -> None:
        if not self._pending and self.e.step == k - 1 and k - 1 in self._kept:
            self._kept[k - 1].gyro_next = gyro_rate_B
        super().predict(k, gyro_rate_B)

    def coast_to(self, k, gyro_of) -> None:
        if self.e.step < k - 1:
            self._kept.clear()  # a gap: replay does not cross steps it missed
        super().coast_to(k, gyro_of)

    def step_inputs(self, inputs: StepInputs, rep: StepReport, peers_batch: RelativeMeasurements | None = None) -> Kept:
        """Begin step ``inputs.step``: predict to it, replay from the earliest step a late
        delivery belongs to (counted in ``rep``), and keep what this step is given; returns
        that, for the live update. ``peers_batch``: the on-time peers' measurements in one
        batch, kept for a replay of the step (None: gathered from what it heard)."""
        k = inputs.step
        self.begin_step(k, inputs.gyro_rate_B)
        late = inputs.late()
        if late:
            first = self._take_late(late, rep)
            if first is not None:
                self._replay(first, k)
                rep.replayed_steps = k - first
        kept = Kept(self.snapshot(), inputs.absolute, inputs.own, {r.sender: r for r in inputs.on_time()}, peers_batch)
        if self.history_steps:
            self._kept[k] = kept
            for old in [s for s in self._kept if s <= k - self.history_steps]:
                del self._kept[old]
        return kept

    def _take_late(self, late: list[Received], rep: StepReport) -> int | None:
        """File each late delivery under the step it was taken at; returns the earliest step
        to replay from (None: nothing kept to replay)."""
        first = None
        for r in late:
            kept = self._kept.get(r.step)
            involving = int(np.count_nonzero(r.measurements.target == self.own))
            if kept is None or r.sender in kept.heard:
                rep.late_dropped += involving
                continue
            kept.heard[r.sender] = r
            kept.peers_batch = None  # gathered again from what it heard
            involving += int(np.count_nonzero(kept.own.target == r.sender))  # its own measurements of the sender
            rep.late_used += involving
            first = r.step if first is None else min(first, r.step)
        return first

    def _replay(self, first: int, k: int) -> None:
        """Re-run steps ``first`` … k−1 from their kept priors and inputs: the prior of step k."""
        self.restore(self._kept[first].prior)
        for s in range(first, k):
            kept = self._kept[s]
            kept.prior = self.snapshot()
            self._update(kept, count=False)
            self.propagate(kept.gyro_next)
