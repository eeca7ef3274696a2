"""In-process commands: ``sim``, ``mc``, ``compare``, ``links-study``, ``compare-estimators``, ``starfox``."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from swarm.cli.common import (
    ClusterOpt,
    ResumeOpt,
    SetOpt,
    _fmt3,
    _links_table,
    _load,
    _progress,
    _report_failed,
    _study,
    _summary_table,
    app,
    console,
    number,
)
from swarmcore.scenario import STRATEGIES


@app.command()
def sim(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder to write"),
    seed: int | None = typer.Option(None, help="override the scenario seed"),
    sets: list[str] | None = SetOpt,
    arrays: bool = typer.Option(True, help="write truth.npz and estimates.npz"),
    scene: bool = typer.Option(True, help="write scene.mcap: the 3-D scene for Foxglove (the channels of a recording and "
                               "of the live view; docs/foxglove-layout.json opens it)"),
    measurements: bool = typer.Option(
        False, "--measurements", help="rendered scenarios: also write OUT/measurements.npz (every vision "
        "measurement's camera-frame error, the variances attached, what the error model read) and their "
        "normalised statistics and autocorrelation in summary.json (measurement_residuals)"),
):
    """Run every satellite's filter in this process (fast, no bus).

    Writes OUT/summary.json, OUT/truth.npz, OUT/estimates.npz, OUT/scene.mcap and OUT/scenario.yaml.
    """
    from swarm.api import simulate
    from swarm.record.scene_file import SCENE_FILE

    sc = _load(scenario, sets, seed)
    records: list | None = [] if measurements and sc.vision.pipeline != "none" else None
    with _progress() as prog:
        task = prog.add_task(f"sim {sc.name} n={sc.n_sats}", total=sc.steps)
        res = simulate(sc, progress=lambda k, K: prog.update(task, completed=k), measurements=records,
                       scene=out / SCENE_FILE if scene else False)
    extra = None
    if records is not None:
        from swarmvision.residuals import residuals, summarize_residuals, write_residuals

        assert res.sim is not None
        rr = residuals(records, res.sim.truth, res.sim.t_s, sc.orbit.mean_motion_rad_s)
        out.mkdir(parents=True, exist_ok=True)
        write_residuals(rr, out / "measurements.npz")
        extra = {"measurement_residuals": summarize_residuals(rr)}
        mr = extra["measurement_residuals"]
        if mr["n"]:
            console.print(
                f"{mr['n']} vision measurements: mean (e/σ)² att {_fmt3(mr['mean_z2'][:3])} pos {_fmt3(mr['mean_z2'][3:])}, "
                f"clipped at 5σ att {_fmt3(mr['mean_z2_clipped'][:3])} pos {_fmt3(mr['mean_z2_clipped'][3:])}; "
                f"lag-1 autocorrelation att {_fmt3(mr['lag1'][:3])} pos {_fmt3(mr['lag1'][3:])}",
                highlight=False)
    summary = res.save(out, arrays=arrays, extra_summary=extra)
    console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed}"))
    if (lt := _links_table(summary)) is not None:
        console.print(lt)
    console.print(
        f"NEES mean {number(summary['nees']['mean'], '.2f')} (dof 6) · gate accepted {summary['gate']['accepted']}, "
        f"rejected {summary['gate']['rejected']} · filter step median "
        f"{summary['timing']['filter_step_ms_median']:.3f} ms · wrote {out}"
    )


@app.command()
def mc(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    runs: int = typer.Option(..., "--runs", "-r", min=1, help="number of runs (run i has seed S + i)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for run_XXXX/ and mc.json"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: int | None = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: list[str] | None = SetOpt,
    arrays: bool = typer.Option(False, help="also write each run's npz arrays"),
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Monte Carlo: R runs in parallel processes (or on a Dask cluster); writes each run's
    summary as it finishes (run_XXXX/, results.jsonl) and mc.json.

    A run that fails is listed with its seed and error (and in mc.json "failed"); the others
    complete, and the exit status is 1.
    """
    from swarm.api import monte_carlo

    sc = _load(scenario, sets)
    with _progress() as prog:
        task = prog.add_task(f"mc {sc.name} ×{runs}", total=runs)
        res = _study(monte_carlo, sc, runs, out=out, seed=seed, workers=workers, arrays=arrays, cluster=cluster, resume=resume,
                     progress=lambda k, K: prog.update(task, completed=k), log=lambda m: console.print(m, highlight=False)).doc
    st = res["stats"]
    if not st:
        _report_failed([(str(f["seed"]), f["error"]) for f in res["failed"]], "runs", out, "seed")
    t = Table(title=f"{sc.name}: {res['runs_ok']} runs (mean ± std)")
    t.add_column("field")
    t.add_column("mean ± std", justify="right")
    for key in (
        "rms.self.att_rad",
        "rms.self.pos_m",
        "rms.others.att_rad",
        "rms.others.pos_m",
        "rms_second_half.others.att_rad",
        "rms_second_half.others.pos_m",
        "nees.mean",
    ):
        t.add_row(key, f"{number(st[key]['mean'], '.4g')} ± {number(st[key]['std'], '.2g')}")
    console.print(t)
    console.print(f"wrote {out / 'mc.json'}")
    _report_failed([(str(f["seed"]), f["error"]) for f in res["failed"]], "runs", out, "seed")


