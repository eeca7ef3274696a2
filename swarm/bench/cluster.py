"""``swarm bench cluster``: Monte Carlo runs per minute on the local pool and on a Dask
cluster of the same size on this machine, and the scheduling overhead per task.

* **runs per minute**: the same study (``mc.run_one`` over R seeds) through
  :func:`swarm.studies.executor.run_study` on ``LocalPool(W)`` and on a scheduler with W
  single-threaded workers started here with Dask's own commands
  (:class:`swarm.studies.dask_local.LocalDaskProcesses`). Each backend is timed twice: *cold* —
  the local pool spawns its processes for the study (what ``swarm mc`` pays every time),
  fresh Dask workers import the project with their first task — and *warm* — the same
  processes again, the steady state of a long study or a long-lived cluster (``repeats``
  times, alternating the backends; the median is reported).
* **scheduling overhead per task**: a no-op task (:func:`swarm.studies.executor.noop`) through
  each backend, (a) one at a time — the round trip, submit to result — and (b) N at once,
  wall time / N — the throughput cost, what a study of N short runs pays.
* ``in_process_run_s``: one run in this process (after a warm-up), for the ideal
  ``W × 60 / run_s`` runs per minute.

Every result is checked to be the same on both backends (all but wall-clock fields).
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from typing import Any

from swarm.studies.executor import DaskCluster, Executor, LocalPool, noop, run_study
from swarm.studies.mc import run_one
from swarmcore.scenario import Scenario

__all__ = ["bench_cluster"]


def _noop_overhead(ex: Executor, n: int) -> dict:
    """Round-trip latency of one no-op task at a time, and ms per task for n at once."""
    run_study(ex, noop, {f"warm{i}": (i,) for i in range(4)})  # processes up, function imported
    rtt = []
    for i in range(n):
        t0 = time.perf_counter()
        ex.submit(f"rt{i}", noop, i)
        (oc,) = list(ex.as_completed())
        rtt.append((time.perf_counter() - t0) * 1e3)
        assert oc.ok and oc.result == i, oc
    st = run_study(ex, noop, {f"b{i}": (i,) for i in range(n)})
    assert not st.errors and len(st.results) == n
    rtt.sort()
    return {
        "tasks": n,
        "round_trip_ms_median": statistics.median(rtt),
        "round_trip_ms_p90": rtt[int(0.9 * (n - 1))],
        "batch_ms_per_task": st.wall_s / n * 1e3,
    }


def _comparable(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("timing", "cpu")}


def bench_cluster(sc: Scenario, runs: int = 40, workers: int = 2, noop_tasks: int = 200, repeats: int = 3,
                  log: Callable[[str], None] = print) -> dict:
    from swarm.studies.dask_local import LocalDaskProcesses

    load_before = os.getloadavg()
    data = sc.model_dump(mode="json")
    jobs = {str(sc.seed + i): (data, sc.seed + i, False) for i in range(runs)}
    run_one(data, sc.seed)  # warm-up (imports, compiled kernels)
    t0 = time.perf_counter()
    for i in range(3):
        run_one(data, sc.seed + i)
    run_s = (time.perf_counter() - t0) / 3
    log(f"{sc.name}: n={sc.n_sats}, {sc.duration_s:g} s simulated; one run in this process {run_s * 1e3:.0f} ms "
        f"(ideal on {workers} processes: {workers * 60 / run_s:.0f} runs/min)")
    rows: list[dict[str, Any]] = []
    results = []

    def study(backend: str, ex: Executor) -> dict:
        st = run_study(ex, run_one, jobs)
        assert not st.errors, st.errors
        row = {"backend": backend, "runs": runs, "wall_s": st.wall_s, "runs_per_min": runs / st.wall_s * 60}
        log(f"  {backend:<34} {row['runs_per_min']:8.1f} runs/min  ({runs} runs in {st.wall_s:.2f} s)")
        rows.append(row)
        results.append({k: _comparable(v) for k, v in st.results.items()})
        return row

    local_name, dask_name = f"local pool, {workers} processes", f"dask, {workers} workers"
    # Both backends stay up side by side and the warm studies alternate, so a change in
    # the machine's load (it is shared) hits both alike.
    with LocalPool(workers) as pool, LocalDaskProcesses(workers) as c, DaskCluster(c.address) as dask:
        study(f"{local_name}, cold", pool)
        study(f"{dask_name}, cold", dask)
        for _ in range(repeats):
            study(f"{local_name}, warm", pool)
            study(f"{dask_name}, warm", dask)
        local_noop = _noop_overhead(pool, noop_tasks)
        dask_noop = _noop_overhead(dask, noop_tasks)
    identical = all(r == results[0] for r in results)
    warm = {name: statistics.median(r["runs_per_min"] for r in rows if r["backend"] == f"{name}, warm")
            for name in (local_name, dask_name)}
    log(f"  warm, median of {repeats}: {local_name} {warm[local_name]:.1f} runs/min, {dask_name} {warm[dask_name]:.1f} runs/min")
    for name, o in (("local pool", local_noop), ("dask", dask_noop)):
        log(f"  no-op task on {name:<10}: round trip {o['round_trip_ms_median']:.2f} ms median "
            f"({o['round_trip_ms_p90']:.2f} p90); {o['batch_ms_per_task']:.3f} ms per task for {o['tasks']} at once")
    log(f"  results identical on both backends: {identical}")
    load_after = os.getloadavg()
    log(f"  load average (1 min) {load_before[0]:.1f} before, {load_after[0]:.1f} after, on {os.cpu_count()} CPUs "
        "(other work on a shared machine skews every number)")
    return {
        "scenario": sc.name,
        "n_sats": sc.n_sats,
        "duration_s": sc.duration_s,
        "workers": workers,
        "in_process_run_s": run_s,
        "ideal_runs_per_min": workers * 60 / run_s,
        "rows": rows,
        "warm_runs_per_min_median": {"local_pool": warm[local_name], "dask": warm[dask_name]},
        "noop": {"local_pool": local_noop, "dask": dask_noop},
        "identical_results": identical,
        "load_avg_1min": {"before": load_before[0], "after": load_after[0]},
    }
