"""Whose batches the ideal radio delivers to each agent (:func:`swarmcore.graphs.radio_peers`):
bounded by the graph for an estimator that hears its neighbours, and the same numbers as
hearing everyone, since such an estimator uses nothing else."""

import dataclasses

import numpy as np
import pytest

from swarmcore.estimators import configure
from swarmcore.estimators.ci import CIEstimator
from swarmcore.estimators.full import FullEstimator
from swarmcore.estimators.pairwise import PairwiseEstimator
from swarmcore.graphs import incidence, lattice_positions, radio_peers, scenario_graph
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate


def _nearest(n: int, k: int = 3) -> np.ndarray:
    return incidence(n, "nearest", positions=lattice_positions(n, 50.0), neighbors=k)


@pytest.mark.parametrize("n", [10, 40, 100])
def test_graph_peers_are_the_neighbours_both_ways_and_bounded(n):
    G = _nearest(n)
    hears = radio_peers(G, "graph")
    assert hears is not None and len(hears) == n
    for i, h in enumerate(hears):
        want = sorted({int(j) for j in np.flatnonzero(G[i]) if j != i} | {int(j) for j in np.flatnonzero(G[:, i]) if j != i})
        assert h.tolist() == want, i  # ascending, itself excluded, in- and out-neighbours
        for j in h:
            assert i in hears[j].tolist()  # symmetric: whom i hears hears i
    # Nearest-3 on a lattice: at most 3 out-neighbours and a bounded number of in-neighbours,
    # whatever the swarm's size (a lattice point is among the 3 nearest of few others).
    assert max(len(h) for h in hears) <= 12


def test_all_scope_is_everyone_and_unknown_scope_is_refused():
    G = _nearest(10)
    assert radio_peers(G, "all") is None
    with pytest.raises(ValueError, match="radio scope 'nearby'"):
        radio_peers(G, "nearby")
    # A complete graph: the graph scope is everyone but oneself.
    full = radio_peers(incidence(5, "complete"), "graph")
    assert full is not None and [h.tolist() for h in full] == [[j for j in range(5) if j != i] for i in range(5)]


def test_estimators_declare_their_scope():
    assert FullEstimator.radio == "all"  # it fuses the whole swarm's measurements
    assert CIEstimator.radio == "graph" and PairwiseEstimator.radio == "graph"


def _everyone(cls):
    """The same estimator, delivered every live peer's batch (the old ideal radio)."""
    return type(f"Everyone{cls.__name__}", (cls,), {"radio": "all"})


@pytest.mark.parametrize("cls", [CIEstimator, PairwiseEstimator])
@pytest.mark.parametrize("strategy", ["none", "random"])
def test_hearing_only_the_neighbours_changes_no_number(cls, strategy):
    """The simulator delivers each agent its radio peers' batches only; an estimator that
    uses only measurements involving its own satellite gives the numbers, bit for bit, it
    gives when it hears the whole swarm."""
    sc = Scenario(name="radio", seed=5, n_sats=9, duration_s=12, estimator={"kind": cls.kind},
                  graph={"kind": "nearest", "neighbors": 2}, initial={"layout": "lattice"},
                  selection={"strategy": strategy, "budget": 6} if strategy != "none" else {"strategy": "none"})
    hears = radio_peers(scenario_graph(sc), cls.radio)
    assert hears is not None and max(len(h) for h in hears) < sc.n_sats - 1  # some peers are not heard
    params = configure(cls, sc)
    wide = _everyone(cls)
    a = simulate(sc, estimator_factory=lambda s, own: cls(s, own, params))
    b = simulate(sc, estimator_factory=lambda s, own: wide(s, own, params))
    compared = 0
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ("step_ms", "cpu_ms"):
            continue
        if dataclasses.is_dataclass(x):
            for g in dataclasses.fields(x):
                u, v = getattr(x, g.name), getattr(y, g.name)
                if isinstance(u, np.ndarray):
                    assert np.array_equal(u, v, equal_nan=u.dtype.kind == "f"), f"{f.name}.{g.name}"
                    compared += 1
        elif isinstance(x, np.ndarray):
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f.name
            compared += 1
    assert compared > 10
    assert int(np.asarray(a.taken).sum()) > 0  # measurements were taken and fused
