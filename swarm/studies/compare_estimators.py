"""``swarm compare-estimators``: estimators side by side on the same truth, sensors, links
and faults (paired seeds).

Every (condition, estimator) cell runs over the same seeds S, S+1, …, S+R−1: the same
truth, sensor noise and link draws, so differences within a condition are the estimator's
alone. Conditions (:data:`CONDITIONS`; ``--conditions`` picks some):

* ``ideal``: the scenario's own radio (the ideal one unless it enables ``links``);
* ``latency``: every batch and estimator message delayed 3 s (``links`` on, no loss);
* ``loss``: 3 s and 20 % Gilbert–Elliott loss in bursts of 3 messages on average;
* ``cap``: each transmitter capped at half of what the full estimator's complete graph
  needs (measured by the network study's probe, :func:`swarm.studies.links_study.probe`),
  its queue holding 10 s at that rate — the same cap for every estimator;
* ``restart``: the agent of satellite n // 2 killed at a third of the run and restarted at
  half (in-process, :func:`swarmcore.sim.simulate` ``outages``): warm rejoin from a peer
  for ``full``, a cold start from its own sensors for the others.

What each run reports (:func:`run_one`, from its ``summary.json``): own-state errors,
the run's centralized Cramér–Rao bound (:mod:`swarmcore.crlb`: every gyro, anchor and
relative measurement taken; the same for every estimator of a seed) and each estimator's
RMS over it (own and relative position, "RMS / bound"), errors of its estimate of each
tracked peer relative to itself (and, per (filter, peer) pair, their second-half squares,
so that the paired ratio of relative errors to the reference is taken over the pairs both
estimate: :func:`same_pairs_ratio`), NEES of both against what the estimator claims, bytes
each satellite put on its radio per second, median filter step CPU time. Writes
``results.jsonl`` (as runs finish), ``compare_estimators.json``,
``compare_estimators.md`` and ``estimators.png`` into OUT. Runs on the local pool or a Dask
cluster (:mod:`swarm.studies.executor`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from swarm.outputs import write_json
from swarm.studies.executor import ResultStore, open_executor, run_study
from swarmcore.scenario import Scenario

__all__ = ["CONDITIONS", "METRICS", "condition_overrides", "relative_pairs", "run_one", "run_compare_estimators", "same_pairs_ratio"]

#: The conditions of the study, in the order of its tables.
CONDITIONS = ("ideal", "latency", "loss", "cap", "restart")
#: (key, label, lower is better) of each run's figures.
METRICS = (
    ("self_pos", "own position RMS, 2nd half (m)", True),
    ("self_att", "own attitude RMS, 2nd half (rad)", True),
    ("bound_pos", "bound: own position, 2nd half (m)", None),
    ("self_pos_over_bound", "RMS / bound (own position, 2nd half)", True),
    ("rel_pos_over_bound", "RMS / bound (relative position, 2nd half)", True),
    ("rel_pos", "relative position RMS, 2nd half (m)", True),
    ("rel_att", "relative attitude RMS, 2nd half (rad)", True),
    ("nees_dof", "NEES / dof (own and tracked)", None),
    ("rel_nees_dof", "relative NEES / dof", None),
    ("bytes_per_s", "bytes sent per satellite per second", True),
    ("cpu_ms", "filter step CPU (ms, median)", True),
)
LATENCY_S = 3.0
LOSS_RATE = 0.2
MEAN_BURST = 3.0
CAP_FRACTION = 0.5
QUEUE_S = 10.0


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def condition_overrides(condition: str, data: dict, cap_Bps: float | None = None) -> dict:
    """The scenario fields a condition sets (merged over the scenario)."""
    links = {"enabled": True, "latency": {"fixed_s": LATENCY_S, "speed_of_light": False}, "loss": {"model": "none", "rate": 0.0},
             "rate_Bps": None}
    if condition in ("ideal", "restart"):
        return {}
    if condition == "latency":
        return {"links": links}
    if condition == "loss":
        return {"links": {**links, "loss": {"model": "gilbert_elliott", "rate": LOSS_RATE, "mean_burst": MEAN_BURST}}}
    if condition == "cap":
        if cap_Bps is None:
            raise ValueError("the cap condition needs the measured rate")
        return {"links": {**links, "latency": {"fixed_s": 0.0, "speed_of_light": False}, "rate_Bps": cap_Bps,
                          "queue_bytes": int(QUEUE_S * cap_Bps)}}
    raise ValueError(f"unknown condition {condition!r}; expected one of {CONDITIONS}")


def run_one(data: dict, kind: str, condition: str, over: dict, seed: int) -> dict:
    """One (condition, estimator, seed) run: plain values in, plain values out."""
    from swarm.simulation import measurement_model
    from swarmcore.sim import simulate
    from swarmrt.bus.convert import batch_wire_size
    from swarmrt.estimators import codec_for, estimator_factory
    from swarmrt.scenario_files import scenario_from_dict

    sc = scenario_from_dict(_merge({**data, "seed": seed, "estimator": {**data.get("estimator", {}), "kind": kind}}, over),
                            f"{condition} / {kind} / seed {seed}")
    outages: dict[int, tuple[int, int | None]] | None = {sc.n_sats // 2: (sc.steps // 3, sc.steps // 2)} if condition == "restart" else None
    res = simulate(sc, measurement_model(sc), wire_size=batch_wire_size("sim", codec_for(sc).to_msg),
                   estimator_factory=estimator_factory(sc), outages=outages)
    s = res.summary()
    rel = s.get("relative", {})
    return {
        "estimator": kind,
        "condition": condition,
        "seed": seed,
        "self_pos": s["rms_second_half"]["self"]["pos_m"],
        "self_att": s["rms_second_half"]["self"]["att_rad"],
        "rel_pos": rel.get("rms_second_half", {}).get("pos_m", float("nan")),
        "rel_att": rel.get("rms_second_half", {}).get("att_rad", float("nan")),
        "bound_pos": s.get("bound", {}).get("rms_second_half", {}).get("pos_m", float("nan")),
        "self_pos_over_bound": _num(s.get("rms_over_bound", {}).get("second_half", {}).get("self", {}).get("pos")),
        "rel_pos_over_bound": _num(s.get("rms_over_bound", {}).get("second_half", {}).get("relative", {}).get("pos")),
        "nees_dof": s["nees"]["mean"] / 6,
        "rel_nees_dof": rel.get("nees", {}).get("mean", float("nan")) / 6,
        "bytes_per_s": s.get("traffic", {}).get("bytes_per_sat_per_s_mean", float("nan")),
        "cpu_ms": s.get("cpu", {}).get("filter_step_cpu_ms_median", float("nan")),
        "late": s.get("late", {}),
        "links": (s.get("links") or {}).get("totals", {}),
        "rel_pairs": relative_pairs(res.rel_pos_err_m, res.rel_att_err_rad),
    }


def relative_pairs(rel_pos_err_m: np.ndarray, rel_att_err_rad: np.ndarray) -> dict:
    """Second-half sums of squared relative errors per (filter, peer) and their counts, (F, n)
    each (plain lists): what :func:`same_pairs_ratio` needs to compare two estimators on the
    pairs both estimate. An estimator that tracks only its graph neighbours is then held
    against the reference's errors of those pairs, not of every pair (far pairs are worse)."""
    K = rel_pos_err_m.shape[0]
    p, a = rel_pos_err_m[K // 2 :], rel_att_err_rad[K // 2 :]
    have = np.isfinite(p) & np.isfinite(a)
    return {"count": have.sum(axis=0).tolist(), "pos_m2": np.where(have, p**2, 0.0).sum(axis=0).tolist(),
            "att_rad2": np.where(have, a**2, 0.0).sum(axis=0).tolist()}


def same_pairs_ratio(run: dict, ref: dict, key: str) -> float:
    """The paired ratio of ``run``'s relative RMS (``key``: ``pos_m2`` or ``att_rad2``) to
    ``ref``'s over the (filter, peer) pairs both estimate in the second half: for each, the
    mean over its filters of each filter's RMS over those pairs (as the summary's relative
    RMS is over all of an estimator's pairs), NaN when they share none."""
    a, b = run.get("rel_pairs"), ref.get("rel_pairs")
    if not a or not b:
        return float("nan")
    ca, cb = np.asarray(a["count"], float), np.asarray(b["count"], float)
    if ca.shape != cb.shape:
        return float("nan")
    both = (ca > 0) & (cb > 0)
    rows = both.any(axis=1)
    if not rows.any():
        return float("nan")

    def rms(d: dict, c: np.ndarray) -> float:
        s = np.where(both, np.asarray(d[key], float), 0.0).sum(axis=1)[rows]
        return float(np.mean(np.sqrt(s / np.where(both, c, 0.0).sum(axis=1)[rows])))

    den = rms(b, cb)
    return rms(a, ca) / den if den > 0 else float("nan")


def _num(x) -> float:
    return float("nan") if x is None else float(x)


def _reference(estimators: Sequence[str]) -> str:
    """The estimator the others' paired ratios are taken to: the centralized reference
    (``central``) when it runs, else ``full``, else the first."""
    return next((e for e in ("central", "full") if e in estimators), estimators[0])


#: The relative errors, compared on the pairs both estimators estimate (:func:`same_pairs_ratio`).
_SAME_PAIRS = {"rel_pos": "pos_m2", "rel_att": "att_rad2"}


def _paired_ratio(run: dict, ref: dict, key: str) -> float:
    """One seed's ratio of ``key`` to the reference's (relative errors: on the same pairs)."""
    if key in _SAME_PAIRS:
        return same_pairs_ratio(run, ref, _SAME_PAIRS[key])
    return run[key] / ref[key] if ref[key] else float("nan")


def _nanmean(x: list[float]) -> float:
    a = np.asarray(x, float)
    return float(a[np.isfinite(a)].mean()) if np.isfinite(a).any() else float("nan")


def _stats(rows: list[dict], key: str) -> dict:
    a = np.array([r[key] for r in rows], dtype=float)
    a = a[np.isfinite(a)]
    if not a.size:
        return {"mean": float("nan"), "std": float("nan"), "n": 0}
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if a.size > 1 else 0.0, "n": int(a.size)}


