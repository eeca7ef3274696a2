"""``swarm report``: PNG figures and one self-contained HTML page for a run.

Accepts a ``swarm sim`` folder (npz arrays), a ``swarm run`` folder or a bare MCAP file
(read back from the recording), or a Monte Carlo / comparison / links-study folder
(``mc.json``, ``compare.json``, ``links_study.json``). Figures follow the dissertation where it has them (Figure 4.5: each
filter's own and others' errors against ±3σ); fault events are marked on every time axis.

A run with ``links:`` also gets a *Links* section: a table per directed link (sent,
delivered, delivered late, lost, dropped at the queue, unreachable, bytes, mean and p95
latency), the latency histogram of delivered batches, what happened on the links per step
(the differences of the cumulative counters), each transmitter's queue over time and what
the filters did with late measurements (used, dropped, steps replayed). A recording (the
world's ``LinkStats`` of every step) and a ``swarm sim`` folder carry the same.

Every run is read into its :class:`~swarmcore.result.RunResult` (one schema for the
simulator's folder and the recording), and the figures are drawn from that.
"""

from __future__ import annotations

import base64
import html
import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.stats import chi2

from swarm.chaos.campaign import FIRED_COLUMNS, fired_rows
from swarm.outputs import NO_DATA, no_data_reason, number
from swarmcore.result import LINK_TOTALS, RunResult

__all__ = ["RunData", "LinkData", "load_run", "make_report"]

#: The columns of the per-step link totals (:attr:`swarmcore.result.LinkArrays.totals`).
SERIES = LINK_TOTALS


@dataclass
class LinkData:
    """What the radio did in a run (``links.enabled``)."""

    per_link: dict  # LinkCounters fields → (n, n) cumulative over the run, row = sender
    k: np.ndarray  # (S,) steps of the series
    totals: np.ndarray  # (S, 6) cumulative totals after each step, columns SERIES
    latencies: np.ndarray  # (m, 4): sender, receiver, sent step, latency (s)
    queue_bytes: np.ndarray  # (S, n) bytes each transmitter still had to send
    late_used: np.ndarray  # (K, F) late measurements inserted (replay)
    late_dropped: np.ndarray  # (K, F) late measurements dropped
    replayed: np.ndarray  # (K, F) filter steps re-run


@dataclass
class RunData:
    name: str
    t: np.ndarray  # (K,)
    n: int
    err: np.ndarray  # (K, F, n, 6) [a (rad), Δr (m)]
    sigma: np.ndarray  # (K, F, n, 6) 1σ of the same
    nees: np.ndarray  # (K, F, n)
    rejected: np.ndarray  # (K, F)
    schedule: np.ndarray  # (K, n, n)
    alive: np.ndarray  # (K, F)
    faults: list = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    links: LinkData | None = None
    r_true_H: np.ndarray | None = None  # (K, n, 3) true positions in H (m): ranges


def _links(r: RunResult) -> LinkData | None:
    if r.links is None:
        return None
    L = r.links
    return LinkData(per_link={k: np.asarray(v) for k, v in L.counters.as_dict().items()}, k=np.arange(len(L.totals)),
                    totals=L.totals, latencies=np.array(L.latencies, dtype=float).reshape(-1, 4), queue_bytes=L.queue_bytes,
                    late_used=r.late_used, late_dropped=r.late_dropped, replayed=r.replayed_steps)


