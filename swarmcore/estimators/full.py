"""``full``: the full-swarm cooperative MEKF of the source dissertation (chapter 4).

Every agent carries every satellite's state (12 error states each, 12n in all) with the
full cross-covariance and applies every relative measurement any satellite broadcasts:
the centralized-equivalent answer, the reference the decentralized estimators are held
against. Its cost per agent grows about as n³ and its radio traffic as n² (a complete
graph's batches). The filter itself is :class:`swarmcore.agent.AgentFilter` (predict,
iterated update, history and exact replay of late measurements); this class adapts it to
the :class:`~swarmcore.estimators.base.Estimator` interface without changing a bit of its
arithmetic. It sends no message of its own: its peers' batches are all it needs. The
centralized reference (``central``, or ``full`` with ``central: true``) also sends each
step's own absolute reading (:class:`CentralMessage`) and applies its peers'.

Reference: W. Bezouska, *Cooperative Localization of a Compact Spacecraft Group using
Computer Vision*, USC 2019, chapter 4 (and :mod:`swarmcore.mekf` for the equations).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field

from ..agent import AgentFilter, filter_params
from ..mekf import Absolute, AbsoluteMeasurement, RelativeMeasurements, SwarmEstimate, reframe
from .base import EstimateView, Estimator, EstimatorParams, StepInputs, StepReport
from .views import full_view

__all__ = ["FullEstimator", "FullParams", "CentralEstimator", "CentralMessage"]


#: Layout of :class:`CentralMessage`'s bytes: one byte of flags (bit 0: a star-tracker
#: attitude, bit 1: a GPS position), then float64 little-endian: σ_att (rad), σ_pos (m),
#: q_BI (4) when bit 0, r_H (3, m) when bit 1.
_STAR, _GPS = 1, 2


@dataclass(frozen=True)
class CentralMessage:
    """What an agent of the centralized reference sends each step it has an absolute
    reading: that reading (star tracker attitude, GPS position, their σ), exactly the
    :class:`~swarmcore.mekf.AbsoluteMeasurement` its own filter applies. Encoded as
    float64 (:meth:`encode`), so a peer applies the same numbers bit for bit; 1 + 8·(2 + 4
    + 3) = 73 bytes with both sensors. It travels on the radio like every estimator
    message (the link model's latency, loss and data-rate cap apply to it)."""

    absolute: AbsoluteMeasurement

    def encode(self) -> bytes:
        a = self.absolute
        flags = (_STAR if a.q_BI is not None else 0) | (_GPS if a.r_H is not None else 0)
        if not flags:
            raise ValueError("central: an absolute reading with neither a star tracker nor a GPS part")
        parts = [np.array([a.sigma_att_rad, a.sigma_pos_m], dtype="<f8")]
        if a.q_BI is not None:
            parts.append(np.asarray(a.q_BI, dtype="<f8").reshape(4))
        if a.r_H is not None:
            parts.append(np.asarray(a.r_H, dtype="<f8").reshape(3))
        return bytes([flags]) + np.concatenate(parts).tobytes()

    @classmethod
    def decode(cls, data: bytes) -> CentralMessage:
        if len(data) < 1:
            raise ValueError("central: empty message")
        flags = data[0]
        if flags not in (_STAR, _GPS, _STAR | _GPS):
            raise ValueError(f"central: unknown flags {flags:#x}")
        want = 1 + 8 * (2 + (4 if flags & _STAR else 0) + (3 if flags & _GPS else 0))
        if len(data) != want:
            raise ValueError(f"central: {len(data)} bytes where flags {flags:#x} make {want}")
        x = np.frombuffer(data, dtype="<f8", offset=1).astype(float)
        if not np.all(np.isfinite(x)):
            raise ValueError("central: a reading that is not finite")
        if not (x[0] > 0.0 and x[1] > 0.0):
            raise ValueError(f"central: sigma_att_rad {x[0]!r} and sigma_pos_m {x[1]!r} must be positive")
        q = x[2:6].copy() if flags & _STAR else None
        if q is not None and abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
            raise ValueError(f"central: q_BI is not a unit quaternion (norm {float(np.linalg.norm(q))!r})")
        r = x[-3:].copy() if flags & _GPS else None
        return cls(AbsoluteMeasurement(q_BI=q, r_H=r, sigma_att_rad=float(x[0]), sigma_pos_m=float(x[1])))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CentralMessage) and self.encode() == other.encode()

    def __hash__(self) -> int:
        return hash(self.encode())


