"""Measurement graphs: G[i, j] = True when satellite i measures satellite j.

The diagonal marks absolute pose sensors (star tracker + GPS) of satellite i.
Topologies of the dissertation's study (section 4.5.3): complete, star (every
satellite measures one landmark), chain (a spanning path 0 → 1 → … → n−1) and duplex
chain (the same path measured in both directions), or an explicit incidence matrix.
"""

from __future__ import annotations

import numpy as np

__all__ = ["incidence", "edges", "scenario_graph", "GRAPH_KINDS"]

GRAPH_KINDS = ("complete", "star", "chain", "duplex_chain", "matrix")


def incidence(
    n: int,
    kind: str,
    *,
    landmark: int = 0,
    matrix=None,
    absolute="all",
) -> np.ndarray:
    """n×n boolean incidence matrix of a topology (diagonal: absolute sensors)."""
    G = np.zeros((n, n), dtype=bool)
    if kind == "complete":
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


def scenario_graph(sc) -> np.ndarray:
    """The incidence matrix a :class:`swarmcore.scenario.Scenario`'s ``graph`` section describes."""
    g = sc.graph
    return incidence(sc.n_sats, g.kind, landmark=g.landmark, matrix=g.matrix, absolute=g.absolute)
