"""Measurement graphs: G[i, j] = True when satellite i measures satellite j.

The diagonal marks absolute pose sensors (star tracker + GPS) of satellite i.
Topologies of the dissertation's study (section 4.5.3): complete, star (every
satellite measures one landmark), chain (a spanning path 0 → 1 → … → n−1) and duplex
chain (the same path measured in both directions), or an explicit incidence matrix.
"""

from __future__ import annotations

import numpy as np

__all__ = ["incidence", "edges", "scenario_graph", "radio_peers", "RADIO_SCOPES", "nominal_positions", "lattice_positions", "encounter_schedule", "GRAPH_KINDS"]

GRAPH_KINDS = ("complete", "star", "chain", "duplex_chain", "matrix", "nearest")
RADIO_SCOPES = ("all", "graph")


def incidence(
    n: int,
    kind: str,
    *,
    landmark: int = 0,
    matrix=None,
    absolute="all",
    positions=None,
    neighbors: int = 3,
) -> np.ndarray:
    """n×n boolean incidence matrix of a topology (diagonal: absolute sensors). ``nearest``:
    each satellite measures its ``neighbors`` nearest by ``positions`` (n, 3) (ties by id)."""
    G = np.zeros((n, n), dtype=bool)
    if kind == "nearest":
        if positions is None:
            raise ValueError("graph kind 'nearest' needs the nominal positions")
        p = np.asarray(positions, float)
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        order = np.lexsort((np.broadcast_to(np.arange(n), (n, n)), d), axis=1)  # by distance, then id
        for i in range(n):
            G[i, order[i, :neighbors]] = True
    elif kind == "complete":
        G[:] = True
    elif kind == "star":
        if not 0 <= landmark < n:
            raise ValueError(f"landmark {landmark} is not a satellite id (0..{n - 1})")
        G[:, landmark] = True
    elif kind in ("chain", "duplex_chain"):
        k = np.arange(n - 1)
        G[k, k + 1] = True
        if kind == "duplex_chain":
            G[k + 1, k] = True
    elif kind == "matrix":
        M = np.asarray(matrix)
        if M.shape != (n, n):
            raise ValueError(f"incidence matrix must be {n}×{n}, got {M.shape}")
        return M.astype(bool)
    else:
        raise ValueError(f"unknown graph kind {kind!r}; expected one of {GRAPH_KINDS}")
    np.fill_diagonal(G, False)
    if absolute == "all":
        np.fill_diagonal(G, True)
    elif absolute != "none":
        for i in absolute:
            G[i, i] = True
    return G


def edges(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Off-diagonal (observer, target) pairs in canonical (row-major) order."""
    off = G.copy()
    np.fill_diagonal(off, False)
    i, j = np.nonzero(off)
    return i, j


def lattice_positions(n: int, spacing_m: float) -> np.ndarray:
    """(n, 3) nominal positions of ``initial.layout: lattice``: the first n points of a grid
    of ``spacing_m`` with sides as equal as n allows (x fastest), centred on the origin."""
    side = int(np.ceil(n ** (1 / 3) - 1e-9))
    nx = ny = side
    nz = int(np.ceil(n / (nx * ny)))
    idx = np.arange(n)
    grid = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1).astype(float)
    grid -= (np.array([nx, ny, nz]) - 1) / 2.0
    return grid * spacing_m


def nominal_positions(sc) -> np.ndarray | None:
    """The formation's nominal positions (H frame, m) when its layout has them (lattice)."""
    ini = sc.initial
    return lattice_positions(sc.n_sats, ini.spacing_m) if ini.layout == "lattice" else None


def scenario_graph(sc) -> np.ndarray:
    """The incidence matrix a :class:`swarmcore.scenario.Scenario`'s ``graph`` section describes."""
    g = sc.graph
    return incidence(sc.n_sats, g.kind, landmark=g.landmark, matrix=g.matrix, absolute=g.absolute,
                     positions=nominal_positions(sc) if g.kind == "nearest" else None, neighbors=g.neighbors)


def encounter_schedule(G: np.ndarray) -> tuple[np.ndarray, int]:
    """A proper edge colouring of the undirected measurement graph (i and j meet when
    either measures the other): ``colour[i, j]`` (symmetric; −1 where they never meet) and
    the number of colours C. The edges of one colour form a matching, so when the pairs of
    colour ``k mod C`` meet at step k, every satellite meets at most one peer per step.
    Deterministic (networkx's greedy colouring of the line graph, largest degree first, on
    edges in ascending order): every agent computes the same schedule."""
    import networkx as nx

    n = G.shape[0]
    U = (np.asarray(G, dtype=bool) | np.asarray(G, dtype=bool).T) & ~np.eye(n, dtype=bool)
    g: nx.Graph = nx.Graph()
    g.add_edges_from((int(i), int(j)) for i, j in zip(*np.nonzero(np.triu(U, 1))))
    colour = np.full((n, n), -1, dtype=int)
    if g.number_of_edges() == 0:
        return colour, 1
    c = nx.greedy_color(nx.line_graph(g), strategy="largest_first")
    for (i, j), v in sorted(c.items()):
        colour[i, j] = colour[j, i] = v
    return colour, int(colour.max()) + 1


def radio_peers(G: np.ndarray, scope: str) -> list[np.ndarray] | None:
    """Whose batches the ideal radio (``links.enabled: false``) delivers to each agent: for
    every satellite i, the ascending ids j ≠ i it hears; None: every live peer (``scope``
    ``"all"``). ``"graph"``: its neighbours in the measurement graph ``G``, both
    directions (j measures i, or i measures j) — every measurement that involves i is
    taken along such an edge (the selector chooses among the graph's edges too), and the
    estimate of its other end comes with that end's batch. The in-process simulator and
    the world both deliver by this function (the estimator's class says its scope:
    :attr:`swarmcore.estimators.Estimator.radio`), so they give the same numbers."""
    if scope == "all":
        return None
    if scope != "graph":
        raise ValueError(f"radio scope {scope!r}: expected one of {RADIO_SCOPES}")
    A = np.asarray(G, dtype=bool)
    A = A | A.T
    np.fill_diagonal(A, False)
    return [np.flatnonzero(A[i]) for i in range(A.shape[0])]