def load_run(path: str | Path) -> RunData:
    """The figures' data of a run folder (``swarm sim``'s arrays or ``swarm run``'s
    recording) or of a bare MCAP file: its :class:`~swarmcore.result.RunResult`, whatever ran it."""
    from swarm.outputs import read_run
    from swarm.record.recording import load_recording
    from swarmrt.scenario_files import load_scenario

    p = Path(path)
    d = p.parent if p.is_file() else p
    if not (p.is_file() and p.suffix == ".mcap") and not (p / "estimates.npz").exists() and not (p / "run.mcap").exists():
        raise FileNotFoundError(f"{p}: neither a run folder (estimates.npz or run.mcap) nor an MCAP file")
    sc = load_scenario(d / "scenario.yaml") if (d / "scenario.yaml").exists() else None
    summary = json.loads((d / "summary.json").read_text()) if (d / "summary.json").exists() else {}
    if p.is_dir() and (p / "estimates.npz").exists():
        r, name = read_run(p, sc), p.name
    else:
        mcap = p if p.is_file() else p / "run.mcap"
        r = load_recording(mcap, sc.n_sats if sc else None, sc.steps if sc else None, scenario=sc)
        name = sc.name if sc else mcap.stem
    a, dr = r.pose_errors()
    return RunData(
        name=summary.get("scenario", name),
        t=np.where(np.isfinite(r.t_s), r.t_s, np.arange(r.K, dtype=float)),
        n=r.n,
        err=np.concatenate([a, dr], axis=-1),
        sigma=np.sqrt(r.est.pose_var),
        nees=r.nees,
        rejected=r.gate_rejected,
        schedule=r.taken,
        alive=r.alive,
        faults=summary.get("faults", r.bus.faults if r.bus is not None else []),
        summary=summary,
        links=_links(r),
        r_true_H=r.truth.r_H_m,
    )


# --------------------------------------------------------------------------- figures


