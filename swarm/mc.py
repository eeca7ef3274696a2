"""Monte Carlo over seeds: run i uses seed S + i, in parallel worker processes."""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable

import numpy as np

from swarmcore.scenario import Scenario

from .outputs import write_json, write_run

__all__ = ["run_mc", "aggregate"]


def _one(args):
    data, seed, out_dir, arrays = args
    from .models import simulate_scenario

    sc = Scenario.model_validate({**data, "seed": seed})
    res = simulate_scenario(sc)
    return seed, write_run(res, Path(out_dir), arrays=arrays)


def _leaves(d: dict, prefix=""):
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            yield from _leaves(v, key + ".")
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            yield key, float(v)


def aggregate(summaries: list[dict]) -> dict:
    """Mean, std, min and max across runs of every numeric ``rms*`` and ``nees`` field."""
    fields: dict[str, list[float]] = {}
    for s in summaries:
        for section in ("rms", "rms_second_half", "nees", "gate", "timing"):
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
) -> dict:
    """Run ``runs`` simulations seeded ``seed + i``; write each run and ``mc.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = sc.seed if seed is None else seed
    data = sc.model_dump(mode="json")
    jobs = [(data, base + i, str(out / f"run_{i:04d}"), arrays) for i in range(runs)]
    results: dict[int, dict] = {}
    if workers <= 1:
        for k, job in enumerate(jobs):
            s, summ = _one(job)
            results[s] = summ
            if progress:
                progress(k + 1, runs)
    else:
        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futs = [pool.submit(_one, job) for job in jobs]
            for k, fut in enumerate(as_completed(futs)):
                s, summ = fut.result()
                results[s] = summ
                if progress:
                    progress(k + 1, runs)
    ordered = [results[base + i] for i in range(runs)]
    mc = {
        "scenario": sc.name,
        "runs": runs,
        "seeds": [base + i for i in range(runs)],
        "n_sats": sc.n_sats,
        "stats": aggregate(ordered),
        "per_run": [
            {"seed": base + i, "rms": s["rms"], "rms_second_half": s["rms_second_half"], "nees_mean": s["nees"]["mean"]}
            for i, s in enumerate(ordered)
        ],
    }
    write_json(out / "mc.json", mc)
    return mc
