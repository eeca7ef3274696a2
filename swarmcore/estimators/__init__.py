"""Estimators an agent can fly, behind one interface (:mod:`.base`).

Built in: ``full`` (:mod:`.full`, the full-swarm MEKF), ``central`` (:mod:`.full`, the
full-swarm MEKF that also applies every anchor's absolute reading: the centralized
reference; the anchors send their readings on the radio), ``ci``
(:mod:`.ci`, covariance intersection), ``pairwise`` (:mod:`.pairwise`, Luft et al.'s
pairwise cross-covariance factors), ``gbp`` (:mod:`.gbp`, Gaussian belief propagation on
the swarm's factor graph, a Robot Web). Plug-ins from other packages are found by the runtime
(:mod:`swarmrt.estimators`, entry-point group ``swarm_coloc.estimators``).
"""

from __future__ import annotations

from collections.abc import Mapping

from pydantic import ValidationError

from .base import (
    EstimateView,
    Estimator,
    EstimatorParams,
    IncompatibleScenario,
    Received,
    StepInputs,
    StepReport,
)
from .ci import CIEstimator
from .full import CentralEstimator, FullEstimator
from .gbp import GbpEstimator
from .pairwise import PairwiseEstimator

__all__ = [
    "Estimator",
    "EstimatorParams",
    "EstimateView",
    "StepInputs",
    "StepReport",
    "Received",
    "IncompatibleScenario",
    "BUILTIN",
    "estimator_class",
    "configure",
    "builtin_estimator",
]

#: The estimators that ship with the core, by ``estimator.kind``.
BUILTIN: dict[str, type[Estimator]] = {c.kind: c for c in (FullEstimator, CIEstimator, PairwiseEstimator, GbpEstimator, CentralEstimator)}


def estimator_class(kind: str, extra: Mapping[str, type[Estimator]] | None = None) -> type[Estimator]:
    """The class of ``kind`` among the built-ins and ``extra`` (plug-ins)."""
    known = {**BUILTIN, **(extra or {})}
    if kind not in known:
        raise IncompatibleScenario(f"estimator.kind: unknown estimator {kind!r}; known: {', '.join(sorted(known))} "
                                   "(a plug-in package must be installed to add one: docs/estimators.md)")
    return known[kind]


def configure(cls: type[Estimator], sc) -> EstimatorParams:
    """Validate the scenario's ``estimator`` parameters for ``cls`` and check that it can
    fly the scenario; errors name the field (``estimator.<field>: ...``)."""
    try:
        params = cls.Params(**sc.estimator.params())
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"])
        raise IncompatibleScenario(f"estimator.{loc}: {first['msg']}") from None
    cls.check_scenario(sc, params)
    return params


def builtin_estimator(sc, own: int) -> Estimator:
    """Satellite ``own``'s estimator of the scenario's built-in ``estimator.kind``."""
    cls = estimator_class(sc.estimator.kind)
    return cls(sc, own, configure(cls, sc))
