"""``full``: the full-swarm cooperative MEKF of the source dissertation (chapter 4).

Every agent carries every satellite's state (12 error states each, 12n in all) with the
full cross-covariance and applies every relative measurement any satellite broadcasts:
the centralized-equivalent answer, the reference the decentralized estimators are held
against. Its cost per agent grows about as n³ and its radio traffic as n² (a complete
graph's batches). The filter itself is :class:`swarmcore.agent.AgentFilter` (predict,
iterated update, history and exact replay of late measurements); this class adapts it to
the :class:`~swarmcore.estimators.base.Estimator` interface without changing a bit of its
arithmetic. It sends no message of its own: its peers' batches are all it needs.

Reference: W. Bezouska, *Cooperative Localization of a Compact Spacecraft Group using
Computer Vision*, USC 2019, chapter 4 (and :mod:`swarmcore.mekf` for the equations).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..agent import AgentFilter, filter_params
from ..mekf import Absolute, RelativeMeasurements, SwarmEstimate, reframe
from .base import EstimateView, Estimator, EstimatorParams, IncompatibleScenario, StepInputs, StepReport
from .views import full_view

__all__ = ["FullEstimator", "FullParams", "CentralEstimator", "central_refusal"]


def central_refusal(sc) -> str | None:
    """Why a distributed run (``swarm run``) cannot fly the scenario's estimator, or None:
    the centralized reference (``estimator: {kind: full, central: true}``) applies every
    anchor's absolute reading, which the agents do not put on the radio."""
    if sc.estimator.kind == "central" or (sc.estimator.kind == "full" and sc.estimator.params().get("central")):
        return ("estimator.central: the centralized reference applies every anchor's absolute readings (star tracker, "
                "GPS), which do not travel on the radio of a distributed run; fly it in-process (swarm sim, swarm mc, "
                "swarm compare-estimators) or set estimator.central: false")
    return None


class FullParams(EstimatorParams):
    """The full filter's own settings live in the scenario's ``filter`` section (update
    form, gate, iterations, late handling); nothing more is needed here."""

    mode: Literal["cooperative", "isolated"] | None = Field(
        None, description="override filter.mode (cooperative: every broadcast measurement; isolated: only its own)")
    central: bool = Field(
        False, description="the centralized reference: also apply every other anchor's absolute reading (star tracker, "
        "GPS) each step; in-process only (swarm sim): the readings do not travel on the radio of a distributed run")


class FullEstimator(Estimator):
    kind = "full"
    Params = FullParams
    provides_swarm_covariance = True
    provides_prediction = True
    warm_rejoin = True

    def __init__(self, sc, own: int, params: FullParams | None = None):
        super().__init__(sc, own, params)
        self.filter_params = filter_params(sc, own)
        f = sc.filter
        self.mode = self.params.mode or f.mode  # type: ignore[attr-defined]
        self.late = f.late
        self.history_steps = int(np.ceil(f.history_s / sc.dt_s)) if sc.links.enabled and f.late == "replay" else 0
        self.filter: AgentFilter | None = None
        self.central = bool(self.params.central)  # type: ignore[attr-defined]

    @property
    def hears_peer_absolute(self) -> bool:
        return self.central

    # -- start -----------------------------------------------------------------------
    @classmethod
    def prior_ids_for(cls, sc, own: int) -> list[int] | None:
        return None

    def _make(self, est: SwarmEstimate, pending: bool) -> None:
        self.filter = AgentFilter(self.filter_params, est, self.mode, late=self.late, history_steps=self.history_steps,
                                  prior_pending=pending)

    def start(self, prior: SwarmEstimate, step_pending: bool = True) -> None:
        self._make(prior, step_pending)

    def rejoin_state(self) -> SwarmEstimate | None:
        return None if self.filter is None else self.filter.est

    def rejoin(self, state: SwarmEstimate, sender: int, now: int | None) -> None:
        """Borrow a live peer's full estimate, re-framed for this satellite
        (:func:`swarmcore.mekf.reframe`), carried to ``now`` (the swarm's present) when it
        arrived later than it was taken (no gyro samples meanwhile)."""
        s = self.sc.filter.initial_sigma
        self._make(reframe(state, sender, self.own, s.bias_rad_s, s.rate_rad_s), False)
        if now is not None:
            self.flt.coast_to(now, lambda _s: None)

    @property
    def flt(self) -> AgentFilter:
        if self.filter is None:
            raise RuntimeError(f"estimator of satellite {self.own}: not started")
        return self.filter

    # -- each step -------------------------------------------------------------------
    @property
    def step_index(self) -> int:
        return self.flt.est.step

    @property
    def prior_pending(self) -> bool:
        return self.flt.prior_pending

    def coast_to(self, k, gyro_of) -> None:
        self.flt.coast_to(k, gyro_of)

    def predict(self, k, gyro_rate_B) -> None:
        f = self.flt
        if k > 0 and f.est.step < k:
            f.predict_to(k, gyro_rate_B)

    def prediction(self) -> SwarmEstimate:
        return self.flt.est

    def selection_reference(self):
        return self.flt.est, self.filter_params

    def transmit(self, k: int) -> None:
        return None

    def step(self, inputs: StepInputs) -> StepReport:
        rel = RelativeMeasurements.concat([inputs.own, *(r.measurements for r in inputs.on_time())])
        absolute: Absolute = inputs.absolute
        if self.central:
            if inputs.peer_absolute is None:
                raise IncompatibleScenario(central_refusal(self.sc) or "estimator.central: no peer absolute readings")
            absolute = {**({self.own: inputs.absolute} if inputs.absolute is not None else {}),
                        **{i: m for i, m in inputs.peer_absolute.items() if i != self.own}}
        late: dict[int, list] = {}
        for r in inputs.late():
            late.setdefault(r.step, []).append(r.measurements)
        late_m = {s: RelativeMeasurements.concat(v) for s, v in late.items()}
        rep, lrep = self.flt.step(inputs.step, inputs.gyro_rate_B, absolute, rel, late=late_m)
        return StepReport(gate_accepted=rep.n_accepted, gate_rejected=rep.n_rejected, nis=rep.nis, nis_dof=rep.nis_dof,
                          iterations=rep.iterations, late_used=lrep.used, late_dropped=lrep.dropped,
                          replayed_steps=lrep.replayed_steps)

    def view(self) -> EstimateView:
        return full_view(self.flt.est, self.own)


class CentralEstimator(FullEstimator):
    """``central``: the centralized reference, ``full`` with ``central: true``. Every
    agent's full-swarm filter applies, besides its own gyro, star tracker and GPS and every
    relative measurement, every other live anchor's absolute reading of the step: one
    filter of everything the swarm measures but the peers' gyros (which no estimator here
    hears). In-process only: a distributed run refuses it (:func:`central_refusal`)."""

    kind = "central"

    def __init__(self, sc, own: int, params: FullParams | None = None):
        super().__init__(sc, own, params)
        self.central = True
