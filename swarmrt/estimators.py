"""Which estimator a scenario's agents fly, plug-ins included, and its messages' wire form.

Built-in estimators live in the core (:mod:`swarmcore.estimators`). A plug-in is any
installed Python package that declares an entry point in the group
``swarm_coloc.estimators`` whose name is the estimator's ``kind`` and whose object is its
:class:`~swarmcore.estimators.base.Estimator` subclass::

    [project.entry-points."swarm_coloc.estimators"]
    mykind = "my_package.module:MyEstimator"

``docs/estimators.md`` walks through writing one (``examples/estimator-plugin`` is a
complete package). A plug-in's message crosses the bus as the bytes its ``encode`` makes
(``EstimatorMessage.opaque``); the built-ins' have protobuf messages of their own.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

from swarmcore.estimators import BUILTIN, Estimator, IncompatibleScenario, configure, estimator_class
from swarmcore.estimators.ci import CiState
from swarmcore.estimators.pairwise import PairwiseState
from swarmcore.scenario import Scenario

__all__ = ["ENTRY_POINT_GROUP", "plugins", "estimator_for", "estimator_factory", "check_estimator", "EstimatorCodec", "codec_for",
           "IncompatibleScenario"]

#: The entry-point group a plug-in package declares its estimators in.
ENTRY_POINT_GROUP = "swarm_coloc.estimators"


@functools.cache
def plugins() -> dict[str, type[Estimator]]:
    """Every installed plug-in estimator, by kind (loaded once per process). A broken
    plug-in is an error naming its package, not a silent absence."""
    out: dict[str, type[Estimator]] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:
            raise IncompatibleScenario(f"estimator plug-in {ep.name!r} ({ep.value}) failed to load: {exc}") from exc
        if not (isinstance(obj, type) and issubclass(obj, Estimator)):
            raise IncompatibleScenario(f"estimator plug-in {ep.name!r} ({ep.value}) is not an Estimator subclass")
        if getattr(obj, "kind", None) != ep.name:
            raise IncompatibleScenario(f"estimator plug-in {ep.name!r} ({ep.value}) declares kind {getattr(obj, 'kind', None)!r}")
        if ep.name in BUILTIN:
            raise IncompatibleScenario(f"estimator plug-in {ep.name!r} ({ep.value}) would replace the built-in of that name")
        out[ep.name] = obj
    return out


def _class(sc: Scenario) -> type[Estimator]:
    kind = sc.estimator.kind
    return estimator_class(kind, plugins() if kind not in BUILTIN else None)


def check_estimator(sc: Scenario) -> type[Estimator]:
    """The scenario's estimator class, its parameters validated and its compatibility with
    the scenario checked (raises :class:`IncompatibleScenario` naming the field)."""
    cls = _class(sc)
    configure(cls, sc)
    return cls


def estimator_for(sc: Scenario, own: int) -> Estimator:
    """Satellite ``own``'s estimator."""
    cls = _class(sc)
    return cls(sc, own, configure(cls, sc))


def estimator_factory(sc: Scenario) -> Callable[[Scenario, int], Estimator]:
    """``factory(sc, own)`` for :func:`swarmcore.sim.simulate` (parameters checked once)."""
    cls = _class(sc)
    params = configure(cls, sc)
    return lambda s, own: cls(s, own, params)


@dataclass(frozen=True)
class EstimatorCodec:
    """An estimator's message ⇄ ``swarm.v1.EstimatorMessage`` (exact: float64 as float64)."""

    cls: type[Estimator]

    @property
    def kind(self) -> str:
        return self.cls.kind

    def to_msg(self, payload: Any):
        """The message to put in the batch (None when the estimator sent nothing)."""
        from swarmrt.bus.convert import ci_state_msg, pairwise_state_msg
        from swarmrt.bus.messages import MAX_OPAQUE_BYTES, EstimatorMessage

        if payload is None:
            return None
        kind, version = self.cls.kind, self.cls.message_version
        if isinstance(payload, CiState):
            return EstimatorMessage(kind=kind, version=version, ci=ci_state_msg(payload))
        if isinstance(payload, PairwiseState):
            return EstimatorMessage(kind=kind, version=version, pairwise=pairwise_state_msg(payload))
        opaque = self.cls.encode(payload)
        if len(opaque) > MAX_OPAQUE_BYTES:
            # Every receiver refuses it (swarmrt.bus.messages.validate): said here, at the
            # sender, the same in `swarm sim` and `swarm run`, not as peers that never hear it.
            raise ValueError(f"estimator {kind!r}: its message of step {getattr(payload, 'step', '?')} encodes to {len(opaque)} bytes, "
                             f"over the {MAX_OPAQUE_BYTES} an EstimatorMessage.opaque may hold (proto/swarm/v1/estimators.proto)")
        return EstimatorMessage(kind=kind, version=version, opaque=opaque)

    def from_msg(self, msg, sender: int, step: int) -> Any:
        """The estimator's value of a received message; None when it is another estimator's
        or of another layout version (a swarm flies one estimator). Raises ValueError on a
        plug-in message its decoder refuses."""
        from swarmrt.bus.convert import ci_state, pairwise_state

        if msg.kind != self.cls.kind or msg.version != self.cls.message_version:
            return None
        which = msg.WhichOneof("body")
        if which == "ci":
            return ci_state(msg.ci, sender, step)
        if which == "pairwise":
            return pairwise_state(msg.pairwise, sender, step)
        if which == "opaque":
            return self.cls.decode(bytes(msg.opaque))
        return None


def codec_for(sc: Scenario) -> EstimatorCodec:
    return EstimatorCodec(_class(sc))
