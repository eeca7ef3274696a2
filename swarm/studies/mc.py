"""Monte Carlo over seeds: run i uses seed S + i, on a local process pool or a Dask cluster.

Each run is one task (:func:`run_one`: scenario as a dict and a seed in, summary out) of a
study (:func:`swarm.studies.executor.run_study`): as each run finishes, this process writes its
folder ``run_XXXX/`` and appends its summary to ``results.jsonl``; ``resume`` skips every
seed already there. A run that fails is listed in ``mc.json`` under ``failed`` (seed and
error) and left out of the statistics; the other runs complete.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from swarm.outputs import write_json, write_run
from swarm.studies.executor import ResultStore, open_executor, run_study
from swarmcore.scenario import Scenario

__all__ = ["run_mc", "run_one", "aggregate", "RESULTS"]

#: the study's result stream, in the output folder
RESULTS = "results.jsonl"


def run_one(data: dict, seed: int, arrays: bool = False):
    """One run (a task: plain values in, plain values out): the scenario ``data`` with
    ``seed``. Returns the summary, or the whole :class:`~swarmcore.result.RunResult` when ``arrays``."""
    from swarm.simulation import simulate_scenario
    from swarmrt.scenario_files import scenario_from_dict

    res = simulate_scenario(scenario_from_dict({**data, "seed": seed}, f"run with seed {seed}"))
    return res if arrays else res.summary()


def _write(run_dir: Path, data: dict, seed: int, payload) -> dict:
    """The run folder, written by the study's own process (workers may be other hosts)."""
    if isinstance(payload, dict):
        run_dir.mkdir(parents=True, exist_ok=True)
        sc = Scenario.model_validate({**data, "seed": seed})
        (run_dir / "scenario.yaml").write_text(yaml.safe_dump(sc.model_dump(mode="json"), sort_keys=False))
        write_json(run_dir / "summary.json", payload)
        return payload
    return write_run(payload, run_dir, arrays=True)


def _leaves(d: dict, prefix=""):
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            yield from _leaves(v, key + ".")
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            yield key, float(v)


def aggregate(summaries: list[dict]) -> dict:
    """Mean, std, min and max across runs of every numeric field of the accuracy,
    consistency, traffic and timing blocks (``rms*``, ``nees``, ``gate``, ``relative``,
    ``traffic``, ``cpu``, ``timing``), whatever the estimator."""
    fields: dict[str, list[float]] = {}
    for s in summaries:
        for section in ("rms", "rms_second_half", "nees", "gate", "relative", "traffic", "cpu", "timing"):
            if section in s and isinstance(s[section], dict):
                for k, v in _leaves(s[section], section + "."):
                    fields.setdefault(k, []).append(v)
    stats = {}
    for k, vals in sorted(fields.items()):
        a = np.asarray(vals)
        stats[k] = {
            "mean": float(a.mean()),
            "std": float(a.std(ddof=1)) if a.size > 1 else 0.0,
            "min": float(a.min()),
            "max": float(a.max()),
        }
    return stats


def run_mc(
    sc: Scenario,
    runs: int,
    out: Path,
    *,
    seed: int | None = None,
    workers: int = 2,
    arrays: bool = False,
    progress: Callable[[int, int], None] | None = None,
    cluster: str | None = None,
    resume: bool = False,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Run ``runs`` simulations seeded ``seed + i`` on ``workers`` local processes or the
    Dask scheduler at ``cluster``; write each run, ``results.jsonl`` and ``mc.json``.

    ``mc.json``: ``stats`` over the runs that succeeded, ``per_run`` for them, ``failed``
    (seed and error) for the others, ``skipped`` (runs reused by ``resume``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = sc.seed if seed is None else seed
    data = sc.model_dump(mode="json")
    seeds = [base + i for i in range(runs)]
    jobs = {str(s): (data, s, arrays) for s in seeds}
    dirs = {str(base + i): out / f"run_{i:04d}" for i in range(runs)}
    store = ResultStore(out / RESULTS, resume=resume)
    try:
        with open_executor(workers, cluster) as ex:
            st = run_study(ex, run_one, jobs, store=store, progress=progress, log=log,
                           on_result=lambda key, payload: _write(dirs[key], data, int(key), payload))
    finally:
        store.close()
    ok = [s for s in seeds if str(s) in st.results]
    ordered = [st.results[str(s)] for s in ok]
    mc = {
        "scenario": sc.name,
        "runs": runs,
        "seeds": seeds,
        "n_sats": sc.n_sats,
        "runs_ok": len(ok),
        "failed": [{"seed": s, "error": st.errors[str(s)]} for s in seeds if str(s) in st.errors],
        "skipped": st.skipped,
        "backend": ex.description,
        "estimator": sc.estimator.kind,
        "stats": aggregate(ordered),
        "per_run": [
            {"seed": s, "rms": r["rms"], "rms_second_half": r["rms_second_half"], "nees_mean": r["nees"]["mean"],
             "relative": r.get("relative"), "traffic": r.get("traffic")}
            for s, r in zip(ok, ordered)
        ],
    }
    write_json(out / "mc.json", mc)
    return mc
