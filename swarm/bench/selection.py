"""Selection-time benchmark: ms per step of each strategy's ``select_for_scenario`` call.

Numbers only (printed and written as JSON); never timed asserts. The estimate the selector
plans with is a real filter's, carried through a few warm-up steps (random spanning-tree
measurements) so its covariance has the cross-correlations of a running swarm; then each
strategy is timed on the same predicted estimate over several steps k (fresh random streams).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from swarm.bench.filter import machine_info
from swarm.outputs import write_json
from swarmcore import graphs
from swarmcore import selection as sel
from swarmcore.agent import filter_params
from swarmcore.mekf import predict, update
from swarmcore.scenario import Scenario
from swarmcore.streams import stream
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import (
    absolute_measurements,
    initial_estimate,
    initial_truth,
    step_truth,
    world_params,
)

__all__ = ["bench_selection"]


def _planning_estimate(sc: Scenario, warm_steps: int):
    """Filter 0 after ``warm_steps`` steps of random-tree measurements, predicted one step."""
    n = sc.n_sats
    wp = world_params(sc)
    truth = initial_truth(sc)
    p = filter_params(sc, 0)
    est = initial_estimate(sc, truth, 0)
    full = ~np.eye(n, dtype=bool)
    for k in range(warm_steps):
        truth, gyro = step_truth(wp, truth)
        est = predict(est, p, gyro[0])
        obs, tgt = sel.random_tree_select(full, None, stream(sc.seed, "bench-warm", k))
        rel = synthetic_batch(wp, truth, obs, tgt)
        est, _ = update(est, p, absolute_measurements(wp, truth)[0], rel)
    return predict(est, p, None), p


def bench_selection(
    sats: Sequence[int] = (10, 50),
    budgets: Sequence[int] = (5,),
    strategies: Sequence[str] = sel.STRATEGIES,
    reps: int | None = None,
    warm_steps: int = 5,
    scenario: Scenario | None = None,
    out: Path | None = None,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Median (and 90th percentile) ms per ``select_for_scenario`` call, per n, budget, strategy.

    ``scenario``: the base (e.g. ``scenarios/selection.yaml``); ``n_sats`` is overridden and
    the initial cube grows as n^(1/3) from the base's so the density stays that of the base.
    Writes ``out`` (JSON: machine info and rows) when given.
    """
    base = scenario or Scenario()
    rows = []
    for n in sats:
        grow = (n / base.n_sats) ** (1.0 / 3.0)
        data = base.model_dump(mode="json")
        data["n_sats"] = n
        data["initial"]["position_max_m"] = base.initial.position_max_m * max(1.0, grow)
        data["selection"]["sat_weights"] = None
        sc = Scenario.model_validate(data)
        est, p = _planning_estimate(sc, warm_steps)
        G = graphs.incidence(n, "complete")
        ok = np.ones((n, 6), dtype=bool)
        cfg = sel.config_for_scenario(sc)
        n_cand = int(sel.candidate_mask(G, est, p, ok, cfg).sum())
        k_reps = reps or (30 if n <= 20 else 10)
        for m in budgets:
            for s in strategies:
                scs = sc.model_copy(update={"selection": sc.selection.model_copy(update={"strategy": s, "budget": m})})
                sel.select_for_scenario(scs, 0, G, est, p, ok)  # warm-up (imports, caches)
                times = []
                for k in range(1, k_reps + 1):
                    t0 = time.perf_counter()
                    obs, _ = sel.select_for_scenario(scs, k, G, est, p, ok)
                    times.append((time.perf_counter() - t0) * 1e3)
                row = {
                    "n": n,
                    "budget": m,
                    "strategy": s,
                    "pairs": n * (n - 1),
                    "candidates": n_cand,
                    "selected": int(obs.size),
                    "ms_median": statistics.median(times),
                    "ms_p90": float(np.percentile(times, 90)),
                    "reps": k_reps,
                }
                rows.append(row)
                log(
                    f"n={n:4d} m={m:3d} {s:14s} candidates {n_cand:5d}  selected {row['selected']:5d}  "
                    f"median {row['ms_median']:9.3f} ms  p90 {row['ms_p90']:9.3f} ms"
                )
    if out is not None:
        write_json(Path(out), {"machine": machine_info(), "rows": rows})
    return rows