def _faults(ax, data: RunData) -> None:
    for f in data.faults:
        if f.get("phase") not in ("done", None):
            continue
        t = f.get("t_s", f.get("k", 0))
        ax.axvline(t, color="crimson", lw=0.8, ls="--", alpha=0.7)
        label = f"{f['action']}" + (f" {f['target']}" if f.get("target") is not None else "")
        ax.annotate(label, (t, 1.0), xycoords=("data", "axes fraction"), rotation=90, va="top", ha="right", fontsize=7, color="crimson")


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def fig_filter(data: RunData, f: int, out: Path) -> Path:
    t = data.t
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True)
    titles = [
        (f"filter {f}: own attitude error [rad]", slice(0, 3), [f]),
        (f"filter {f}: own position error [m]", slice(3, 6), [f]),
        (f"filter {f}: other satellites' attitude errors [rad]", slice(0, 3), [j for j in range(data.n) if j != f]),
        (f"filter {f}: other satellites' position errors [m]", slice(3, 6), [j for j in range(data.n) if j != f]),
    ]
    for ax, (title, sl, targets) in zip(axes.ravel(), titles):
        for j in targets:
            e = data.err[:, f, j, sl]
            s = data.sigma[:, f, j, sl]
            ax.plot(t, e, lw=0.6, alpha=0.8)
            ax.plot(t, 3 * s, color="r", lw=0.6, alpha=0.6)
            ax.plot(t, -3 * s, color="r", lw=0.6, alpha=0.6)
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        _faults(ax, data)
        finite = np.abs(data.err[:, f][:, targets][..., sl])
        finite = finite[np.isfinite(finite)]
        if finite.size:
            lim = np.percentile(finite, 99) * 1.5
            ax.set_ylim(-lim, lim)
    for ax in axes[1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{data.name}: errors and ±3σ bounds (red), filter {f}", fontsize=10)
    return _save(fig, out / f"errors_filter_{f}.png")


#: Above this range (m) between two satellites a run is "long range": the report adds the
#: range and percentage-of-range figure (angles-only navigation is judged by it).
LONG_RANGE_M = 1000.0


def fig_range(data: RunData, out: Path) -> Path | None:
    """Long-range runs: the true range from each filter's satellite to the others, and that
    filter's relative position error |Δr_j − Δr_f| as a percentage of it (the figure
    angles-only navigation reports, e.g. StarFOX). None at close range."""
    r = data.r_true_H
    if r is None:
        return None
    F = data.err.shape[1]
    rng = np.linalg.norm(r[:, None, :, :] - r[:, :, None, :], axis=-1)  # (K, n, n): |r_j − r_i|
    if not np.nanmax(rng) > LONG_RANGE_M:
        return None
    fig, (ax_r, ax_p) = plt.subplots(2, 1, figsize=(11, 7), sharex=True)
    colours = plt.get_cmap("tab10")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # steps a dead filter did not run
        for f in range(F):
            rel = data.err[:, f, :, 3:6] - data.err[:, f, f : f + 1, 3:6]  # (K, n, 3): its error of j relative to itself
            for j in range(data.n):
                if j == f:
                    continue
                c = colours((f * data.n + j) % 10)
                if f == 0:
                    ax_r.plot(data.t, rng[:, 0, j] / 1e3, lw=0.8, color=c, label=f"0 → {j}")
                pct = 100 * np.linalg.norm(rel[:, j], axis=-1) / rng[:, f, j]
                ax_p.plot(data.t, pct, lw=0.6, color=c, alpha=0.8, label=f"filter {f}: {j}" if F * data.n <= 24 else None)
    ax_r.set_ylabel("true range from satellite 0 [km]")
    ax_r.legend(fontsize=7, ncol=4)
    ax_r.grid(alpha=0.3)
    ax_p.set_yscale("log")
    ax_p.set_ylabel("relative position error [% of range]")
    ax_p.set_xlabel("time [s]")
    ax_p.grid(alpha=0.3, which="both")
    if F * data.n <= 24:
        ax_p.legend(fontsize=6, ncol=4)
    _faults(ax_p, data)
    fig.suptitle(f"{data.name}: ranges, and each filter's error of the others relative to itself as a percentage of range", fontsize=10)
    return _save(fig, out / "range.png")


def fig_nees(data: RunData, out: Path) -> Path:
    fig, ax = plt.subplots(figsize=(11, 4))
    n = data.n
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: steps a dead filter did not run
        avg = np.nanmean(data.nees, axis=2)  # (K, F) average over the n targets
    for f in range(avg.shape[1]):
        ax.plot(data.t, avg[:, f], lw=0.7, label=f"filter {f}")
    lo, hi = chi2.ppf(np.array([0.025, 0.975]), 6 * n) / n
    ax.axhspan(lo, hi, color="green", alpha=0.15, label=f"95 % χ² band ({6 * n} dof / {n})")
    ax.axhline(6, color="k", lw=0.6)
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("NEES (6-dof pose, mean over targets)")
    ax.grid(alpha=0.3)
    _faults(ax, data)
    ax.legend(fontsize=7, ncol=min(6, avg.shape[1] + 1))
    return _save(fig, out / "nees.png")


def fig_gate(data: RunData, out: Path) -> Path:
    fig, ax = plt.subplots(figsize=(11, 3))
    rej = np.nan_to_num(data.rejected.astype(float))
    bottom = np.zeros(len(data.t))
    for f in range(rej.shape[1]):
        ax.bar(data.t, rej[:, f], bottom=bottom, width=(data.t[1] - data.t[0]) if len(data.t) > 1 else 1.0, label=f"filter {f}")
        bottom += rej[:, f]
    ax.set_xlabel("time [s]")
    ax.set_ylabel("gate rejections")
    ax.set_title(f"validation gate: {int(rej.sum())} rejections in all", fontsize=9)
    ax.grid(alpha=0.3)
    _faults(ax, data)
    return _save(fig, out / "gate.png")


def fig_schedule(data: RunData, out: Path) -> Path:
    counts = data.schedule.sum(axis=0)
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    im = ax.imshow(counts, cmap="viridis")
    ax.set_xlabel("target")
    ax.set_ylabel("observer")
    ax.set_title("measurements taken (count over the run)", fontsize=9)
    if data.n <= 16:
        ax.set_xticks(range(data.n))
        ax.set_yticks(range(data.n))
        for i in range(data.n):
            for j in range(data.n):
                ax.text(j, i, str(int(counts[i, j])), ha="center", va="center", fontsize=7, color="w")
    fig.colorbar(im, ax=ax)
    return _save(fig, out / "schedule.png")


def _mc_figures(d: Path, out: Path) -> tuple[list[Path], str]:
    """Bars and a table for a Monte Carlo folder (mc.json) or several side by side."""
    mc = json.loads((d / "mc.json").read_text())
    st = mc["stats"]
    keys = ["rms.self.att_rad", "rms.self.pos_m", "rms.others.att_rad", "rms.others.pos_m", "rms_second_half.others.att_rad", "rms_second_half.others.pos_m"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.5))
    for ax, unit in zip(axes, ("att_rad", "pos_m")):
        ks = [k for k in keys if k.endswith(unit)]
        ax.bar(range(len(ks)), [st[k]["mean"] for k in ks], yerr=[st[k]["std"] for k in ks], capsize=4)
        ax.set_xticks(range(len(ks)))
        ax.set_xticklabels([k.replace(".", "\n", 1) for k in ks], fontsize=7)
        ax.set_yscale("log")
        ax.set_title(f"{mc['scenario']}: {mc['runs']} runs, mean ± std ({unit})", fontsize=9)
    p = _save(fig, out / "mc_bars.png")
    rows = "".join(
        f"<tr><td>{r['seed']}</td>"
        + "".join(f"<td>{number(r[b]['others'][u], '.4g')}</td>" for b in ("rms", "rms_second_half") for u in ("att_rad", "pos_m"))
        + f"<td>{number(r['nees_mean'], '.2f')}</td></tr>"
        for r in mc["per_run"]
    )
    table = (
        "<table><tr><th>seed</th><th>others att [rad]</th><th>others pos [m]</th><th>2nd half att</th><th>2nd half pos</th><th>NEES</th></tr>"
        + rows
        + "</table><table><tr><th>field</th><th>mean</th><th>std</th><th>min</th><th>max</th></tr>"
        + "".join(f"<tr><td>{k}</td><td>{number(v['mean'], '.4g')}</td><td>{number(v['std'], '.2g')}</td><td>{number(v['min'], '.4g')}</td>"
                  f"<td>{number(v['max'], '.4g')}</td></tr>" for k, v in st.items())
        + "</table>"
    )
    return [p], table


