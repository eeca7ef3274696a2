"""Paired comparison of measurement-selection strategies (dissertation Table 6.1, Figure 6.3).

Every strategy runs over the same seeds S, S+1, …, S+R−1: the same truth, the same sensor
noise (every stream is keyed by seed, purpose and step, and relative noise is drawn for all
n×n pairs each step), so per-run differences are due to the selection alone (paired runs).

Writes into OUT:

* ``compare.json`` — per run and strategy: orientation / position error (full run and second
  half), selection time per step, measurements per step, the (observer, target) counts;
  per strategy: means, ratios to ``random`` (ratio of means, and the mean of per-run ratios),
  paired wins and a Wilcoxon signed-rank p-value against ``random`` and ``greedy``.
* ``compare.md`` — the Table 6.1-style table and the summary.
* ``heatmap_<strategy>.png`` — how often each (observer, target) pair was chosen, mean per
  run (Figure 6.3).

Errors are the run summary's "others" figures (:func:`swarmcore.metrics.summarize`): for each
filter, the RMS over time of its errors on every *other* satellite, averaged over filters —
the cooperative part of the estimate, which the relative measurements drive. (Each filter's
own satellite is pinned by its star tracker and GPS.) ``ref`` repeats them for the reference
filter 0 alone, the one the selector plans with.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from swarm.outputs import write_json
from swarm.studies.executor import ResultStore, open_executor, run_study
from swarmcore.scenario import Scenario
from swarmcore.selection import STRATEGIES

__all__ = ["run_compare", "run_one", "METRICS", "RESULTS"]

#: the study's result stream, in the output folder
RESULTS = "results.jsonl"

#: (key, label) of the four Table 6.1 figures.
METRICS = (
    ("att_full", "orientation, full run (rad)"),
    ("att_half", "orientation, second half (rad)"),
    ("pos_full", "position, full run (m)"),
    ("pos_half", "position, second half (m)"),
)


def _ref_rms(err: np.ndarray, start: int) -> float:
    """RMS over time from ``start`` and over the other satellites, of filter 0's errors."""
    e = err[start:, 0, 1:]
    return float(np.sqrt(np.nanmean(e**2)))


_timing = threading.local()
_timer: Callable | None = None  # the timing wrapper this process installed (once)


def _install_selection_timer() -> None:
    """Wrap the entry point the simulator imports at call time
    (``swarmcore.selection.select_for_scenario``) once per process, so that every call is
    timed into the list of the run on the calling thread (``_timing.ms``) — correct when a
    Dask worker runs several runs at once on threads. Outside a run it only passes through."""
    from swarmcore import selection

    global _timer
    if _timer is not None and selection.select_for_scenario is _timer:
        return
    inner = selection.select_for_scenario

    def timed(*a, **kw):
        t0 = time.perf_counter()
        out = inner(*a, **kw)
        sink = getattr(_timing, "ms", None)
        if sink is not None:
            sink.append((time.perf_counter() - t0) * 1e3)
        return out

    _timer = selection.select_for_scenario = timed


