"""``swarm links-study``: how the cooperative filter degrades when the network is part of the
experiment (issue 11): latency, bursty loss, and a data-rate cap below what the complete
graph needs; ``filter.late: replay`` against ``drop``, the complete graph against greedy
selection under the cap.

The sweep is defined in one place, :class:`Sweep` (:data:`DEFAULT_SWEEP`, :data:`FULL_SWEEP`);
:func:`cells` turns it into the study's cells, each a set of scenario overrides:

* every cell: ``links.enabled``, ``links.latency.speed_of_light: false`` (so 0 s is the ideal
  network: in lockstep any positive delay, even range / c, delivers at the next step), its
  fixed latency, Gilbert–Elliott loss at its rate with ``mean_burst`` (none at 0 %), no rate
  cap outside the cap group, its ``filter.late``; the scenario's other link settings (jitter,
  range, line of sight, overrides, ``filter.history_s``) are kept;
* ``latency`` and ``loss`` groups — default: latency (0, 1, 2, 5, 10 s) without loss, and
  loss (0, 10, 30, 50 %) at 2 s, both for replay and drop; full (``--full``): every latency ×
  every loss × both modes;
* ``cap`` group: each transmitter capped at a fraction (0.5, 0.25) of what the complete graph
  needs, latency 0, no loss, replay; the complete graph (``selection.strategy: none``) against
  ``greedy`` with the largest budget whose swarm-average load fits the cap, and that greedy
  budget without a cap (what selection alone costs). The queue holds ``queue_s`` of the cap,
  so no batch waits longer than the filter's history.

What the complete graph needs is measured, not assumed: a short probe run (two steps of the
scenario, ideal links) gives each transmitter's batch size on the bus; transmitter i must
send n − 1 copies of its batch per step, ``need_i = (n − 1) · batch_i / dt``, and the study
caps at fractions of ``max_i need_i``. The probe also gives the size of an empty batch (h) and
of one measurement (s), from which the greedy budget under a cap C is
``m = floor(n · (C · dt / (n − 1) − h) / s)``: every observer broadcasts its batch (empty or
not) to n − 1 peers, so the swarm-average load per transmitter is (n − 1)(h + s · m / n) / dt.

Runs are paired: every cell runs over the same seeds S, S+1, …, S+R−1 (same truth, same
sensor noise, same link draws where the cells' links agree), so differences between cells
are due to the network alone. Each run is :func:`run_cell` — a top-level function of plain
values (a scenario dict and a seed) returning plain values — mapped over a local process
pool by :func:`_map`, the one place to route the study through another executor.

Writes into OUT: ``links_study.json`` (the sweep, the probe, every cell's overrides, every
run, the means and std over seeds, paired replay / drop and complete / greedy ratios),
``links_study.md`` (the tables) and ``latency.png``, ``loss.png``, ``cap.png``.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from swarm.outputs import write_json
from swarmcore.scenario import Scenario

__all__ = ["Sweep", "DEFAULT_SWEEP", "FULL_SWEEP", "Cell", "cells", "probe", "run_cell", "run_links_study", "METRICS"]


@dataclass(frozen=True)
class Sweep:
    """What the study varies (the one place the sweep is defined)."""

    latencies_s: tuple[float, ...] = (0.0, 1.0, 2.0, 5.0, 10.0)
    loss_rates: tuple[float, ...] = (0.0, 0.1, 0.3, 0.5)  # Gilbert–Elliott long-run loss
    mean_burst: float = 3.0  # messages
    loss_latency_s: float = 2.0  # the latency of the loss group (default sweep)
    late_modes: tuple[str, ...] = ("replay", "drop")
    cap_fractions: tuple[float, ...] = (0.5, 0.25)  # of what the complete graph needs
    queue_s: float = 10.0  # a capped transmitter's queue holds this many seconds at its rate
    grid: bool = False  # every latency × every loss rate (the full study)


#: 22 cells; with scenarios/links-study.yaml (n = 5, 60 s) and 5 seeds, a few minutes on 2 cores.
DEFAULT_SWEEP = Sweep()
#: The full study: latency × loss × late mode, and the caps (``--full``; run it with more seeds).
FULL_SWEEP = Sweep(grid=True)

#: (key, label) of the figures each run reports.
METRICS = (
    ("att_others", "others' attitude RMS (rad)"),
    ("pos_others", "others' position RMS (m)"),
    ("att_others_2h", "others' attitude RMS, second half (rad)"),
    ("pos_others_2h", "others' position RMS, second half (m)"),
    ("nees", "NEES (mean, all targets, dof 6)"),
    ("nees_others", "NEES (mean, other satellites, dof 6)"),
)


@dataclass(frozen=True)
class Cell:
    """One point of the sweep: its scenario overrides and what they mean."""

    group: str  # latency | loss | cap
    latency_s: float
    loss: float
    late: str
    arm: str = "complete"  # complete | greedy
    cap_fraction: float | None = None
    rate_Bps: float | None = None
    budget: int | None = None
    queue_bytes: int | None = None
    mean_burst: float = 3.0

    @property
    def key(self) -> str:
        cap = "none" if self.rate_Bps is None else f"{self.cap_fraction:g}x"
        arm = self.arm if self.budget is None else f"{self.arm}-m{self.budget}"
        return f"lat{self.latency_s:g}-loss{self.loss:g}-{self.late}-{arm}-cap{cap}"

    def overrides(self) -> dict:
        """The nested scenario fields this cell sets (merged over the scenario)."""
        links: dict = {
            "enabled": True,
            "latency": {"fixed_s": float(self.latency_s), "speed_of_light": False},
            "loss": ({"model": "gilbert_elliott", "rate": float(self.loss), "mean_burst": float(self.mean_burst)}
                     if self.loss > 0 else {"model": "none", "rate": 0.0}),
            "rate_Bps": self.rate_Bps,
        }
        if self.queue_bytes is not None:
            links["queue_bytes"] = int(self.queue_bytes)
        out: dict = {"links": links, "filter": {"late": self.late}}
        if self.arm == "greedy":
            if self.budget is None:
                raise ValueError(f"cell {self.key}: the greedy arm needs a budget")
            out["selection"] = {"strategy": "greedy", "budget": int(self.budget)}
            out["graph"] = {"kind": "complete"}
        elif self.group == "cap":
            out["selection"] = {"strategy": "none"}
            out["graph"] = {"kind": "complete"}
        return out


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def cell_scenario(data: dict, cell: Cell) -> dict:
    """The scenario dict of a cell (the base scenario with the cell's overrides)."""
    return _merge(data, cell.overrides())


# --------------------------------------------------------------------------- the probe


def probe(data: dict) -> dict:
    """What the complete graph needs: each transmitter's batch size on the bus, measured over
    two steps of the scenario with ideal links (see the module docstring)."""
    from swarm.simulation import SIM_RUN_ID, simulate_scenario
    from swarmcore.mekf import RelativeMeasurements
    from swarmrt.bus.convert import batch_wire_size

    over = Cell("probe", 0.0, 0.0, "replay").overrides()
    over["graph"] = {"kind": "complete"}
    over["selection"] = {"strategy": "none"}
    d = _merge(data, over)
    d["duration_s"] = d.get("dt_s", 1.0)  # two steps
    d["links"]["overrides"] = []  # every link alive: what the complete graph needs
    d["links"]["latency"]["jitter"] = {"distribution": "none", "scale_s": 0.0}  # every copy within its step
    d["links"]["max_range_m"] = None
    d["links"]["line_of_sight"] = False
    sc = Scenario.model_validate(d)
    res = simulate_scenario(sc)
    assert res.links is not None  # links.enabled
    c = res.links.counters
    bytes_, copies = c.bytes_delivered.sum(axis=1), c.delivered.sum(axis=1)
    n, dt, K = sc.n_sats, sc.dt_s, res.schedule.shape[0]
    batch = bytes_ / np.maximum(copies, 1)  # (n,) mean batch of each observer (bytes)
    meas = res.schedule.sum(axis=(0, 2)) / K  # (n,) measurements per batch
    header = batch_wire_size(SIM_RUN_ID)(0, 0, 0.0, RelativeMeasurements.empty(), np.zeros(0, dtype=int))
    per_meas = float((batch - header).sum() / max(meas.sum(), 1e-12))
    need = (n - 1) * batch / dt
    return {
        "n_sats": n,
        "dt_s": dt,
        "batch_bytes": batch.round(1).tolist(),
        "measurements_per_batch": meas.tolist(),
        "empty_batch_bytes": int(header),
        "bytes_per_measurement": per_meas,
        "need_Bps_per_transmitter": need.round(1).tolist(),
        "need_Bps": float(need.max()),
    }


def budget_for(cap_Bps: float, pr: dict) -> int:
    """The largest greedy budget whose swarm-average load per transmitter fits ``cap_Bps``."""
    n, dt = pr["n_sats"], pr["dt_s"]
    m = math.floor(n * (cap_Bps * dt / (n - 1) - pr["empty_batch_bytes"]) / pr["bytes_per_measurement"])
    return int(min(max(m, 1), n * (n - 1)))


def cells(sweep: Sweep, pr: dict) -> list[Cell]:
    """Every cell of the sweep, in table order, without duplicates (``pr``: the probe, for
    the cap group)."""
    out: list[Cell] = []
    b = sweep.mean_burst
    if sweep.grid:
        pts = [(L, p) for L in sweep.latencies_s for p in sweep.loss_rates]
        out += [Cell("grid", L, p, m, mean_burst=b) for L, p in pts for m in sweep.late_modes]
    else:
        out += [Cell("latency", L, 0.0, m, mean_burst=b) for L in sweep.latencies_s for m in sweep.late_modes]
        out += [Cell("loss", sweep.loss_latency_s, p, m, mean_burst=b) for p in sweep.loss_rates for m in sweep.late_modes]
    for f in sweep.cap_fractions:
        cap = round(f * pr["need_Bps"], 1)
        q = round(cap * sweep.queue_s)
        m = budget_for(cap, pr)
        out += [
            Cell("cap", 0.0, 0.0, "replay", "complete", f, cap, None, q, b),
            Cell("cap", 0.0, 0.0, "replay", "greedy", f, cap, m, q, b),
            Cell("cap", 0.0, 0.0, "replay", "greedy", f, None, m, None, b),
        ]
    seen, uniq = set(), []
    for c in out:
        same = (c.latency_s, c.loss, c.late, c.arm, c.rate_Bps, c.budget)  # the group is only where it is shown
        if same not in seen:
            seen.add(same)
            uniq.append(c)
    return uniq


# --------------------------------------------------------------------------- one run


def run_cell(data: dict, seed: int) -> dict:
    """One run of one cell: the scenario ``data`` (a cell's, as a dict) with ``seed``;
    plain values in, plain values out (a picklable task for any executor)."""
    from swarm.simulation import simulate_scenario

    sc = Scenario.model_validate({**data, "seed": seed})
    t0 = time.perf_counter()
    res = simulate_scenario(sc)
    wall = time.perf_counter() - t0
    s = res.summary()
    n = sc.n_sats
    others = ~np.eye(n, dtype=bool)
    with np.errstate(all="ignore"):
        nees_others = float(np.nanmean(res.nees[:, others]))
        nees_self = float(np.nanmean(res.nees[:, ~others]))
    lk = s.get("links", {})
    return {
        "seed": seed,
        "att_others": s["rms"]["others"]["att_rad"],
        "pos_others": s["rms"]["others"]["pos_m"],
        "att_others_2h": s["rms_second_half"]["others"]["att_rad"],
        "pos_others_2h": s["rms_second_half"]["others"]["pos_m"],
        "att_self": s["rms"]["self"]["att_rad"],
        "pos_self": s["rms"]["self"]["pos_m"],
        "nees": s["nees"]["mean"],
        "nees_others": nees_others,
        "nees_self": nees_self,
        "nis_ratio": s["nis"]["ratio"],
        "gate_rejected": s["gate"]["rejected"],
        "measurements_per_step": s["measurements_per_step_mean"],
        "links": lk.get("totals", {}),
        "latency_s": lk.get("latency_s"),
        "late": s.get("late", {}),
        "wall_s": wall,
    }


def _map(fn: Callable, jobs: dict[str, tuple], workers: int, progress: Callable[[int], None] | None = None) -> dict:
    """``{key: fn(*args)}`` over a local pool of spawned processes (this process for
    ``workers=1``). The study's only executor: the same contract as a study executor's
    ``run_study(executor, fn, jobs)`` results, so routing it elsewhere changes this function only."""
    out: dict = {}
    if workers <= 1:
        for key, args in jobs.items():
            out[key] = fn(*args)
            if progress:
                progress(len(out))
        return out
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futs = {pool.submit(fn, *args): key for key, args in jobs.items()}
        for fut in as_completed(futs):
            out[futs[fut]] = fut.result()
            if progress:
                progress(len(out))
    return out


# --------------------------------------------------------------------------- aggregation


def _stats(rows: list[dict]) -> dict:
    st = {}
    keys = [k for k, _ in METRICS] + ["att_self", "pos_self", "nees_self", "nis_ratio", "measurements_per_step", "wall_s"]
    for k in keys:
        a = np.array([r[k] for r in rows], dtype=float)
        st[k] = {"mean": float(np.nanmean(a)), "std": float(np.nanstd(a, ddof=1)) if a.size > 1 else 0.0}
    tot = lambda name, part: float(np.mean([r[part].get(name, 0) for r in rows]))  # noqa: E731
    sent = tot("sent", "links")
    st["links"] = {name: tot(name, "links") for name in
                   ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")}
    st["links"]["delivered_fraction"] = st["links"]["delivered"] / sent if sent else float("nan")
    lat = [r["latency_s"]["mean"] for r in rows if r.get("latency_s")]
    st["links"]["latency_mean_s"] = float(np.mean(lat)) if lat else float("nan")
    st["late"] = {name: tot(name, "late") for name in ("used", "dropped", "replayed_steps")}
    return st


def _paired(a: list[dict], b: list[dict], key: str) -> dict:
    x = np.array([r[key] for r in a], dtype=float)
    y = np.array([r[key] for r in b], dtype=float)
    return {"ratio_of_means": float(x.mean() / y.mean()), "wins": int(np.sum(x < y)), "runs": int(x.size)}


def _comparisons(doc: dict) -> dict:
    """Paired: replay / drop at every (latency, loss); greedy / complete at every cap."""
    by = {c["key"]: c for c in doc["cells"]}
    out: dict[str, list[dict]] = {"replay_vs_drop": [], "greedy_vs_complete": []}
    for c in doc["cells"]:
        p = c["params"]
        if p["late"] == "replay" and p["group"] != "cap":
            twin = Cell(**{**p, "late": "drop"}).key
            if twin in by:
                out["replay_vs_drop"].append({"latency_s": p["latency_s"], "loss": p["loss"], **{
                    k: _paired(c["runs"], by[twin]["runs"], k) for k, _ in METRICS}})
        if p["group"] == "cap" and p["arm"] == "greedy" and p["rate_Bps"] is not None:
            twin = Cell(**{**p, "arm": "complete", "budget": None}).key
            if twin in by:
                out["greedy_vs_complete"].append({"cap_fraction": p["cap_fraction"], "rate_Bps": p["rate_Bps"], "budget": p["budget"], **{
                    k: _paired(c["runs"], by[twin]["runs"], k) for k, _ in METRICS}})
    return out


# --------------------------------------------------------------------------- outputs


def _ms(st: dict, k: str) -> str:
    m, s = st[k]["mean"], st[k]["std"]
    return f"{m:.3g} ± {s:.2g}" if np.isfinite(m) else "—"


def _markdown(doc: dict) -> str:
    pr, sw = doc["probe"], doc["sweep"]
    L = [
        f"# Links study: {doc['scenario']} (n = {doc['n_sats']}, {doc['duration_s']:g} s, {len(doc['seeds'])} paired seeds "
        f"{doc['seeds'][0]}–{doc['seeds'][-1]})",
        "",
        f"Gilbert–Elliott loss with mean burst {sw['mean_burst']:g}; latency = the fixed part (range / c off). "
        f"The complete graph needs {pr['need_Bps']:.0f} B/s per transmitter (n − 1 = {doc['n_sats'] - 1} copies of a "
        f"{max(pr['batch_bytes']):.0f} B batch per {pr['dt_s']:g} s step; empty batch {pr['empty_batch_bytes']} B, "
        f"{pr['bytes_per_measurement']:.0f} B per measurement). Errors: time RMS of each filter's errors on the other "
        "satellites, mean over filters; mean ± std over seeds.",
        "",
        "| group | latency s | loss | late | arm | cap B/s | att others rad | pos others m | att 2nd half | pos 2nd half | "
        "NEES | NEES others | delivered | late used | late dropped | queue drops |",
        "|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in doc["cells"]:
        p, st = c["params"], c["stats"]
        cap = "—" if p["rate_Bps"] is None else f"{p['rate_Bps']:.0f} ({p['cap_fraction']:g}×)"
        arm = p["arm"] if p["budget"] is None else f"{p['arm']} m={p['budget']}"
        lk, lt = st["links"], st["late"]
        L.append(
            f"| {p['group']} | {p['latency_s']:g} | {p['loss']:.0%} | {p['late']} | {arm} | {cap} | "
            + " | ".join(_ms(st, k) for k, _ in METRICS)
            + f" | {lk['delivered_fraction']:.1%} | {lt['used']:.0f} | {lt['dropped']:.0f} | {lk['dropped_queue']:.0f} |"
        )
    L += ["", "delivered: copies delivered / copies sent (those still in flight at the end count as not delivered); "
          "late used / dropped: late measurements inserted by replay or dropped, all filters, mean per run; "
          "queue drops: copies that did not fit a transmitter's queue, mean per run.", ""]
    cmp = doc["comparisons"]
    if cmp["replay_vs_drop"]:
        L += _paired_table("## replay / drop (paired: ratio of means, runs where replay is lower)", "latency s | loss", "|---:|---:|",
                           cmp["replay_vs_drop"], lambda r: f"{r['latency_s']:g} | {r['loss']:.0%}")
    if cmp["greedy_vs_complete"]:
        L += _paired_table("## greedy / complete under the cap (paired)", "cap | budget", "|---|---:|",
                           cmp["greedy_vs_complete"], lambda r: f"{r['rate_Bps']:.0f} B/s ({r['cap_fraction']:g}×) | {r['budget']}")
    return "\n".join(L)


def _paired_table(title: str, heads: str, align: str, rows: list[dict], lead: Callable[[dict], str]) -> list[str]:
    """Markdown lines of a table of paired comparisons: each row's leading cells (``lead``,
    under ``heads``), then every metric's ratio of means and the runs won."""
    L = [title, "", f"| {heads} | " + " | ".join(k for k, _ in METRICS) + " |", align + "---:|" * len(METRICS)]
    for r in rows:
        L.append(f"| {lead(r)} | " + " | ".join(f"{r[k]['ratio_of_means']:.3f} ({r[k]['wins']}/{r[k]['runs']})" for k, _ in METRICS) + " |")
    return [*L, ""]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


_PLOTTED = (("att_others", "others' attitude RMS [rad]"), ("pos_others", "others' position RMS [m]"), ("nees_others", "NEES, others (dof 6)"))


def _sweep_plot(doc: dict, x: str, fixed: dict, series: str | None, path: Path, xlabel: str) -> Path | None:
    """Metrics against ``x`` (latency_s or loss) for replay and drop (and, in the full grid,
    one line per value of ``series``), over the non-cap cells matching ``fixed``."""
    rows = [c for c in doc["cells"] if c["params"]["group"] != "cap"
            and all(c["params"][k] == v for k, v in fixed.items())]
    if not rows:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    groups: dict[tuple, list] = {}
    for c in rows:
        p = c["params"]
        groups.setdefault((p["late"], p[series] if series else None), []).append(c)
    svals = sorted({k[1] for k in groups if k[1] is not None})
    cmap = plt.get_cmap("viridis")
    for (late, sv), cs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0)):
        cs = sorted(cs, key=lambda c: c["params"][x])
        xs = [c["params"][x] * (100 if x == "loss" else 1) for c in cs]
        color = (cmap(svals.index(sv) / max(1, len(svals) - 1)) if sv is not None else ("tab:blue" if late == "replay" else "tab:red"))
        label = late + ("" if sv is None else f", loss {sv * 100:g} %" if series == "loss" else f", latency {sv:g} s")
        for ax, (k, ylabel) in zip(axes, _PLOTTED):
            m = [c["stats"][k]["mean"] for c in cs]
            s = [c["stats"][k]["std"] for c in cs]
            ax.errorbar(xs, m, yerr=s, marker="o" if late == "replay" else "s", ls="-" if late == "replay" else "--",
                        color=color, capsize=3, lw=1, ms=4, label=label)
            ax.set_ylabel(ylabel)
    for ax, (k, _) in zip(axes, _PLOTTED):
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
        if k != "nees_others":
            ax.set_yscale("log")
        else:
            ax.axhline(6, color="k", lw=0.6)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{doc['scenario']}: n = {doc['n_sats']}, {len(doc['seeds'])} seeds (mean ± std)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _cap_plot(doc: dict, path: Path) -> Path | None:
    rows = [c for c in doc["cells"] if c["params"]["group"] == "cap"]
    if not rows:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    labels = []
    for c in rows:
        p = c["params"]
        cap = "no cap" if p["rate_Bps"] is None else f"{p['cap_fraction']:g}× cap"
        arm = p["arm"] if p["budget"] is None else f"greedy m={p['budget']}"
        labels.append(f"{arm}\n{cap}")
    colors = ["tab:blue" if c["params"]["arm"] == "complete" else ("tab:green" if c["params"]["rate_Bps"] else "tab:olive") for c in rows]
    ref = next((c for c in doc["cells"] if c["params"]["group"] != "cap" and c["params"]["latency_s"] == 0 and c["params"]["loss"] == 0
                and c["params"]["late"] == "replay"), None)
    for ax, (k, ylabel) in zip(axes, _PLOTTED):
        ax.bar(range(len(rows)), [c["stats"][k]["mean"] for c in rows], yerr=[c["stats"][k]["std"] for c in rows], color=colors, capsize=3)
        if ref is not None:
            ax.axhline(ref["stats"][k]["mean"], color="k", ls="--", lw=0.8, label="complete, no cap")
        ax.set_xticks(range(len(rows)))
        ax.set_xticklabels(labels, fontsize=7, rotation=30, ha="right")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, axis="y")
        if k != "nees_others":
            ax.set_yscale("log")
    axes[0].legend(fontsize=7)
    caps = ", ".join(f"{c['params']['cap_fraction']:g}× = {c['params']['rate_Bps']:.0f} B/s" for c in rows
                     if c["params"]["arm"] == "complete")
    fig.suptitle(f"data-rate cap: the complete graph needs {doc['probe']['need_Bps']:.0f} B/s per transmitter; {caps} "
                 f"(latency 0, replay; {len(doc['seeds'])} seeds, mean ± std)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- the study


def run_links_study(
    sc: Scenario,
    out: Path,
    *,
    runs: int = 5,
    sweep: Sweep = DEFAULT_SWEEP,
    seed: int | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
    mapper: Callable | None = None,
) -> dict:
    """Probe, run every cell over seeds ``seed + i`` (i < runs), write the table, the JSON
    and the plots into ``out``; return the JSON document. ``mapper(fn, jobs, progress)``:
    where the runs go (a :class:`swarm.studies.executor.StudyMapper`: the local pool or a Dask
    cluster, results streamed and resumable); default: a local pool of ``workers``. Cells
    with a failed run are left out of the table and listed under ``failed``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    base = sc.seed if seed is None else seed
    seeds = [base + i for i in range(runs)]
    data = sc.model_dump(mode="json")
    pr = probe(data)  # what the complete graph needs (two steps: cheap; reported even without caps)
    cs = cells(sweep, pr)
    jobs = {f"{c.key}/{s}": (cell_scenario(data, c), s) for c in cs for s in seeds}
    total = len(jobs)
    if progress:
        progress(0, total)
    t0 = time.perf_counter()
    if mapper is None:
        res = _map(run_cell, jobs, workers, (lambda k: progress(k, total)) if progress else None)
    else:
        res = mapper(run_cell, jobs, progress)
    wall = time.perf_counter() - t0
    doc: dict[str, Any] = {
        "scenario": sc.name,
        "n_sats": sc.n_sats,
        "duration_s": sc.duration_s,
        "dt_s": sc.dt_s,
        "seeds": seeds,
        "sweep": asdict(sweep),
        "probe": pr,
        "wall_s": wall,
        "workers": workers,
        "cells": [],
        "failed": sorted(k for k in jobs if k not in res),
    }
    for c in cs:
        if any(f"{c.key}/{s}" not in res for s in seeds):
            continue  # paired statistics: a cell is whole or left out
        rows = [res[f"{c.key}/{s}"] for s in seeds]
        doc["cells"].append({"key": c.key, "params": asdict(c), "overrides": c.overrides(), "stats": _stats(rows), "runs": rows})
    doc["comparisons"] = _comparisons(doc)
    write_json(out / "links_study.json", doc)
    (out / "links_study.md").write_text(_markdown(doc))
    if sweep.grid:
        _sweep_plot(doc, "latency_s", {}, "loss", out / "latency.png", "latency [s]")
        _sweep_plot(doc, "loss", {}, "latency_s", out / "loss.png", "Gilbert–Elliott loss [%]")
    else:
        _sweep_plot(doc, "latency_s", {"group": "latency"}, None, out / "latency.png", "latency [s]")
        _sweep_plot(doc, "loss", {"latency_s": sweep.loss_latency_s}, None, out / "loss.png",
                    f"Gilbert–Elliott loss [%] (mean burst {sweep.mean_burst:g}) at {sweep.loss_latency_s:g} s latency")
    _cap_plot(doc, out / "cap.png")
    return doc
