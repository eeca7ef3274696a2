"""StarFOX-like study (``swarm starfox``): angles-only relative navigation, one observer vs several.

Flies ``scenarios/starfox.yaml`` (or another file) in-process over R seeds in two configurations:

* ``several``: every satellite observes every other (graph.kind complete);
* ``single``: satellite 0 (the one with GPS) is the only observer (graph.kind matrix, row 0),

and reports, over the second half of each run, for satellite 0's filter and its estimates
of satellites 1..n−1 relative to itself (what StarFOX's figure is about):

* ``err_pct``: |relative position error| / range (%), averaged over targets and steps;
* ``sigma_pct``: the filter's 1σ, √trace(P_rel_pos), / range (%);
* ``nees_pos``: relative-position NEES / 3 (1 when consistent);
* ``nees_pos_abs``: satellite 0's filter, every satellite's position (in H) NEES / 3;
* ``nees6``: the run summary's pose NEES / 6 over every filter and satellite (includes the
  other satellites' attitudes, which bearings do not observe: they drift, nonlinearly).

:func:`run_starfox` returns each run and the mean, spread and median over the seeds of each
configuration; ``swarm starfox`` prints them, writes them as JSON and draws :func:`plot`.
The runs go through the studies' executors (:func:`swarm.studies.executor.open_executor`:
the local pool or a Dask scheduler), each with its seed, so the numbers do not depend on
where or in which order they ran.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from swarm.simulation import simulate_scenario
from swarmrt.scenario_files import load_scenario

__all__ = ["CONFIGS", "KEYS", "one_run", "run_starfox", "plot"]

#: The two configurations: satellite 0 the only observer, or every satellite observing every other.
CONFIGS = ("single", "several")
#: The per-run numbers aggregated over the seeds.
KEYS = ("err_pct", "sigma_pct", "nees_pos", "nees_pos_abs", "nees6", "claimed", "range_km")


def single_observer(n: int) -> list[str]:
    m = np.eye(n, dtype=int)
    m[0, 1:] = 1
    return ["graph.kind=matrix", f"graph.matrix={json.dumps(m.tolist())}"]


def one_run(args: tuple[str, str, int, list[str]]) -> dict:
    path, config, seed, extra = args
    sc = load_scenario(path, extra, seed=seed)
    if config == "single":
        sc = load_scenario(path, [*extra, *single_observer(sc.n_sats)], seed=seed)
    rows: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def on_step(s) -> None:
        for v in s.views:
            if v.own == 0:
                rows.append((s.k, s.r_H.copy(), v.ids.copy(), v.r_H.copy(), v.P_rel_pose.copy(), v.P_pose.copy()))

    res = simulate_scenario(sc, on_step=on_step)
    K = sc.steps
    err, sig, nees, nees_abs = [], [], [], []
    claimed = 0  # (step, target) pairs of the second half at which satellite 0's view claims the target
    series: list[tuple[float, float, float]] = []  # (t_s, mean |Δr|/range %, mean 1σ/range %) per step
    for k, r_true, ids, r_hat, P_rel, P_pose in rows:
        # A decentralized estimator claims only the peers it tracks at the step (ci, gbp:
        # those it fused with; pairwise: the neighbours it heard): rows by id, not by index.
        at = {int(j): r for r, j in enumerate(ids)}
        if 0 not in at:
            continue
        o = at[0]
        pct = []
        for j in range(1, sc.n_sats):
            if j not in at:
                continue
            d_true = r_true[j] - r_true[0]
            rng = float(np.linalg.norm(d_true))
            e = (r_hat[at[j]] - r_hat[o]) - d_true
            pct.append((100 * np.linalg.norm(e) / rng, 100 * np.sqrt(np.trace(P_rel[at[j]][3:6, 3:6])) / rng))
        series.append((k * sc.dt_s, *(np.mean(pct, axis=0).tolist() if pct else [float("nan")] * 2)))
        if k < K // 2:
            continue
        for j, r in at.items():
            e = r_hat[r] - r_true[j]
            nees_abs.append(float(e @ np.linalg.solve(P_pose[r][3:6, 3:6], e)) / 3.0)
        for j in range(1, sc.n_sats):
            if j not in at:
                continue
            claimed += 1
            d_true = r_true[j] - r_true[0]
            e = (r_hat[at[j]] - r_hat[o]) - d_true
            rng = float(np.linalg.norm(d_true))
            P = P_rel[at[j]][3:6, 3:6]
            err.append(np.linalg.norm(e) / rng)
            sig.append(np.sqrt(np.trace(P)) / rng)
            nees.append(float(e @ np.linalg.solve(P, e)) / 3.0)
    summ = res.summary()

    def mean(x: Sequence[Any]) -> float:
        return float(np.mean(x)) if x else float("nan")

    second_half = (K - K // 2) * (sc.n_sats - 1)
    return {"config": config, "seed": seed, "estimator": sc.estimator.kind, "err_pct": 100 * mean(err), "sigma_pct": 100 * mean(sig),
            "nees_pos": mean(nees), "nees_pos_abs": mean(nees_abs), "nees6": float(summ["nees"]["mean"]) / 6.0,
            "claimed": claimed / second_half,
            "range_km": float(np.mean([np.linalg.norm(rows[-1][1][j] - rows[-1][1][0]) for j in range(1, sc.n_sats)]) / 1e3),
            "gate_rejected": int(summ["gate"]["rejected"]) if "gate" in summ else None, "series": series}


def run_starfox(scenario: str | Path, runs: int, executor, configs: tuple[str, ...] = CONFIGS, sets: tuple[str, ...] = (),
                progress: Callable[[int, int], None] = lambda k, K: None, log: Callable[[str], None] = lambda s: None) -> dict:
    """``runs`` seeds (the scenario's seed + r) of each configuration on ``executor``; returns
    ``{"per_run": [...], "aggregate": {config: {"runs", key: {"mean", "std", "median"}}}, "failed": [...]}``."""
    if bad := [c for c in configs if c not in CONFIGS]:
        raise ValueError(f"unknown configuration(s) {bad}: expected some of {list(CONFIGS)}")
    base = load_scenario(scenario, list(sets)).seed
    tasks = [(str(scenario), c, base + r, list(sets)) for c in configs for r in range(runs)]
    for t in tasks:
        executor.submit(f"{t[1]}/{t[2]}", one_run, t)
    results, failed = [], []
    for done, o in enumerate(executor.as_completed(), start=1):
        if o.ok:
            results.append(o.result)
            log(json.dumps({k: v for k, v in o.result.items() if k != "series"}))
        else:
            failed.append({"run": o.key, "error": o.error})
        progress(done, len(tasks))
    results.sort(key=lambda r: (configs.index(r["config"]), r["seed"]))
    out = {}
    for c in configs:
        rs = [r for r in results if r["config"] == c]
        agg = {}
        for key in KEYS:
            v = np.array([r[key] for r in rs])
            agg[key] = {"mean": float(v.mean()) if v.size else float("nan"), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                        "median": float(np.median(v)) if v.size else float("nan")}
        out[c] = {"runs": len(rs), **agg}
    return {"per_run": results, "aggregate": out, "failed": failed}


def plot(results: list[dict], configs: tuple[str, ...] | list[str], path: str | Path) -> None:
    """Median over the seeds (and the 10–90 % band) of satellite 0's relative position error
    and of its 1σ, as a percentage of range, over time: StarFOX's figure, one observer
    against several."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    colours = {"single": "tab:red", "several": "tab:blue"}
    for c in configs:
        S = np.array([r["series"] for r in results if r["config"] == c])  # (runs, K, 3)
        if S.size == 0:
            continue
        t_min = S[0, :, 0] / 60.0
        col = colours.get(c)
        for idx, style, what in ((1, "-", "|error|"), (2, "--", "1σ")):
            med = np.nanmedian(S[:, :, idx], axis=0)
            ax.plot(t_min, med, style, color=col, label=f"{c} observer{'s' if c == 'several' else ''}: {what} (median of {len(S)})")
            if idx == 1:
                lo, hi = np.nanpercentile(S[:, :, idx], [10, 90], axis=0)
                ax.fill_between(t_min, lo, hi, color=col, alpha=0.15, linewidth=0)
    for level, lab in ((1.3, "StarFOX, one observer: 1.3 %"), (0.6, "StarFOX, several: 0.6 %")):
        ax.axhline(level, color="grey", linestyle=":", linewidth=1)
        ax.text(0.2, level * 1.05, lab, color="grey", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylim(0.05, 50)
    ax.set_xlabel("time (min)")
    ax.set_ylabel("relative position, % of range")
    ax.set_title("Angles-only, satellite 0's filter: error (band 10–90 %) and 1σ as a percentage of range")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: The estimators the per-estimator table compares (every one that flies bearings).
ESTIMATORS = ("full", "ci", "pairwise", "gbp")


def run_per_estimator(scenario: str | Path, runs: int, out_jsonl: str | Path, estimators: tuple[str, ...] = ESTIMATORS,
                      configs: tuple[str, ...] = CONFIGS, sets: tuple[str, ...] = (), seed: int | None = None,
                      log: Callable[[str], None] = lambda s: None) -> list[dict]:
    """:func:`one_run` of every estimator, configuration and seed (``seed`` or the scenario's,
    + r), seed by seed (so that a study cut short still compares every estimator on the same
    seeds), each appended to ``out_jsonl`` as it finishes; runs already there are kept, not
    run again. Returns every run (``series`` left out)."""
    path = Path(out_jsonl)
    done = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []
    have = {(r["estimator"], r["config"], r["seed"]) for r in done}
    base = load_scenario(scenario, list(sets)).seed if seed is None else seed
    for r in range(runs):
        for est in estimators:
            for c in configs:
                if (est, c, base + r) in have:
                    continue
                res = one_run((str(scenario), c, base + r, [*sets, f"estimator.kind={est}"]))
                res.pop("series")
                with path.open("a") as f:
                    f.write(json.dumps(res) + "\n")
                done.append(res)
                log(json.dumps(res))
    return done


def estimator_table(results: list[dict], estimators: tuple[str, ...] = ESTIMATORS, configs: tuple[str, ...] = CONFIGS) -> str:
    """The percentage-of-range table per estimator and configuration (Markdown), over the
    seeds every estimator of a configuration has run (paired): mean ± standard deviation
    over the seeds (median in brackets) of satellite 0's relative position error and 1σ as
    a percentage of range, its relative-position NEES/3 and the fraction of (step, target)
    pairs of the second half it claims an estimate of."""
    rows = ["| observers | estimator | seeds | \\|Δr\\| / range | 1σ / range | rel. position NEES/3 | abs. position NEES/3 | claimed |",
            "| --- | --- | ---: | --- | --- | --- | --- | ---: |"]
    for c in configs:
        seeds = sorted(set.intersection(*[{r["seed"] for r in results if r["config"] == c and r["estimator"] == e} for e in estimators]))
        for e in estimators:
            rs = [r for r in results if r["config"] == c and r["estimator"] == e and r["seed"] in seeds]
            if not rs:
                continue

            def stat(key: str, fmt: str, rs: list[dict] = rs) -> str:
                v = np.array([r[key] for r in rs])
                sd = f" ± {v.std(ddof=1):{fmt}}" if v.size > 1 else ""
                return f"{v.mean():{fmt}}{sd} ({np.median(v):{fmt}})"

            rows.append(f"| {c} | {e} | {len(rs)} | {stat('err_pct', '.2f')} % | {stat('sigma_pct', '.2f')} % | {stat('nees_pos', '.2f')} | "
                        f"{stat('nees_pos_abs', '.2f')} | {np.mean([r['claimed'] for r in rs]):.2f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    """``python -m swarm.studies.starfox``: the per-estimator table (:func:`run_per_estimator`,
    :func:`estimator_table`), one process, resumable from its JSON lines."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m swarm.studies.starfox", description=main.__doc__)
    ap.add_argument("scenario", nargs="?", default="scenarios/starfox.yaml")
    ap.add_argument("--out", required=True, help="JSON lines file: one run a line (appended; runs already there are kept)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--estimators", default=",".join(ESTIMATORS))
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--set", action="append", default=[], dest="sets", help="dotted.key=value (repeatable)")
    ap.add_argument("--table-only", action="store_true", help="print the table of what OUT holds, run nothing")
    a = ap.parse_args(argv)
    ests = tuple(e for e in a.estimators.split(",") if e)
    cfgs = tuple(c for c in a.configs.split(",") if c)
    if a.table_only:
        res = [json.loads(line) for line in Path(a.out).read_text().splitlines() if line.strip()]
    else:
        res = run_per_estimator(a.scenario, a.runs, a.out, ests, cfgs, tuple(a.sets), a.seed, log=print)
    print(estimator_table(res, ests, cfgs))


if __name__ == "__main__":
    main()