# --------------------------------------------------------------------------- links


def _link_t(data: RunData, k: np.ndarray) -> np.ndarray:
    """Times of steps ``k`` (the run's time axis)."""
    k = np.clip(np.asarray(k, dtype=int), 0, len(data.t) - 1)
    return data.t[k]


def fig_link_latency(data: RunData, out: Path) -> Path | None:
    L = data.links
    if L is None or not len(L.latencies):
        return None
    lat = L.latencies[:, 3]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.hist(lat, bins=min(60, max(10, int(np.sqrt(lat.size)))), color="tab:blue", alpha=0.8)
    for q, ls in ((50, "-"), (95, "--")):
        v = np.percentile(lat, q)
        ax.axvline(v, color="k", ls=ls, lw=0.8, label=f"p{q} {v:.3g} s")
    ax.set_xlabel("latency of a delivered batch [s] (sent → arrived)")
    ax.set_ylabel("batches")
    ax.set_title(f"{lat.size} deliveries, mean {lat.mean():.3g} s, max {lat.max():.3g} s", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return _save(fig, out / "links_latency.png")


def fig_link_events(data: RunData, out: Path) -> Path | None:
    """Per step: copies delivered on time and late, lost, dropped at the queue, unreachable
    (differences of the cumulative totals)."""
    L = data.links
    if L is None or len(L.k) < 2:
        return None
    d = np.diff(np.vstack([np.zeros((1, len(SERIES)), dtype=L.totals.dtype), L.totals]), axis=0)
    col = {name: d[:, i] for i, name in enumerate(SERIES)}
    t = _link_t(data, L.k)
    fig, ax = plt.subplots(figsize=(11, 3.8))
    for name, label, c in (("on_time", "delivered on time", "tab:green"), ("delivered_late", "delivered late", "orange"),
                           ("lost", "lost", "tab:red"), ("dropped_queue", "dropped at the queue", "tab:purple"),
                           ("unreachable", "unreachable", "grey")):
        y = col["delivered"] - col["delivered_late"] if name == "on_time" else col[name]
        ax.step(t, y, where="mid", lw=0.9, color=c, label=f"{label} ({int(y.sum())})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("copies per step")
    ax.set_title(f"links per step: {int(L.totals[-1, 0])} copies sent in all", fontsize=9)
    ax.grid(alpha=0.3)
    _faults(ax, data)
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.18))
    return _save(fig, out / "links_events.png")