def run_one(data: dict, strategy: str, seed: int) -> dict:
    """One (strategy, seed) run (a task: plain values in, plain values out), with every
    selector call timed."""
    from swarm.simulation import simulate_scenario
    from swarmrt.scenario_files import scenario_from_dict

    sc = scenario_from_dict({**data, "seed": seed, "selection": {**data["selection"], "strategy": strategy}},
                            f"run {strategy} with seed {seed}")
    _install_selection_timer()
    times_ms: list[float] = []
    _timing.ms = times_ms
    try:
        t0 = time.perf_counter()
        res = simulate_scenario(sc)
        wall = time.perf_counter() - t0
    finally:
        _timing.ms = None
    s = res.summary()
    K = res.att_err_rad.shape[0]
    t_ms = np.asarray(times_ms)
    return {
        "strategy": strategy,
        "seed": seed,
        "att_full": s["rms"]["others"]["att_rad"],
        "att_half": s["rms_second_half"]["others"]["att_rad"],
        "pos_full": s["rms"]["others"]["pos_m"],
        "pos_half": s["rms_second_half"]["others"]["pos_m"],
        "self": {"rms": s["rms"]["self"], "rms_second_half": s["rms_second_half"]["self"]},
        "ref": {
            "att_full": _ref_rms(res.att_err_rad, 0),
            "att_half": _ref_rms(res.att_err_rad, K // 2),
            "pos_full": _ref_rms(res.pos_err_m, 0),
            "pos_half": _ref_rms(res.pos_err_m, K // 2),
        },
        "nees_mean": s["nees"]["mean"],
        "gate": s["gate"],
        "measurements_per_step": float(res.schedule.sum(axis=(1, 2)).mean()),
        "select_ms_median": float(np.median(t_ms)) if t_ms.size else None,
        "select_ms_mean": float(np.mean(t_ms)) if t_ms.size else None,
        "counts": res.schedule.sum(axis=0).astype(int).tolist(),
        "wall_s": wall,
    }


def _paired(a: np.ndarray, b: np.ndarray) -> dict:
    """Paired statistics of ``a`` against ``b`` (same seeds): ratio of means, mean of
    per-run ratios, runs where a < b, and the two-sided Wilcoxon signed-rank p-value."""
    from scipy.stats import wilcoxon

    out = {
        "ratio_of_means": float(a.mean() / b.mean()),
        "mean_of_ratios": float(np.mean(a / b)),
        "wins": int(np.sum(a < b)),
        "runs": int(a.size),
        "wilcoxon_p": None,
    }
    if a.size >= 5 and np.any(a != b):
        out["wilcoxon_p"] = float(wilcoxon(a, b).pvalue)
    return out


def _heatmap(counts: np.ndarray, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = counts.shape[0]
    fig, ax = plt.subplots(figsize=(5.2, 4.4), dpi=120)
    im = ax.imshow(counts, cmap="viridis", origin="upper")
    ax.set_xlabel("target j")
    ax.set_ylabel("observer i")
    ax.set_xticks(range(n))
    ax.set_yticks(range(n))
    ax.set_title(title, fontsize=9)
    if n <= 12:
        hi = counts.max() if counts.size else 0
        for i in range(n):
            for j in range(n):
                ax.text(j, i, f"{counts[i, j]:.0f}", ha="center", va="center", fontsize=6,
                        color="black" if counts[i, j] > 0.6 * hi else "white")
    fig.colorbar(im, ax=ax, label="times chosen per run (mean)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt(v: float) -> str:
    return f"{v:.3f}" if np.isfinite(v) else "—"


def _markdown(res: dict) -> str:
    strategies = res["strategies"]
    seeds = res["seeds"]
    lines = [
        f"# Sensor selection: {res['scenario']} (n = {res['n_sats']}, budget {res['budget']} of "
        f"{res['n_sats'] * (res['n_sats'] - 1)}, {res['duration_s']:g} s, {len(seeds)} paired runs)",
        "",
        "Errors: RMS over time of each filter's errors on the other satellites, mean over filters.",
        "",
    ]
    for key, label in METRICS:
        lines += [f"## {label}", "", "| run | seed | " + " | ".join(strategies) + " |",
                  "|---|---|" + "---:|" * len(strategies)]
        for r, seed in enumerate(seeds):
            vals = [res["per_run"][s][r][key] for s in strategies]
            best = int(np.argmin([np.inf if s == "complete" else v for s, v in zip(strategies, vals)]))
            cells = [f"**{v:.3g}**" if i == best else f"{v:.3g}" for i, v in enumerate(vals)]
            lines.append(f"| {r + 1} | {seed} | " + " | ".join(cells) + " |")
        means = [res["summary"][s][key]["mean"] for s in strategies]
        lines.append("| mean | | " + " | ".join(f"{v:.3g}" for v in means) + " |")
        lines.append("")
    lines += ["Bold: lowest error among the strategies held to the budget (complete excluded).", ""]
    lines += ["## Summary", "", "| strategy | meas/step | share with sat 0 | select ms/step (median) | "
              + " | ".join(f"{k} / random" for k, _ in METRICS) + " | "
              + " | ".join(f"{k} / greedy" for k, _ in METRICS) + " |",
              "|---|---:|---:|---:|" + "---:|" * (2 * len(METRICS))]
    for s in strategies:
        sm = res["summary"][s]
        vr = [sm[k]["vs_random"]["ratio_of_means"] if sm[k].get("vs_random") else float("nan") for k, _ in METRICS]
        vg = [sm[k]["vs_greedy"]["ratio_of_means"] if sm[k].get("vs_greedy") else float("nan") for k, _ in METRICS]
        ms = sm["select_ms_median"]
        lines.append(
            f"| {s} | {sm['measurements_per_step']:.2f} | {sm['share_touching_ref']:.3f} | {ms:.3f} | "
            + " | ".join(_fmt(v) for v in vr) + " | " + " | ".join(_fmt(v) for v in vg) + " |"
        )
    lines += ["", "Ratios are ratios of the means over runs. \"share with sat 0\": fraction of the chosen "
              "measurements that involve satellite 0, whose filter the selector plans with (0.2 for an "
              "unbiased choice at n = 10). Selection time: median over runs of each run's median ms per "
              "`select_for_scenario` call (n = 10, while other work shared the machine).", ""]
    for ref in ("random", "greedy"):
        if ref not in strategies:
            continue
        lines += [f"## Paired against {ref}: runs with a lower error, two-sided Wilcoxon signed-rank p", "",
                  "| strategy | " + " | ".join(k for k, _ in METRICS) + " |", "|---|" + "---:|" * len(METRICS)]
        for s in strategies:
            if s == ref:
                continue
            cells = []
            for k, _ in METRICS:
                pr = res["summary"][s][k][f"vs_{ref}"]
                pv = "n/a" if pr["wilcoxon_p"] is None else f"{pr['wilcoxon_p']:.2g}"
                cells.append(f"{pr['wins']}/{pr['runs']} (p={pv})")
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
        lines.append("")
    if res.get("failed"):
        lines += [f"## Failed runs (seeds {', '.join(map(str, res['seeds_dropped']))} left out of every strategy)", "",
                  "| strategy | seed | error |", "|---|---|---|"]
        for f in res["failed"]:
            lines.append(f"| {f['strategy']} | {f['seed']} | {f['error'].splitlines()[0] if f['error'] else ''} |")
        lines.append("")
    return "\n".join(lines)


def run_compare(
    sc: Scenario,
    runs: int,
    out: Path,
    *,
    strategies: Sequence[str] = STRATEGIES,
    seed: int | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
    cluster: str | None = None,
    resume: bool = False,
    log: Callable[[str], None] | None = None,
) -> dict:
    """Run every strategy over seeds ``seed + i`` (i < runs) on ``workers`` local processes
    or the Dask scheduler at ``cluster``; write results.jsonl (as runs finish), compare.json,
    compare.md and one heat map per strategy into ``out``; return the JSON document.

    A run that fails is listed under ``failed`` (strategy, seed, error) and its seed is left
    out of every strategy's statistics (they are paired); ``resume`` reuses finished runs."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = sc.seed if seed is None else seed
    all_seeds = [base + i for i in range(runs)]
    data = sc.model_dump(mode="json")
    strategies = list(strategies)
    jobs = {f"{s}@{sd}": (data, s, sd) for sd in all_seeds for s in strategies}
    store = ResultStore(out / RESULTS, resume=resume)
    try:
        with open_executor(workers, cluster) as ex:
            st = run_study(ex, run_one, jobs, store=store, progress=progress, log=log)
    finally:
        store.close()
    failed = [{"strategy": s, "seed": sd, "error": st.errors[f"{s}@{sd}"]} for sd in all_seeds for s in strategies
              if f"{s}@{sd}" in st.errors]
    # Paired statistics need every strategy on a seed: a seed with a failed run is dropped.
    seeds = [sd for sd in all_seeds if all(f"{s}@{sd}" in st.results for s in strategies)]
    per_run = {s: [st.results[f"{s}@{sd}"] for sd in seeds] for s in strategies}
    doc = {
        "scenario": sc.name,
        "n_sats": sc.n_sats,
        "budget": sc.selection.budget,
        "duration_s": sc.duration_s,
        "strategies": strategies,
        "seeds": seeds,
        "failed": failed,
        "seeds_dropped": [sd for sd in all_seeds if sd not in seeds],
        "skipped": st.skipped,
        "backend": ex.description,
    }
    if not seeds:
        write_json(out / "compare.json", doc)
        return doc
    summary: dict[str, dict] = {}
    for s in strategies:
        rows = per_run[s]
        sm: dict = {}
        for key, _ in METRICS:
            a = np.array([r[key] for r in rows])
            entry: dict[str, Any] = {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if a.size > 1 else 0.0}
            for ref in ("random", "greedy"):
                if ref in per_run and ref != s:
                    entry[f"vs_{ref}"] = _paired(a, np.array([r[key] for r in per_run[ref]]))
            sm[key] = entry
            b = np.array([r["ref"][key] for r in rows])
            sm.setdefault("ref_filter", {})[key] = float(b.mean())
        ms = [r["select_ms_median"] for r in rows if r["select_ms_median"] is not None]
        sm["select_ms_median"] = float(np.median(ms)) if ms else float("nan")
        sm["select_ms_mean"] = float(np.mean([r["select_ms_mean"] for r in rows if r["select_ms_mean"] is not None])) if ms else float("nan")
        sm["measurements_per_step"] = float(np.mean([r["measurements_per_step"] for r in rows]))
        sm["nees_mean"] = float(np.mean([r["nees_mean"] for r in rows]))
        counts = np.mean([np.asarray(r["counts"]) for r in rows], axis=0)
        sm["counts_mean_per_run"] = counts.round(3).tolist()
        tot = counts.sum()
        sm["share_touching_ref"] = float((counts[0].sum() + counts[:, 0].sum()) / tot) if tot else float("nan")
        summary[s] = sm
        _heatmap(counts, f"{s}: pairs chosen, mean over {len(seeds)} runs of {sc.duration_s:g} s", out / f"heatmap_{s}.png")
    doc = {
        **doc,
        "error_definition": "RMS over time of each filter's errors on the other satellites, mean over filters "
        "(summary 'others'); ref_filter: filter 0 alone",
        "summary": summary,
        "per_run": {s: [{k: v for k, v in r.items() if k != "counts"} for r in per_run[s]] for s in strategies},
    }
    write_json(out / "compare.json", doc)
    (out / "compare.md").write_text(_markdown(doc))
    return doc
