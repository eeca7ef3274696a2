"""What every estimator that keeps its own satellite's state shares: a one-satellite
estimate (12 error states ``[a, Δβ, Δr, Δv]``, its gyro in dynamic-model-replacement mode,
as the full filter's own block), its prediction, its own star tracker and GPS update, and
the bookkeeping of the step it is at. ``ci`` and ``pairwise`` build on it, and so can a
plug-in (``examples/estimator-plugin``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..agent import filter_params
from ..mekf import BLOCK, AbsoluteMeasurement, FilterParams, SwarmEstimate, absolute_residual, apply_correction, predict
from .base import Estimator, EstimatorParams
from .views import POSE

__all__ = ["OwnStateEstimator", "absolute_update"]


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
