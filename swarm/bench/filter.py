"""Benchmarks that print numbers and write JSON (never timed asserts)."""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from swarmcore import graphs
from swarmcore.agent import filter_params
from swarmcore.mekf import predict, update
from swarmcore.scenario import Scenario
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import (
    absolute_measurements,
    initial_estimate,
    initial_truth,
    step_truth,
    world_params,
)

__all__ = ["bench_filter", "machine_info"]


def machine_info() -> dict:
    import os

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }


def _inputs(n: int, graph: str, steps: int, seed: int):
    sc = Scenario(n_sats=n, seed=seed, graph={"kind": graph}, duration_s=float(steps))
    wp = world_params(sc)
    G = graphs.incidence(n, graph)
    obs, tgt = graphs.edges(G)
    truth = initial_truth(sc)
    est0 = initial_estimate(sc, truth, 0)
    params = filter_params(sc, 0)
    inputs = []
    for _ in range(steps):
        truth, gyro = step_truth(wp, truth)
        inputs.append((gyro[0], absolute_measurements(wp, truth)[0], synthetic_batch(wp, truth, obs, tgt)))
    return params, est0, inputs


def _time_filter(params, est0, inputs, method: str, warmup: int) -> list[float]:
    est = est0
    times = []
    for k, (gyro, ab, rel) in enumerate(inputs):
        t0 = time.perf_counter()
        est = predict(est, params, gyro)
        est, _ = update(est, params, ab, rel, method=method)
        dt = (time.perf_counter() - t0) * 1e3
        if k >= warmup:
            times.append(dt)
    return times


def _time_update_vs_peer(params, est0, inputs, warmup: int, repeats: int) -> tuple[list[float], list[float]]:
    """The measurement update alone on the same prior and the same measurements: ours
    (``update``, the auto form) and filterpy's ``KalmanFilter.update`` on the stacked
    problem (H, y, R of :func:`swarmcore.mekf.stacked_problem`, at the same linearisation).
    filterpy is the well-known peer: a textbook EKF update (S, K by inversion, Joseph P)."""
    from filterpy.kalman import KalmanFilter

    from swarmcore.mekf import gate, linearize, stacked_problem

    ours, peer = [], []
    est = est0
    for k, (gyro, ab, rel) in enumerate(inputs[: warmup + repeats]):
        prior = predict(est, params, gyro)
        t0 = time.perf_counter()
        est, _ = update(prior, params, ab, rel, method="auto")
        t_ours = (time.perf_counter() - t0) * 1e3
        # The peer gets the same accepted set at the same linearisation (its update has no gate).
        *_, accepted = gate(prior, params, rel)
        lin = linearize(prior, params, ab, rel.subset(accepted))
        N = prior.P.shape[0]
        H, y, R = stacked_problem(N, prior.n, lin)
        kf = KalmanFilter(dim_x=N, dim_z=y.size)
        kf.x = np.zeros(N)
        kf.P = prior.P.copy()
        t0 = time.perf_counter()
        kf.update(y, R=R, H=H)
        t_peer = (time.perf_counter() - t0) * 1e3
        if k >= warmup:
            ours.append(t_ours)
            peer.append(t_peer)
    return ours, peer


