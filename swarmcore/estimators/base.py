"""What an agent's estimator is given and what it returns: the interface every estimator
implements, built in or plug-in, in-process or in a ``sat_agent``.

The in-process simulator (:func:`swarmcore.sim.simulate`) and the distributed agent
(``sat_agent.protocol``) make the same calls in the same order, so an estimator keeps the
bit-equality of in-process, processes and containers by construction. Step k of satellite
``own`` (t_k = k dt):

1. :meth:`Estimator.coast_to` (only after steps the agent missed: stalled, cut off);
2. :meth:`Estimator.predict` to step k with the own gyro sample of the interval (no-op at
   k = 0): its prior of the step, before anything of step k is measured;
   :meth:`Estimator.prediction` is what an image pipeline starts from;
3. :meth:`Estimator.absolute_reading` with its own absolute reading of step k (the one
   :class:`StepInputs` will carry; most estimators ignore it here, the centralized
   reference puts it in its message), then :meth:`Estimator.transmit` — the estimator's message of step k, which the agent puts on
   its radio together with its measurement batch. It crosses the link model like the
   batch (sized as its encoded bytes), reaches the peers the channel delivers it to, when
   it delivers it; its wire form is :mod:`swarmrt.bus.convert`'s (built-in estimators
   have protobuf messages in ``proto/swarm/v1/estimators.proto``; a plug-in's travels as
   the bytes its :meth:`Estimator.encode` makes);
4. :meth:`Estimator.step` with :class:`StepInputs`: its own gyro sample, absolute reading,
   own camera measurements (with the covariance its pose estimator attached), and what
   the radio delivered (:class:`Received`: each peer's batch and message, with the step
   it was taken at; older than k means late). What it does with late deliveries is its
   choice (replay, fuse late, drop); it counts them in its :class:`StepReport`;
5. :meth:`Estimator.view` — what it claims after the step (:class:`EstimateView`): its own
   state and whichever peers it tracks, with covariances, and its estimate of each
   tracked peer relative to itself. Metrics, telemetry and the recording read only this.

Start: :meth:`Estimator.start` with the world's prior over :meth:`Estimator.prior_ids`.
Restart after a kill: :meth:`Estimator.rejoin` with what a peer serves
(:meth:`Estimator.rejoin_state`, over the radio), or a cold start when the estimator
offers no warm rejoin (``warm_rejoin = False``).

Nothing here reads truth, and nothing here touches a bus or a file: an estimator is pure
numbers in, numbers out, like the rest of the core.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from ..mekf import AbsoluteMeasurement, RelativeMeasurements, SwarmEstimate

__all__ = [
    "Estimator",
    "EstimatorParams",
    "StepInputs",
    "Received",
    "StepReport",
    "EstimateView",
    "IncompatibleScenario",
    "cold_prior",
]


class IncompatibleScenario(ValueError):
    """A scenario asks an estimator for something it cannot do (the message names the field)."""


class EstimatorParams(BaseModel):
    """An estimator's parameters: the scenario's ``estimator:`` section less ``kind``.
    Subclass it with typed fields (unknown fields are refused, errors name the field)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Received:
    """One peer transmission the radio delivered: what the peer took at ``step`` and sent.

    ``sender``, ``step`` (the step it was taken at; older than the current step: it came
    late), ``measurements`` (the sender's batch, observer = sender, its R attached) and
    ``payload`` (the sender's estimator message; None: it sent none). The two last may be
    handed over as functions that make them when first read: at n = 100 an agent hears 99
    peers a step and its estimator reads the messages of a few."""

    __slots__ = ("_measurements", "_payload", "sender", "step")

    def __init__(self, sender: int, step: int, measurements: RelativeMeasurements | Callable[[], RelativeMeasurements],
                 payload: Any = None):
        self.sender = int(sender)
        self.step = int(step)
        self._measurements = measurements
        self._payload = payload

    @property
    def measurements(self) -> RelativeMeasurements:
        if callable(self._measurements):
            self._measurements = self._measurements()
        return self._measurements

    @property
    def payload(self) -> Any:
        if callable(self._payload) and not isinstance(self._payload, type):
            self._payload = self._payload()
        return self._payload

    def __repr__(self) -> str:
        return f"Received(sender={self.sender}, step={self.step})"