def _fmt(v: float, spec: str = ".3g") -> str:
    return format(v, spec) if np.isfinite(v) else "—"


def _markdown(doc: dict) -> str:
    ests, conds = doc["estimators"], doc["conditions"]
    ref = _reference(ests)
    lines = [f"# Estimators compared: {doc['scenario']} (n = {doc['n_sats']}, {doc['duration_s']:g} s, "
             f"{len(doc['seeds'])} paired seeds)", "",
             f"Conditions: ideal radio; {LATENCY_S:g} s latency; {LATENCY_S:g} s + {LOSS_RATE:.0%} bursty loss (mean burst "
             f"{MEAN_BURST:g}); a data-rate cap of {CAP_FRACTION:g}× what the full estimator's batches need "
             f"({_fmt(doc.get('cap_Bps') or float('nan'), '.0f')} B/s per transmitter); satellite {doc['n_sats'] // 2}'s agent "
             "killed at a third of the run and restarted at half. Mean ± std over seeds; "
             f"in brackets the paired ratio to `{ref}` (mean of per-seed ratios; the relative ones over the (filter, peer) "
             f"pairs both estimate: an estimator that tracks only its graph neighbours is held against `{ref}`'s errors of "
             "those pairs).", ""]
    for cond in conds:
        lines += [f"## {cond}", "", "| estimator | " + " | ".join(label for _, label, _ in METRICS) + " |",
                  "|---|" + "---:|" * len(METRICS)]
        for e in ests:
            cells = []
            for key, _, _ in METRICS:
                st = doc["summary"][cond][e][key]
                ratio = doc["summary"][cond][e].get("vs_ref", {}).get(key)
                cell = f"{_fmt(st['mean'])} ± {_fmt(st['std'], '.2g')}"
                if ratio is not None and e != ref and np.isfinite(ratio):
                    cell += f" ({ratio:.2f}×)"
                cells.append(cell)
            lines.append(f"| {e} | " + " | ".join(cells) + " |")
        lines.append("")
    if doc.get("failed"):
        lines += ["## Failed runs", "", "| condition | estimator | seed | error |", "|---|---|---|---|"]
        for f in doc["failed"]:
            lines.append(f"| {f['condition']} | {f['estimator']} | {f['seed']} | {f['error'].splitlines()[0] if f['error'] else ''} |")
    return "\n".join(lines) + "\n"