@app.command()
def compare(
    scenario: Path = typer.Argument(..., help="scenario YAML file (e.g. scenarios/selection.yaml)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for compare.json, compare.md and heatmap_<strategy>.png"),
    runs: int = typer.Option(10, "--runs", "-r", min=1, help="paired runs per strategy (run i has seed S + i)"),
    strategies: str = typer.Option(",".join(STRATEGIES), help="comma-separated selection strategies"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: int | None = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: list[str] | None = SetOpt,
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Paired comparison of selection strategies over the same seeds (dissertation Table 6.1, Figure 6.3).

    Writes OUT/results.jsonl (each run as it finishes), OUT/compare.json, OUT/compare.md
    (per-run table, ratios, paired wins) and one heat map per strategy of how often each
    (observer, target) pair was chosen. A failed run is listed with its strategy, seed and
    error, its seed is left out of the paired statistics, and the exit status is 1.
    """
    from swarm.api import compare as compare_variants
    from swarm.studies.compare import METRICS

    sc = _load(scenario, sets)
    names = [s.strip() for s in strategies.split(",") if s.strip()]
    bad = [s for s in names if s not in STRATEGIES]
    if bad or not names:
        console.print(f"[red]error:[/red] --strategies: unknown {bad}; expected some of {list(STRATEGIES)}", highlight=False)
        raise typer.Exit(2)
    with _progress() as prog:
        task = prog.add_task(f"compare {sc.name} {len(names)}×{runs}", total=len(names) * runs)
        res = _study(compare_variants, sc, strategies=names, runs=runs, out=out, seed=seed, workers=workers, cluster=cluster,
                     resume=resume, progress=lambda k, K: prog.update(task, completed=k),
                     log=lambda m: console.print(m, highlight=False)).doc
    failed = [(f"{f['strategy']} seed {f['seed']}", f["error"]) for f in res["failed"]]
    if not res["seeds"]:
        _report_failed(failed, "runs", out, "run")
    t = Table(title=f"{sc.name}: n={sc.n_sats}, budget {sc.selection.budget}, {len(res['seeds'])} paired runs (mean)")
    t.add_column("strategy")
    for key, _ in METRICS:
        t.add_column(key, justify="right")
    t.add_column("att/random", justify="right")
    t.add_column("pos/random", justify="right")
    t.add_column("select ms", justify="right")
    for s in names:
        sm = res["summary"][s]
        ratios = [f"{sm[k]['vs_random']['ratio_of_means']:.3f}" if "vs_random" in sm[k] else "—" for k in ("att_full", "pos_full")]
        t.add_row(s, *[number(sm[k]["mean"]) for k, _ in METRICS], *ratios, number(sm["select_ms_median"], ".2f"))
    console.print(t)
    console.print(f"wrote {out / 'compare.md'}, {out / 'compare.json'} and {len(names)} heat maps")
    _report_failed(failed, "runs", out, "run")


@app.command("links-study")
def links_study(
    scenario: Path = typer.Argument(..., help="scenario YAML file (e.g. scenarios/links-study.yaml)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for links_study.json, links_study.md and the plots"),
    runs: int = typer.Option(5, "--runs", "-r", min=1, help="paired seeds per cell (run i has seed S + i in every cell)"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: int | None = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: list[str] | None = SetOpt,
    full: bool = typer.Option(False, "--full", help="the full sweep: every latency × every loss rate × replay/drop, and the caps"),
    latencies: str | None = typer.Option(None, help="comma-separated latencies (s) instead of the sweep's"),
    losses: str | None = typer.Option(None, help="comma-separated Gilbert–Elliott loss rates (0..1) instead of the sweep's"),
    loss_latency: float | None = typer.Option(None, min=0.0, help="the latency (s) of the loss sweep (default sweep: 2)"),
    caps: str | None = typer.Option(None, help="comma-separated fractions of the complete graph's need ('' for none)"),
    late: str | None = typer.Option(None, help="comma-separated filter.late modes (replay,drop)"),
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Sweep the network: latency, bursty loss and a data-rate cap below what the complete
    graph needs; replay vs drop of late measurements, and the complete graph vs greedy
    selection under the cap (paired seeds). The sweep is defined in swarm/studies/links_study.py
    (DEFAULT_SWEEP, FULL_SWEEP); the options replace parts of it.

    Writes OUT/links_study.md (the table), OUT/links_study.json and latency.png, loss.png, cap.png.
    """
    from dataclasses import replace

    from swarm.studies.links_study import DEFAULT_SWEEP, FULL_SWEEP, METRICS, run_links_study

    sc = _load(scenario, sets)
    sweep = FULL_SWEEP if full else DEFAULT_SWEEP

    def floats(opt: str, text: str, lo: float, hi: float) -> tuple[float, ...]:
        try:
            vals = tuple(float(x) for x in text.split(",") if x.strip())
            if all(lo <= v < hi for v in vals):
                return vals
        except ValueError:
            pass
        console.print(f"[red]error:[/red] --{opt} {text!r}: expected comma-separated numbers in [{lo:g}, {hi:g})", highlight=False)
        raise typer.Exit(2)

    if latencies is not None:
        sweep = replace(sweep, latencies_s=floats("latencies", latencies, 0.0, float("inf")) or sweep.latencies_s)
    if loss_latency is not None:
        sweep = replace(sweep, loss_latency_s=loss_latency)
    if losses is not None:
        sweep = replace(sweep, loss_rates=floats("losses", losses, 0.0, 1.0) or sweep.loss_rates)
    if caps is not None:
        sweep = replace(sweep, cap_fractions=floats("caps", caps, 1e-9, 1.0))
    if late is not None:
        modes = tuple(m.strip() for m in late.split(",") if m.strip())
        if not modes or any(m not in ("replay", "drop") for m in modes):
            console.print(f"[red]error:[/red] --late {late!r}: expected replay and/or drop", highlight=False)
            raise typer.Exit(2)
        sweep = replace(sweep, late_modes=modes)
    from swarm.studies.executor import ResultStore, StudyMapper, open_executor

    out.mkdir(parents=True, exist_ok=True)
    store = ResultStore(out / "results.jsonl", resume=resume)
    try:
        with _study(open_executor, workers, cluster) as ex, _progress() as prog:
            mapper = StudyMapper(ex, store, log=lambda m: console.print(m, highlight=False), noun="runs")
            task = prog.add_task(f"links-study {sc.name} n={sc.n_sats} ×{runs} seeds", total=None)
            doc = run_links_study(sc, out, runs=runs, sweep=sweep, seed=seed, workers=workers, mapper=mapper,
                                  progress=lambda k, K: prog.update(task, completed=k, total=K))
    finally:
        store.close()
    t = Table(title=f"{sc.name}: n={sc.n_sats}, {sc.duration_s:g} s, {runs} paired seeds (mean); "
                    f"complete graph needs {doc['probe']['need_Bps']:.0f} B/s per transmitter")
    for col in ("latency s", "loss", "late", "arm", "cap B/s"):
        t.add_column(col)
    for key, _ in METRICS[:2] + METRICS[4:6]:
        t.add_column(key, justify="right")
    t.add_column("delivered", justify="right")
    for c in doc["cells"]:
        p, st = c["params"], c["stats"]
        t.add_row(f"{p['latency_s']:g}", f"{p['loss']:.0%}", p["late"], p["arm"] + ("" if p["budget"] is None else f" m={p['budget']}"),
                  "—" if p["rate_Bps"] is None else f"{p['rate_Bps']:.0f}",
                  *[number(st[k]["mean"]) for k, _ in METRICS[:2] + METRICS[4:6]], f"{st['links']['delivered_fraction']:.1%}")
    console.print(t)
    console.print(f"{len(doc['cells'])} cells × {runs} seeds in {doc['wall_s']:.0f} s · wrote {out / 'links_study.md'}, "
                  f"{out / 'links_study.json'} and the plots")
    _report_failed(sorted(mapper.result.errors.items()) if mapper.result else [], "runs", out, "cell/seed")


@app.command("compare-estimators")
def compare_estimators(
    scenario: Path = typer.Argument(..., help="scenario YAML file (e.g. scenarios/estimators.yaml)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for compare_estimators.json, .md and estimators.png"),
    runs: int = typer.Option(5, "--runs", "-r", min=1, help="paired seeds per cell (run i has seed S + i in every cell)"),
    estimators: str = typer.Option("full,ci,pairwise", help="comma-separated estimator kinds (built in or installed plug-ins)"),
    conditions: str = typer.Option("ideal,latency,loss,cap,restart", help="comma-separated conditions: ideal, latency (3 s), "
                                   "loss (3 s + 20 % bursty), cap (half the full graph's need), restart (an agent killed and restarted)"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: int | None = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: list[str] | None = SetOpt,
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Estimators side by side on the same truth, sensors, links and faults (paired seeds):
    accuracy (own and relative), consistency (NEES), traffic and CPU per estimator, under
    the ideal radio, latency, bursty loss, a data-rate cap and an agent killed and restarted.

    Writes OUT/results.jsonl (each run as it finishes), compare_estimators.json, a markdown
    table and estimators.png. A failed run is listed with its error; the exit status is then 1.
    """
    from swarm.studies.compare_estimators import CONDITIONS, METRICS, run_compare_estimators
    from swarmrt.estimators import IncompatibleScenario, estimator_for

    sc = _load(scenario, sets)
    kinds = [k.strip() for k in estimators.split(",") if k.strip()]
    conds = [c.strip() for c in conditions.split(",") if c.strip()]
    if bad := [c for c in conds if c not in CONDITIONS]:
        console.print(f"[red]error:[/red] --conditions: unknown {bad}; expected some of {list(CONDITIONS)}", highlight=False)
        raise typer.Exit(2)
    for k in kinds:
        try:
            estimator_for(sc.model_copy(update={"estimator": sc.estimator.model_copy(update={"kind": k})}), 0)
        except IncompatibleScenario as exc:
            console.print(f"[red]error:[/red] --estimators {k}: {exc}", highlight=False)
            raise typer.Exit(2) from None
    with _progress() as prog:
        task = prog.add_task(f"compare-estimators {sc.name} {len(conds)}×{len(kinds)}×{runs}", total=len(conds) * len(kinds) * runs)
        doc = _study(run_compare_estimators, sc, runs, out, estimators=kinds, conditions=conds, seed=seed, workers=workers,
                     cluster=cluster, resume=resume, progress=lambda k, K: prog.update(task, completed=k),
                     log=lambda m: console.print(m, highlight=False))
    for cond in conds:
        t = Table(title=f"{sc.name}: {cond} ({len(doc['seeds'])} seeds, mean)")
        t.add_column("estimator")
        for _key, label, _ in METRICS:
            t.add_column(label, justify="right")
        for k in kinds:
            t.add_row(k, *[number(doc["summary"][cond][k][key]["mean"]) for key, _, _ in METRICS])
        console.print(t)
    console.print(f"wrote {out / 'compare_estimators.md'}, {out / 'compare_estimators.json'} and {out / 'estimators.png'}")
    _report_failed([(f"{f['condition']}/{f['estimator']} seed {f['seed']}", f["error"]) for f in doc["failed"]], "runs", out, "run")


@app.command()
def starfox(
    scenario: Path = typer.Argument(Path("scenarios/starfox.yaml"), help="scenario YAML file (a StarFOX-like long-range swarm)"),
    out: Path = typer.Option(Path("runs/starfox"), "--out", "-o", help="folder for starfox.json and percent-of-range.png"),
    runs: int = typer.Option(20, "--runs", "-r", min=1, help="seeds per configuration (run i has seed S + i)"),
    configs: str = typer.Option("single,several", "--configs", help="comma-separated: single (satellite 0 the only observer), "
                                "several (every satellite observes every other)"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    estimators: str | None = typer.Option(None, "--estimators", help="instead: the percentage-of-range table per estimator "
                                          "(comma-separated kinds, e.g. full,ci,pairwise,gbp), paired seeds, one process, "
                                          "resumable: OUT/per-estimator.jsonl (each run as it finishes) and OUT/per-estimator.md"),
    sets: list[str] | None = SetOpt,
    cluster: str | None = ClusterOpt,
):
    """Angles-only relative navigation at long range, one observer against several (the
    StarFOX flight's comparison): satellite 0's relative position error and 1σ as a
    percentage of range over the second half of each run, and the consistency (NEES) of
    its filter. Writes OUT/starfox.json (every run and the aggregate) and
    OUT/percent-of-range.png (median and 10–90 % band over time); with --estimators, the
    table per estimator instead."""
    from swarm.studies.executor import open_executor
    from swarm.studies.starfox import CONFIGS, estimator_table, plot, run_per_estimator, run_starfox

    _load(scenario, sets)  # a bad file or field is a usage error before anything runs
    cs = tuple(c.strip() for c in configs.split(",") if c.strip())
    if not cs or any(c not in CONFIGS for c in cs):
        console.print(f"[red]error:[/red] --configs {configs!r}: expected some of {', '.join(CONFIGS)}", highlight=False)
        raise typer.Exit(2)
    out.mkdir(parents=True, exist_ok=True)
    if estimators is not None:
        ests = tuple(e.strip() for e in estimators.split(",") if e.strip())
        for e in ests:
            _load(scenario, [*(sets or ()), f"estimator.kind={e}"])  # an unknown kind is a usage error naming it
        with _progress() as prog:
            task = prog.add_task(f"starfox {scenario.name} per estimator", total=len(ests) * len(cs) * runs)
            res = _study(run_per_estimator, scenario, runs, out / "per-estimator.jsonl", ests, cs, tuple(sets or ()),
                         log=lambda _line: prog.advance(task))
        table = estimator_table(res, ests, cs)
        (out / "per-estimator.md").write_text(table + "\n")
        console.print(table, highlight=False)
        console.print(f"wrote {out / 'per-estimator.jsonl'} and {out / 'per-estimator.md'}")
        return
    with _study(open_executor, workers, cluster) as ex, _progress() as prog:
        task = prog.add_task(f"starfox {scenario.name} {len(cs)}×{runs}", total=len(cs) * runs)
        doc = _study(run_starfox, scenario, runs, ex, cs, tuple(sets or ()), progress=lambda k, K: prog.update(task, completed=k))
    (out / "starfox.json").write_text(json.dumps(doc, indent=1))
    plot(doc["per_run"], cs, out / "percent-of-range.png")
    t = Table(title=f"{scenario.name}: satellite 0's filter, second half ({runs} seeds; mean, median in brackets)")
    for col in ("observers", "runs", "|Δr| / range %", "1σ / range %", "rel NEES_pos/3", "abs NEES_pos/3", "pose NEES/6", "range km"):
        t.add_column(col, justify="right" if col != "observers" else "left")
    for c in cs:
        a = doc["aggregate"][c]
        t.add_row(c, str(a["runs"]), f"{a['err_pct']['mean']:.3f} ({a['err_pct']['median']:.3f})", f"{a['sigma_pct']['mean']:.3f}",
                  f"{a['nees_pos']['mean']:.2f} ({a['nees_pos']['median']:.2f})", f"{a['nees_pos_abs']['mean']:.2f}",
                  f"{a['nees6']['mean']:.2f}", f"{a['range_km']['mean']:.1f}")
    console.print(t)
    console.print(f"wrote {out / 'starfox.json'} and {out / 'percent-of-range.png'}")
    if doc["failed"]:
        for f in doc["failed"]:
            console.print(f"[red]failed run {f['run']}:[/red] {f['error']}", highlight=False)
        raise typer.Exit(1)