@dataclass(frozen=True)
class StepInputs:
    """Everything satellite ``own``'s estimator learns at step ``step`` (never truth)."""

    step: int
    t: float
    gyro_rate_B: np.ndarray | None  # own gyro, mean rate over the interval step-1 → step (None at 0 or missed)
    absolute: AbsoluteMeasurement | None  # own star tracker and GPS (None: no such sensors)
    own: RelativeMeasurements  # own camera measurements of this step (observer = own)
    received: Sequence[Received] = ()  # what the radio delivered, ordered by (step, sender)
    #: Every on-time peer measurement in one batch (observer order), when the caller has them
    #: so (the radio's message is columnar); else :meth:`on_time_measurements` gathers them.
    peer_measurements: RelativeMeasurements | None = None

    def on_time(self) -> list[Received]:
        return [r for r in self.received if r.step == self.step]

    def on_time_measurements(self) -> RelativeMeasurements:
        """The peers' measurements of this step, in one batch."""
        if self.peer_measurements is not None:
            return self.peer_measurements
        return RelativeMeasurements.concat([r.measurements for r in self.on_time()])

    def late(self) -> list[Received]:
        return [r for r in self.received if r.step < self.step]


@dataclass
class StepReport:
    """What one step did (gate, consistency, late deliveries)."""

    gate_accepted: int = 0
    gate_rejected: int = 0
    nis: float = float("nan")  # joint NIS of what was applied
    nis_dof: int = 0
    iterations: int = 1
    late_used: int = 0  # late measurements used (replayed or fused late)
    late_dropped: int = 0
    replayed_steps: int = 0
    extra: dict = field(default_factory=dict)  # anything else the estimator wants recorded (numbers)


@dataclass(frozen=True)
class EstimateView:
    """What an estimator claims at a step: its own satellite and each tracked peer.

    Rows follow ``ids`` (ascending, ``own`` among them). Covariances are over each
    satellite's ``[a (rad, in its body frame), Δr_H (m)]``. ``P_rel_pose[r]`` is the
    covariance of its estimate of satellite ``ids[r]`` relative to itself, over
    ``[a_rel (rad, in B_j), Δ(r_j − r_own)_H (m)]`` with ``a_rel = a_j − T(q_BjBi) a_own``
    (zero on the own row). ``full`` is the whole-swarm estimate when the estimator keeps
    one (it serves restarts and the selector).
    """

    step: int
    t: float
    own: int
    ids: np.ndarray  # (m,) int
    q_BI: np.ndarray  # (m, 4)
    omega_BI_B: np.ndarray  # (m, 3) rad/s
    r_H: np.ndarray  # (m, 3) m
    v_H: np.ndarray  # (m, 3) m/s
    bias_B: np.ndarray  # (3,) own gyro bias, rad/s
    P_pose: np.ndarray  # (m, 6, 6)
    P_rel_pose: np.ndarray  # (m, 6, 6)
    P_diag: np.ndarray  # (12 m,) the diagonal of what it keeps, in row order
    full: SwarmEstimate | None = None

    def row(self, sat: int) -> int | None:
        hit = np.nonzero(self.ids == sat)[0]
        return int(hit[0]) if hit.size else None


def cold_prior(sc: Any, own: int, inputs: StepInputs) -> SwarmEstimate | None:
    """A prior of the own satellite alone from its own readings at ``inputs.step``: the star
    tracker's attitude and the GPS position with the scenario's initial uncertainties
    (velocity: the larger of ``filter.initial_sigma.vel_m_s`` and ``initial.velocity_max_m_s``;
    bias: zero with ``initial_sigma.bias_rad_s``; rate: the gyro's). None without both
    readings. It is the posterior of that step (the readings are not fused twice)."""
    from ..mekf import init_estimate

    a = inputs.absolute
    if a is None or a.q_BI is None or a.r_H is None:
        return None
    s = sc.filter.initial_sigma.model_dump()
    s["att_rad"] = max(float(a.sigma_att_rad), s["att_rad"])
    s["pos_m"] = max(float(a.sigma_pos_m), s["pos_m"])
    s["vel_m_s"] = max(s["vel_m_s"], sc.initial.velocity_max_m_s)
    w = np.zeros((1, 3)) if inputs.gyro_rate_B is None else np.asarray(inputs.gyro_rate_B, float)[None]
    return init_estimate(step=inputs.step, t=inputs.t, q_BI=np.asarray(a.q_BI, float)[None], omega_BI_B=w,
                         r_H=np.asarray(a.r_H, float)[None], v_H=np.zeros((1, 3)), bias_B=np.zeros(3), sigmas=s, own=0)