def fig_link_queue(data: RunData, out: Path) -> Path | None:
    L = data.links
    if L is None or not L.queue_bytes.size:
        return None
    t = _link_t(data, L.k)
    fig, ax = plt.subplots(figsize=(11, 3.5))
    for i in range(L.queue_bytes.shape[1]):
        ax.step(t, L.queue_bytes[:, i], where="post", lw=0.8, label=f"sat {i}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("bytes queued at the step's end")
    ax.set_title("each transmitter's queue (still to send, the copy on the air included)", fontsize=9)
    ax.grid(alpha=0.3)
    _faults(ax, data)
    ax.legend(fontsize=7, ncol=min(10, L.queue_bytes.shape[1]))
    return _save(fig, out / "links_queue.png")


def fig_late(data: RunData, out: Path) -> Path | None:
    L = data.links
    if L is None:
        return None
    fig, ax = plt.subplots(figsize=(11, 3.2))
    for arr, label, c in ((L.late_used, "late measurements used (replay)", "tab:green"),
                          (L.late_dropped, "late measurements dropped", "tab:red"),
                          (L.replayed, "filter steps replayed", "tab:blue")):
        y = np.nansum(arr, axis=1)
        ax.step(data.t[: len(y)], y, where="mid", lw=0.9, color=c, label=f"{label} ({int(y.sum())})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("per step, all filters")
    ax.grid(alpha=0.3)
    _faults(ax, data)
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    return _save(fig, out / "links_late.png")


def _links_table(L: LinkData) -> str:
    """Per directed link: the counters and the latency of its deliveries."""
    pl = L.per_link
    n = pl["sent"].shape[0]
    cols = ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")
    heads = ("link", "sent", "delivered", "delivered late", "lost", "dropped at queue", "unreachable", "bytes", "latency mean [s]",
             "latency p95 [s]")
    rows = []

    def lat_cells(sel) -> str:
        v = L.latencies[sel, 3]
        return (f"<td>{v.mean():.4g}</td><td>{np.percentile(v, 95):.4g}</td>" if v.size else "<td></td><td></td>")

    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            sel = (L.latencies[:, 0] == i) & (L.latencies[:, 1] == j)
            rows.append(f"<tr><td>{i} → {j}</td>" + "".join(f"<td>{int(pl[c][i, j])}</td>" for c in cols) + lat_cells(sel) + "</tr>")
    allsel = np.ones(len(L.latencies), dtype=bool)
    rows.append("<tr><th>all</th>" + "".join(f"<th>{int(pl[c].sum())}</th>" for c in cols)
                + lat_cells(allsel).replace("td>", "th>") + "</tr>")
    late = (f"<p>Late measurements: {int(np.nansum(L.late_used))} used (inserted at their own step), "
            f"{int(np.nansum(L.late_dropped))} dropped, {int(np.nansum(L.replayed))} filter steps replayed (all filters).</p>")
    return "<table><tr>" + "".join(f"<th>{h}</th>" for h in heads) + "</tr>" + "".join(rows) + "</table>" + late


def links_section(data: RunData, out: Path) -> str:
    """The report's Links section ('' when the run had no links)."""
    if data.links is None:
        return ""
    parts = ["<h2>Links</h2>", _links_table(data.links)]
    for fig, caption in ((fig_link_latency, "latency of every delivered batch"),
                         (fig_link_events, "what happened on the links, per step"),
                         (fig_link_queue, "bytes queued at each transmitter"),
                         (fig_late, "late measurements per step: used, dropped, steps replayed")):
        p = fig(data, out)
        if p is not None:
            parts.append(_img(p, caption))
    return "\n".join(parts)


# --------------------------------------------------------------------------- HTML

_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1300px}} img{{max-width:100%;border:1px solid #ddd;margin:.5em 0}}
table{{border-collapse:collapse;margin:1em 0;font-size:90%}} td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}
th{{background:#f0f0f0}} h2{{border-bottom:1px solid #ccc}}</style>
<script>
window.__errors = [];
window.addEventListener("error", function (e) {{ window.__errors.push(String(e.message || e)); }});
window.addEventListener("load", function () {{
  var imgs = Array.from(document.images);
  document.body.dataset.images = imgs.length;
  document.body.dataset.imagesLoaded = imgs.filter(function (i) {{ return i.complete && i.naturalWidth > 0; }}).length;
  document.body.dataset.errors = window.__errors.length;
}});
</script></head>
<body><h1>{title}</h1>{body}</body></html>
"""


def _img(p: Path, caption: str) -> str:
    b64 = base64.b64encode(p.read_bytes()).decode("ascii")
    return f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{b64}"><figcaption>{html.escape(caption)}</figcaption></figure>'


def _summary_table(s: dict) -> str:
    if not s or "rms" not in s:
        return ""
    rows = []
    cells = []
    for key, label in (("rms", "full run"), ("rms_second_half", "second half")):
        r = s[key]
        row = [number(r[w][u]) for w in ("self", "others") for u in ("att_rad", "pos_m")]
        cells += row
        rows.append(f"<tr><td>{label}</td>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>")
    extra = f"<p>NEES mean {number(s['nees']['mean'], '.2f')} (dof 6) · gate accepted {s['gate']['accepted']}, rejected {s['gate']['rejected']}</p>"
    if NO_DATA in cells:
        extra += f"<p><b>{NO_DATA}</b>: {html.escape(no_data_reason(s))}</p>"
    if s.get("interrupted"):
        extra += f"<p><b>This run is incomplete</b>: {html.escape(str(s['interrupted'].get('reason')))}, last step {s['interrupted'].get('last_step')}.</p>"
    for g in s.get("bus_gaps", []):
        extra += (f"<p>Bus gap (no router reachable, seen by the {html.escape(g['observer'])}): "
                  + (f"{g['duration_s']:.2f} s" if g["duration_s"] is not None else "never came back")
                  + f" after step {g['last_step_before']}.</p>")
    return "<table><tr><th>time RMS</th><th>self att [rad]</th><th>self pos [m]</th><th>others att [rad]</th><th>others pos [m]</th></tr>" + "".join(rows) + "</table>" + extra


def _estimator_table(s: dict) -> str:
    """The estimator's shared figures: its estimate of each tracked peer relative to itself
    (RMS and NEES against what it claims), its radio traffic and the CPU of its step."""
    if not s or "relative" not in s:
        return ""
    rel, tr, cpu = s["relative"], s.get("traffic") or {}, s.get("cpu") or {}
    rows = [("estimator", html.escape(str(s.get("estimator", "full")))),
            ("relative attitude RMS, full run / second half [rad]",
             f"{number(rel['rms']['att_rad'])} / {number(rel['rms_second_half']['att_rad'])}"),
            ("relative position RMS, full run / second half [m]",
             f"{number(rel['rms']['pos_m'])} / {number(rel['rms_second_half']['pos_m'])}"),
            ("relative NEES mean (dof 6)", number(rel["nees"]["mean"], ".2f")),
            ("bytes sent per satellite per second (mean / max)",
             f"{number(tr.get('bytes_per_sat_per_s_mean'), '.0f')} / {number(tr.get('bytes_per_sat_per_s_max'), '.0f')}"),
            ("filter step CPU (median / p95) [ms]",
             f"{number(cpu.get('filter_step_cpu_ms_median'), '.3f')} / {number(cpu.get('filter_step_cpu_ms_p95'), '.3f')}")]
    return "<table>" + "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _faults_table(faults: list) -> str:
    if not faults:
        return "<p>No faults.</p>"
    cols = ("k", "t_s", "action", "target", "camera", "state", "phase", "sender", "detail")
    return "<table><tr>" + "".join(f"<th>{c}</th>" for c in cols) + "</tr>" + "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(f.get(c, '')))}</td>" for c in cols) + "</tr>" for f in faults
    ) + "</table>"


def _chaos_section(c: dict) -> str:
    """A chaos campaign's ``chaos.json`` (``swarm chaos``) as the terminal shows it: faults
    fired and recovery per kind, then every invariant with its evidence."""
    fired = "<table><tr>" + "".join(f"<th>{h}</th>" for h in FIRED_COLUMNS) + "</tr>" + "".join(
        "<tr>" + "".join(f"<td>{html.escape(v)}</td>" for v in r) + "</tr>"
        for r in fired_rows(c.get("fired", {}), c.get("recovery", {}))) + "</table>"
    inv = "<table><tr><th>invariant</th><th></th><th>evidence</th></tr>" + "".join(
        f"<tr><td>{html.escape(str(i.get('name', '')))}</td><td>{'pass' if i.get('ok') else '<b>FAIL</b>'}</td>"
        f"<td>{html.escape(str(i.get('evidence', '')))}</td></tr>" for i in c.get("invariants", [])) + "</table>"
    head = (f"<p>{html.escape(str(c.get('scenario', '')))}, seed {c.get('seed')}, {c.get('n_faults')} faults over "
            f"{c.get('steps')} steps (schedule sha256 {html.escape(str(c.get('schedule_sha256', ''))[:12])}); exit code "
            f"{c.get('exit_code')}; {'every invariant holds' if c.get('ok') else '<b>an invariant is violated</b>'}"
            + (f"; broken: {html.escape(str(c['broken']))}" if c.get("broken") else "") + ".</p>")
    return "<h2>Chaos campaign</h2>" + head + "<h3>Faults fired and recovery</h3>" + fired + "<h3>Invariants</h3>" + inv


def make_report(path: str | Path, out: str | Path | None = None) -> Path:
    """Write figures and ``report.html``; returns the HTML path. ``path`` is a run folder (or
    its recording), a study's folder, or a chaos campaign's (``chaos.json``: the campaign's
    tables, then its run's report)."""
    p = Path(path)
    out = Path(out) if out else (p.parent if p.is_file() else p) / "report"
    out.mkdir(parents=True, exist_ok=True)
    sections = []
    campaign = None
    if p.is_dir() and (p / "chaos.json").exists():
        campaign = json.loads((p / "chaos.json").read_text())
        sections.append(_chaos_section(campaign))
        p = p / "run"
    if campaign is not None and not (p / "run.mcap").exists():
        title = f"Chaos campaign: {p.parent.name} (its run left no recording)"
    elif p.is_dir() and (p / "mc.json").exists():
        figs, table = _mc_figures(p, out)
        sections.append("<h2>Monte Carlo</h2>" + table + "".join(_img(f, f.stem) for f in figs))
        title = f"Monte Carlo report: {p.name}"
    elif p.is_dir() and (p / "links_study.json").exists():
        md = (p / "links_study.md").read_text() if (p / "links_study.md").exists() else ""
        sections.append("<h2>Links study</h2><pre>" + html.escape(md) + "</pre>")
        sections.extend(_img(f, f.stem) for f in sorted(p.glob("*.png")))
        title = f"Links study: {p.name}"
    elif p.is_dir() and (p / "compare.json").exists():
        cmp_ = json.loads((p / "compare.json").read_text())
        md = (p / "compare.md").read_text() if (p / "compare.md").exists() else ""
        pngs = sorted(p.glob("*.png"))
        sections.append("<h2>Strategy comparison</h2><pre>" + html.escape(md or json.dumps(cmp_, indent=1)[:20000]) + "</pre>")
        sections.extend(_img(f, f.stem) for f in pngs)
        title = f"Selection comparison: {p.name}"
    elif p.is_dir() and (p / "compare_estimators.json").exists():
        md = (p / "compare_estimators.md").read_text() if (p / "compare_estimators.md").exists() else ""
        sections.append("<h2>Estimators compared</h2><pre>" + html.escape(md) + "</pre>")
        sections.extend(_img(f, f.stem) for f in sorted(p.glob("*.png")))
        title = f"Estimators compared: {p.name}"
    else:
        data = load_run(p)
        title = (f"Chaos campaign: {p.parent.name}, seed {campaign.get('seed')}" if campaign is not None else "Run report") \
            + f": {data.name} (n = {data.n}, {len(data.t)} steps)"
        sections.append("<h2>Summary</h2>" + _summary_table(data.summary))
        if (est := _estimator_table(data.summary)):
            sections.append("<h2>Estimator</h2>" + est)
        sections.append("<h2>Faults</h2>" + _faults_table(data.faults))
        if data.links is not None:
            sections.append(links_section(data, out))
        if (rp := fig_range(data, out)) is not None:
            sections.append("<h2>Range</h2>" + _img(rp, "ranges, and the relative position error as a percentage of range"))
        sections.append("<h2>Consistency</h2>" + _img(fig_nees(data, out), "NEES over time with its 95 % χ² band"))
        sections.append(_img(fig_gate(data, out), "validation-gate rejections over time"))
        sections.append("<h2>Measurement schedule</h2>" + _img(fig_schedule(data, out), "how often each (observer, target) pair was measured"))
        sections.append("<h2>Errors per filter</h2>")
        for f in range(data.err.shape[1]):
            sections.append(_img(fig_filter(data, f, out), f"filter {f}: own and others' errors against ±3σ"))
    page = out / "report.html"
    page.write_text(_PAGE.format(title=html.escape(title), body="\n".join(sections)))
    return page