def bench_filter(
    sats: list[int],
    graph: str = "complete",
    steps: int | None = None,
    stacked_max_n: int = 25,
    peer_max_n: int = 25,
    seed: int = 0,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Median ms per filter step (predict + update, one filter), fast vs stacked reference;
    and the update alone against filterpy's ``KalmanFilter.update`` on the same stacked
    problem (the peer column), measured in the same run."""
    rows = []
    for n in sats:
        k = steps or (30 if n <= 25 else 8 if n <= 60 else 5)
        warm = 2 if k > 4 else 1
        params, est0, inputs = _inputs(n, graph, k + warm, seed)
        fast = _time_filter(params, est0, inputs, "auto", warm)
        row: dict[str, Any] = {
            "n": n,
            "graph": graph,
            "measurements_per_step": len(inputs[0][2]),
            "ms_per_step_median": statistics.median(fast),
            "stacked_ms_per_step_median": None,
            "ratio": None,
        }
        if n <= stacked_max_n:
            ks = min(len(inputs), warm + (10 if n <= 12 else 3))
            stacked = _time_filter(params, est0, inputs[:ks], "stacked", warm)
            row["stacked_ms_per_step_median"] = statistics.median(stacked)
            row["ratio"] = row["stacked_ms_per_step_median"] / row["ms_per_step_median"]
        row["update_ms_median"] = row["filterpy_update_ms_median"] = row["peer_ratio"] = None
        if n <= peer_max_n:
            ours, peer = _time_update_vs_peer(params, est0, inputs, warm, 10 if n <= 12 else 3)
            row["update_ms_median"] = statistics.median(ours)
            row["filterpy_update_ms_median"] = statistics.median(peer)
            row["peer_ratio"] = row["filterpy_update_ms_median"] / row["update_ms_median"]
        log(
            f"n={n:4d} {graph:12s} m={row['measurements_per_step']:5d}  fast {row['ms_per_step_median']:9.3f} ms"
            + (
                f"  stacked {row['stacked_ms_per_step_median']:9.3f} ms  ratio {row['ratio']:7.1f}×"
                if row["ratio"] is not None
                else ""
            )
            + (
                f"  | update {row['update_ms_median']:8.3f} ms  filterpy {row['filterpy_update_ms_median']:9.3f} ms"
                f"  peer ratio {row['peer_ratio']:6.1f}×"
                if row["peer_ratio"] is not None
                else ""
            )
        )
        rows.append(row)
    return rows


def bench_late(n: int = 10, history_s: float = 10.0, lags=(0, 1, 2, 5, 10), steps: int = 40, seed: int = 0,
               log: Callable[[str], None] = print) -> list[dict]:
    """Cost of late measurements for one agent's filter (:class:`swarmcore.agent.AgentFilter`):
    ms per step when every peer batch arrives ``lag`` steps late and is replayed (0: on time),
    with a history of ``history_s``. The replay re-runs ``lag`` steps each step."""
    from swarmcore.agent import AgentFilter

    sc = Scenario(n_sats=n, seed=seed, duration_s=float(steps))
    params, est0, inputs = _inputs(n, "complete", steps, seed)
    hist = int(np.ceil(history_s / sc.dt_s))
    rows = []
    for lag in lags:
        f = AgentFilter(params, est0, "cooperative", late="replay", history_steps=hist, prior_pending=False)
        times, replayed = [], 0
        for k, (gyro, ab, rel) in enumerate(inputs, start=1):
            own = rel.subset(rel.observer == 0)
            peers = rel.subset(rel.observer != 0)
            on_time = rel if lag == 0 else own
            late = {}
            if lag and k - lag >= 1:
                _g, _a, old = inputs[k - lag - 1]
                late = {k - lag: old.subset(old.observer != 0)}
            t0 = time.perf_counter()
            _rep, lrep = f.step(k, gyro, ab, on_time, late=late)
            dt = (time.perf_counter() - t0) * 1e3
            if k > lag + 3:
                times.append(dt)
                replayed += lrep.replayed_steps
            del peers
        row = {"n": n, "history_s": history_s, "lag_steps": lag, "ms_per_step_median": statistics.median(times),
               "replayed_steps_per_step": replayed / len(times), "measurements_per_step": len(inputs[0][2])}
        rows.append(row)
        log(f"n={n} lag {lag:2d} steps: {row['ms_per_step_median']:8.3f} ms/step "
            f"(replaying {row['replayed_steps_per_step']:.1f} steps each step)")
    base = rows[0]["ms_per_step_median"]
    for r in rows:
        r["ratio_to_on_time"] = r["ms_per_step_median"] / base
    return rows