def _plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ests, conds = doc["estimators"], doc["conditions"]
    keys = [m for m in METRICS if m[0] in ("self_pos", "rel_pos", "rel_nees_dof", "bytes_per_s", "cpu_ms", "rel_att")]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), dpi=110)
    width = 0.8 / max(1, len(ests))
    x = np.arange(len(conds))
    for ax, (key, label, _lower) in zip(axes.ravel(), keys):
        for i, e in enumerate(ests):
            m = [doc["summary"][c][e][key]["mean"] for c in conds]
            s = [doc["summary"][c][e][key]["std"] for c in conds]
            ax.bar(x + (i - (len(ests) - 1) / 2) * width, m, width, yerr=s, capsize=2, label=e)
        ax.set_xticks(x, conds, fontsize=8)
        ax.set_title(label, fontsize=9)
        if key in ("self_pos", "rel_pos", "rel_att", "bytes_per_s"):
            ax.set_yscale("log")
        if key == "rel_nees_dof":
            ax.axhline(1.0, color="k", lw=0.8, ls="--")
    axes.ravel()[0].legend(fontsize=8)
    fig.suptitle(f"{doc['scenario']}: estimators side by side ({len(doc['seeds'])} paired seeds)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_compare_estimators(sc: Scenario, runs: int, out: Path, *, estimators: Sequence[str] = ("full", "ci", "pairwise"),
                           conditions: Sequence[str] = CONDITIONS, seed: int | None = None, workers: int = 2,
                           cluster: str | None = None, resume: bool = False,
                           progress: Callable[[int, int], None] | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Run every (condition, estimator) over seeds ``seed + i`` (i < runs); write the files
    of the module docstring into ``out``; return the JSON document. A failed run is listed
    with its error and its seed left out of that condition's statistics (they are paired)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = sc.model_dump(mode="json")
    base = sc.seed if seed is None else seed
    seeds = [base + i for i in range(runs)]
    cap_Bps = None
    if "cap" in conditions:
        from swarm.studies.links_study import probe

        pr = probe(_merge(data, {"estimator": {"kind": "full"}, "selection": {"strategy": "none"}, "graph": {"kind": "complete"}}))
        cap_Bps = CAP_FRACTION * pr["need_Bps"]
    overs = {c: condition_overrides(c, data, cap_Bps) for c in conditions}
    jobs = {f"{c}/{e}@{s}": (data, e, c, overs[c], s) for c in conditions for e in estimators for s in seeds}
    store = ResultStore(out / "results.jsonl", resume=resume)
    try:
        with open_executor(workers, cluster) as ex:
            st = run_study(ex, run_one, jobs, store=store, progress=progress, log=log)
    finally:
        store.close()
    failed = [{"condition": c, "estimator": e, "seed": s, "error": st.errors[f"{c}/{e}@{s}"]}
              for c in conditions for e in estimators for s in seeds if f"{c}/{e}@{s}" in st.errors]
    summary: dict[str, dict] = {}
    ref = _reference(estimators)
    for c in conditions:
        ok = [s for s in seeds if all(f"{c}/{e}@{s}" in st.results for e in estimators)]
        summary[c] = {}
        for e in estimators:
            rows = [st.results[f"{c}/{e}@{s}"] for s in ok]
            sm: dict[str, Any] = {key: _stats(rows, key) for key, _, _ in METRICS}
            if e != ref and rows:
                refs = [st.results[f"{c}/{ref}@{s}"] for s in ok]
                sm["vs_ref"] = {key: _nanmean([_paired_ratio(r, q, key) for r, q in zip(rows, refs)]) for key, _, _ in METRICS}
            summary[c][e] = sm
    doc = {"scenario": sc.name, "n_sats": sc.n_sats, "duration_s": sc.duration_s, "estimators": list(estimators),
           "conditions": list(conditions), "seeds": seeds, "cap_Bps": cap_Bps, "overrides": overs, "summary": summary,
           "failed": failed, "backend": ex.description,
           "per_run": dict(sorted(st.results.items()))}
    write_json(out / "compare_estimators.json", doc)
    (out / "compare_estimators.md").write_text(_markdown(doc))
    _plot(doc, out / "estimators.png")
    return doc