class Estimator(ABC):
    """One satellite's estimator (see the module docstring for the call order)."""

    #: Its name in a scenario (``estimator: {kind: ...}``).
    kind: ClassVar[str]
    #: Its parameters (the scenario's ``estimator`` section less ``kind``).
    Params: ClassVar[type[EstimatorParams]] = EstimatorParams
    #: True when it keeps every satellite's state with the full cross-covariance, which
    #: the covariance-driven selection strategies plan from.
    provides_swarm_covariance: ClassVar[bool] = False
    #: True when it can use a prediction of its targets (image pipelines need one).
    provides_prediction: ClassVar[bool] = False
    #: True when it fuses angles-only bearings (``sensors.relative.model: bearing``) from a
    #: prediction of its own satellite alone (:meth:`prediction`): the observer turns each
    #: line of sight into I with its own predicted attitude, which is all a bearing needs
    #: (an estimator that ``provides_prediction`` accepts them too).
    accepts_bearings: ClassVar[bool] = False
    #: True when a restarted agent can start from what a live peer serves (:meth:`rejoin`).
    warm_rejoin: ClassVar[bool] = False
    #: Version of its message's layout (recorded with every message).
    message_version: ClassVar[int] = 1
    #: Whose batches the ideal radio delivers to it (:func:`swarmcore.graphs.radio_peers`):
    #: ``"all"`` (every live peer's; the default, so a plug-in that says nothing keeps
    #: hearing the whole swarm) or ``"graph"`` (only its measurement graph's neighbours, in
    #: and out: an estimator that uses nothing but the measurements involving its own
    #: satellite and the messages of their other ends).
    radio: ClassVar[str] = "all"

    @property
    def hears_peer_absolute(self) -> bool:
        """True when it applies the absolute readings its peers send in their messages (the
        centralized reference, :meth:`absolute_in`): the Cramér–Rao bound of this filter
        counts those that reached it."""
        return False

    @classmethod
    def absolute_in(cls, payload: Any) -> AbsoluteMeasurement | None:
        """The sender's absolute reading (star tracker, GPS) a message of this estimator
        carries (None: none; only an estimator that :attr:`hears_peer_absolute` sends one)."""
        return None

    def __init__(self, sc: Any, own: int, params: EstimatorParams | None = None):
        self.sc = sc
        self.own = int(own)
        self.n = int(sc.n_sats)
        self.params = params if params is not None else self.Params()

    @classmethod
    def check_scenario(cls, sc: Any, params: EstimatorParams) -> None:
        """Refuse a scenario this estimator cannot fly (raise :class:`IncompatibleScenario`
        naming the field). The default checks selection and vision against the class's
        capabilities."""
        from ..selection import NEEDS_STATE

        if sc.selection.strategy in NEEDS_STATE and not cls.provides_swarm_covariance:
            raise IncompatibleScenario(
                f"selection.strategy: {sc.selection.strategy!r} plans from every satellite's full-swarm covariance, which "
                f"estimator {cls.kind!r} does not keep; use none, complete, random or random_tree, or estimator.kind: full")
        if sc.sensors.relative.model == "bearing" and not (cls.provides_prediction or cls.accepts_bearings):
            raise IncompatibleScenario(
                f"sensors.relative.model: bearing shares each line of sight in I, turned by the observer's predicted attitude, "
                f"which estimator {cls.kind!r} does not make; use estimator.kind: full, ci, pairwise or gbp")
        if sc.vision.pipeline != "none" and not cls.provides_prediction:
            raise IncompatibleScenario(
                f"vision.pipeline: {sc.vision.pipeline!r} starts each measurement from a prediction of its targets, which "
                f"estimator {cls.kind!r} does not make; use vision.pipeline: none or estimator.kind: full")

    # -- start ---------------------------------------------------------------------
    @classmethod
    def prior_ids_for(cls, sc: Any, own: int) -> list[int] | None:
        """The satellites whose prior satellite ``own``'s estimator starts from (ascending;
        None: the whole swarm). The world serves it (``init/<i>``) with these rows."""
        return [own]

    def prior_ids(self) -> list[int] | None:
        return type(self).prior_ids_for(self.sc, self.own)

    @abstractmethod
    def start(self, prior: SwarmEstimate, step_pending: bool = True) -> None:
        """Start from ``prior`` (over :meth:`prior_ids`, rows ascending). ``step_pending``:
        the prior is of the step about to be updated (the world's prior at step 0)."""

    def rejoin_state(self) -> Any:
        """What this (live) estimator serves a restarted peer (None: nothing)."""
        return None

    def rejoin(self, state: Any, sender: int, now: int | None) -> None:
        """Start a restarted agent from a peer's :meth:`rejoin_state` (``warm_rejoin``)."""
        raise NotImplementedError(f"estimator {self.kind!r} offers no warm rejoin")

    def cold_start(self, inputs: StepInputs) -> bool:
        """Start a restarted agent from what it measures itself at a step (a restart when
        ``warm_rejoin`` is False). Returns False when that step gives it too little (the
        agent tries again at the next). The default starts from the own star tracker and
        GPS readings (:func:`cold_prior`)."""
        prior = cold_prior(self.sc, self.own, inputs)
        if prior is None:
            return False
        self.start(prior, step_pending=False)  # the readings are its posterior of the step
        return True

    # -- each step -----------------------------------------------------------------
    @property
    @abstractmethod
    def step_index(self) -> int:
        """The step of its current estimate."""

    @property
    @abstractmethod
    def prior_pending(self) -> bool:
        """True when its estimate is a prior whose update :meth:`step` applies next."""

    @abstractmethod
    def coast_to(self, k: int, gyro_of: Callable[[int], np.ndarray | None]) -> None:
        """Bring a posterior to step ``k − 1`` across steps it missed (predictions only;
        ``gyro_of(s)``: the gyro sample of the interval s−1 → s, or None)."""

    @abstractmethod
    def predict(self, k: int, gyro_rate_B: np.ndarray | None) -> None:
        """Predict to step ``k`` (its prior of the step) before anything of k is measured
        and before :meth:`transmit`; :meth:`step` then only updates."""

    def prediction(self) -> SwarmEstimate | None:
        """The estimate a pose estimator starts from (after :meth:`predict`)."""
        return None

    def selection_reference(self) -> tuple[SwarmEstimate, Any] | None:
        """The whole-swarm estimate and its filter parameters a selector plans from (only
        estimators that ``provides_swarm_covariance``)."""
        return None

    def absolute_reading(self, k: int, reading: AbsoluteMeasurement | None) -> None:
        """Its own absolute reading of step ``k`` (star tracker and GPS; None: no such
        sensors), handed over before :meth:`transmit` (the same reading :meth:`step` then
        gets in :attr:`StepInputs.absolute`). The default ignores it; the centralized
        reference sends it on its radio."""
        return None

    @abstractmethod
    def transmit(self, k: int) -> Any:
        """Its message of step ``k`` (None: none), sent with the measurement batch."""

    @abstractmethod
    def step(self, inputs: StepInputs) -> StepReport:
        """Step ``inputs.step``: predict (unless :meth:`predict` did), then update."""

    @abstractmethod
    def view(self) -> EstimateView:
        """What it claims now."""

    # -- plug-in wire form -----------------------------------------------------------
    @classmethod
    def encode(cls, message: Any) -> bytes:
        """A plug-in's message as bytes (built-in estimators' have protobuf messages)."""
        raise NotImplementedError(f"estimator {cls.kind!r}: encode its message as bytes")

    @classmethod
    def decode(cls, data: bytes) -> Any:
        """Inverse of :meth:`encode`; raise ValueError on anything malformed."""
        raise NotImplementedError(f"estimator {cls.kind!r}: decode its message from bytes")