class FullParams(EstimatorParams):
    """The full filter's own settings live in the scenario's ``filter`` section (update
    form, gate, iterations, late handling); nothing more is needed here."""

    mode: Literal["cooperative", "isolated"] | None = Field(
        None, description="override filter.mode (cooperative: every broadcast measurement; isolated: only its own)")
    central: bool = Field(
        False, description="the centralized reference: also apply every other anchor's absolute reading (star tracker, "
        "GPS) each step, sent on the radio with its batch (links, loss and late replay apply to it)")


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
        self._reading: tuple[int, AbsoluteMeasurement] | None = None  # central: the own reading to send

    @property
    def hears_peer_absolute(self) -> bool:
        return self.central

    @classmethod
    def absolute_in(cls, payload: Any) -> AbsoluteMeasurement | None:
        return payload.absolute if isinstance(payload, CentralMessage) else None

    @classmethod
    def encode(cls, message: Any) -> bytes:
        if not isinstance(message, CentralMessage):
            raise TypeError(f"{cls.kind}: cannot encode {type(message).__name__}")
        return message.encode()

    @classmethod
    def decode(cls, data: bytes) -> Any:
        return CentralMessage.decode(data)

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

    def absolute_reading(self, k: int, reading: AbsoluteMeasurement | None) -> None:
        if self.central:
            self._reading = None if reading is None or (reading.q_BI is None and reading.r_H is None) else (k, reading)

    def transmit(self, k: int) -> CentralMessage | None:
        """``full`` sends nothing of its own; the centralized reference sends its own
        absolute reading of the step (:meth:`absolute_reading`), when it has one."""
        if not self.central or self._reading is None or self._reading[0] != k:
            return None
        return CentralMessage(self._reading[1])

    def step(self, inputs: StepInputs) -> StepReport:
        rel = RelativeMeasurements.concat([inputs.own, *(r.measurements for r in inputs.on_time())])
        absolute: Absolute = inputs.absolute
        late_abs: dict[int, dict[int, AbsoluteMeasurement]] = {}
        if self.central:
            # The own reading and every peer's that the radio brought on time; late ones
            # are inserted at their step and replayed (``filter.late: replay``) like late
            # relative measurements, or dropped and counted.
            readings: dict[int, AbsoluteMeasurement] = {} if inputs.absolute is None else {self.own: inputs.absolute}
            for r in inputs.received:
                a = self.absolute_in(r.payload) if r.sender != self.own else None
                if a is None:
                    continue
                if r.step == inputs.step:
                    readings[r.sender] = a
                else:
                    late_abs.setdefault(r.step, {})[r.sender] = a
            absolute = readings
        late: dict[int, list] = {}
        for r in inputs.late():
            late.setdefault(r.step, []).append(r.measurements)
        late_m = {s: RelativeMeasurements.concat(v) for s, v in late.items()}
        rep, lrep = self.flt.step(inputs.step, inputs.gyro_rate_B, absolute, rel, late=late_m, late_absolute=late_abs)
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
    hears). The peers' readings come on the radio: each agent sends its own in its message
    (:class:`CentralMessage`), so in-process and distributed runs feed it the same, and the
    radio's latency and loss apply to them as to the relative measurements."""

    kind = "central"

    def __init__(self, sc, own: int, params: FullParams | None = None):
        super().__init__(sc, own, params)
        self.central = True
