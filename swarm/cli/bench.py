"""``swarm bench ...``: benchmarks that print numbers and write JSON."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from swarm.cli.common import SetOpt, _load, bench_app, console
from swarmcore.scenario import STRATEGIES


@bench_app.command("filter")
def bench_filter_cmd(
    sats: str = typer.Option("3,6,12,25,50,100", help="comma-separated swarm sizes"),
    graph: str = typer.Option("complete", help="complete, star, chain or duplex_chain"),
    out: Path = typer.Option(Path("bench-filter.json"), "--out", "-o", help="JSON file to write"),
    steps: int | None = typer.Option(None, help="timed steps per size (default: by size)"),
    stacked_max_n: int = typer.Option(25, help="largest n for the stacked reference"),
):
    """Median ms per filter step (predict + update, one filter), fast form vs stacked reference."""
    from swarm.bench.filter import bench_filter, machine_info
    from swarm.outputs import write_json

    sizes = [int(s) for s in sats.split(",") if s.strip()]
    rows = bench_filter(sizes, graph, steps, stacked_max_n, log=lambda s: console.print(s, highlight=False))
    write_json(out, rows)
    write_json(out.with_suffix(".meta.json"), machine_info())
    console.print(f"wrote {out}")


@bench_app.command("late")
def bench_late_cmd(
    n: int = typer.Option(10, "--sats", help="swarm size"),
    history_s: float = typer.Option(10.0, help="filter.history_s of the replaying agent"),
    lags: str = typer.Option("0,1,2,5,10", help="comma-separated lateness of every peer batch (steps)"),
    out: Path = typer.Option(Path("bench-late.json"), "--out", "-o", help="JSON file to write"),
):
    """ms per filter step when every peer batch arrives late and is replayed (filter.late: replay)."""
    from swarm.bench.filter import bench_late, machine_info
    from swarm.outputs import write_json

    rows = bench_late(n, history_s, [int(x) for x in lags.split(",") if x.strip()], log=lambda s: console.print(s, highlight=False))
    write_json(out, {"machine": machine_info(), "rows": rows})
    console.print(f"wrote {out}")


@bench_app.command("bus")
def bench_bus_cmd(
    out: Path = typer.Option(Path("bench-bus.json"), "--out", "-o", help="JSON file to write"),
    samples: int = typer.Option(400, help="round trips of each measurement batch"),
    batch_sats: str = typer.Option("10,40", "--batch-sats", help="swarm sizes whose measurement batch to send"),
    security: str = typer.Option("on,off", "--security", help="bus security settings to measure, side by side (on, off)"),
):
    """Bus latency p50/p99 of measurement batches and of a 1 MB payload (loopback, via a router),
    and the CPU cost of encoding and decoding a batch."""
    from swarm.bench.bus import bench_latency
    from swarm.bench.filter import machine_info
    from swarm.outputs import write_json

    sizes = [int(x) for x in batch_sats.split(",") if x.strip()]
    rows = bench_latency(samples=samples, log=lambda s: console.print(s, highlight=False), batch_sizes=sizes,
                         security=_security_modes(security))
    write_json(out, {"machine": machine_info(), "rows": rows})
    console.print(f"wrote {out}")


@bench_app.command("router")
def bench_router_cmd(
    runs: int = typer.Option(5, help="runs of each case (restart, failover)"),
    down_s: float = typer.Option(1.0, "--down-s", help="restart case: how long the router stays down (s)"),
    out: Path = typer.Option(Path("runs/bench/router.json"), "--out", "-o", help="JSON file to write"),
):
    """How long each role takes to notice a lost router and to be back on the bus (median
    over runs): one router SIGKILLed and restarted, and two meshed routers with one killed."""
    from swarm.bench.filter import machine_info
    from swarm.bench.router import bench_router
    from swarm.outputs import write_json

    doc = bench_router(runs=runs, down_s=down_s, workdir=out.parent / (out.stem + "-runs"), log=lambda s: console.print(s, highlight=False))
    write_json(out, {"machine": machine_info(), **doc})
    for case, m in doc["medians"].items():
        t = Table(title=f"{case}: median over {m['runs']} runs (all completed: {m['all_completed']}); "
                        f"run resumed {m['resumed_median_ms']} ms after the router was back")
        for col in ("role", "notice [ms]", "back on the bus [ms]", "samples"):
            t.add_column(col, justify="right")
        for role, v in sorted(m["roles"].items()):
            t.add_row(role, str(v.get("notice_median_ms", "—")), str(v.get("back_median_ms", "—")), str(v["n"]))
        console.print(t)
    console.print(f"wrote {out}")


def _security_modes(text: str) -> tuple[bool, ...]:
    modes = [m.strip() for m in text.split(",") if m.strip()]
    if not modes or any(m not in ("on", "off") for m in modes):
        console.print(f"[red]error:[/red] --security {text!r}: a comma-separated list of on and off", highlight=False)
        raise typer.Exit(2)
    return tuple(m == "on" for m in modes)


@bench_app.command("run")
def bench_run_cmd(
    sats: str = typer.Option("5,10", help="comma-separated swarm sizes"),
    duration: float = typer.Option(60.0, help="simulated seconds per run"),
    out: Path = typer.Option(Path("bench-run.json"), "--out", "-o", help="JSON file to write"),
    security: str = typer.Option("on,off", "--security", help="bus security settings to measure, side by side (on, off)"),
    estimator: str = typer.Option("full", "--estimator", help="every agent's estimator (full, ci, pairwise, or a plug-in)"),
    graph: str | None = typer.Option(None, "--graph", help="complete, or nearest (a lattice, each satellite measuring its 3 nearest); "
                                     "default: complete for full, nearest otherwise"),
    agent_start: str = typer.Option("fork", "--agent-start", help="fork (the fork server) or spawn (an interpreter per agent)"),
):
    """Real-time factor, start-up, memory (peak PSS and RSS of every process of the run) and
    traffic of `swarm run` in lockstep (synthetic measurements)."""
    from swarm.bench.bus import bench_realtime
    from swarm.bench.filter import machine_info
    from swarm.outputs import write_json

    sizes = [int(s) for s in sats.split(",") if s.strip()]
    if agent_start not in ("fork", "spawn") or (graph is not None and graph not in ("complete", "nearest")):
        console.print("[red]error:[/red] --agent-start fork|spawn, --graph complete|nearest", highlight=False)
        raise typer.Exit(2)
    rows = bench_realtime(sizes, duration, log=lambda s: console.print(s, highlight=False), workdir=out.parent / (out.stem + "-runs"),
                          security=_security_modes(security), estimator=estimator, graph=graph, agent_start=agent_start)
    write_json(out, {"machine": machine_info(), "rows": rows})
    console.print(f"wrote {out}")


@bench_app.command("live")
def bench_live_cmd(
    sats: int = typer.Option(10, "--sats", min=1, help="swarm size"),
    duration: float = typer.Option(60.0, help="simulated seconds per run"),
    repeats: int = typer.Option(3, "--repeats", min=1, help="rounds of the three settings (alternating)"),
    out: Path = typer.Option(Path("bench-live.json"), "--out", "-o", help="JSON file to write"),
):
    """What the live 3-D view costs `swarm run`: its real-time factor (lockstep) without the
    view, with the view and no client, and with a client subscribed to every channel."""
    from swarm.bench.filter import machine_info
    from swarm.bench.live import MODES, bench_live
    from swarm.outputs import write_json

    doc = bench_live(sats, duration, repeats, log=lambda s: console.print(s, highlight=False), workdir=out.parent / (out.stem + "-runs"))
    write_json(out, {"machine": machine_info(), **doc})
    t = Table(title=f"live view at n={sats}: real-time factor, {repeats} runs each (median, min–max)")
    for col in ("setting", "RTF median", "min–max", "vs no view"):
        t.add_column(col, justify="right" if col != "setting" else "left")
    for mode in MODES:
        s = doc["summary"][mode]
        vs = s.get("vs_off")
        t.add_row(mode, f"{s['rtf_median']:.1f}×" if s["rtf_median"] else "n/a",
                  f"{s['rtf_min']:.1f}–{s['rtf_max']:.1f}" if s["rtf_min"] else "n/a", "—" if vs is None else f"{vs:.2f}")
    console.print(t)
    console.print(f"wrote {out}")


@bench_app.command("cluster")
def bench_cluster_cmd(
    scenario: Path = typer.Option(Path("scenarios/demo.yaml"), help="scenario of the Monte Carlo runs"),
    sets: list[str] | None = SetOpt,
    runs: int = typer.Option(40, min=2, help="runs per study"),
    workers: int = typer.Option(2, min=1, help="local pool processes = Dask workers (one thread each)"),
    noop_tasks: int = typer.Option(200, "--noop", min=10, help="no-op tasks for the scheduling overhead"),
    repeats: int = typer.Option(3, min=1, help="warm studies per backend (alternating; the median is reported)"),
    out: Path = typer.Option(Path("bench-cluster.json"), "--out", "-o", help="JSON file to write"),
):
    """Monte Carlo runs per minute, local pool vs a Dask cluster of as many workers started
    on this machine, and the scheduling overhead per task (no-op round trip, batch)."""
    from swarm.bench.cluster import bench_cluster
    from swarm.bench.filter import machine_info
    from swarm.outputs import write_json

    sc = _load(scenario, sets)
    res = bench_cluster(sc, runs=runs, workers=workers, noop_tasks=noop_tasks, repeats=repeats,
                        log=lambda s: console.print(s, highlight=False))
    write_json(out, {"machine": machine_info(), **res})
    console.print(f"wrote {out}")


@bench_app.command("cluster-run")
def bench_cluster_run_cmd(
    nodes: str = typer.Option("1,2,3", "--nodes", help="comma-separated node counts (a local Ray cluster each, namespaced nodes)"),
    sats: str = typer.Option("12,40", "--sats", help="comma-separated swarm sizes"),
    duration: float = typer.Option(30.0, help="simulated seconds per run"),
    estimator: str = typer.Option("ci", "--estimator", help="every agent's estimator"),
    graph: str = typer.Option("nearest", "--graph", help="nearest (a lattice, 3 nearest each) or complete"),
    rust_agent: str | None = typer.Option(None, "--agent-command", help="fly every satellite with this program instead of the "
                                          "Python sat_agent (e.g. participants/target/release/swarm-rust-agent)"),
    scenario: Path | None = typer.Option(None, "--scenario", help="fly this scenario file (its n_sats and duration_s set by "
                                         "--sats and --duration) instead of the benchmark's lattice"),
    out: Path = typer.Option(Path("bench-cluster-run.json"), "--out", "-o", help="JSON file to write"),
):
    """A swarm over 1, 2, 3 ... Ray nodes on this machine (same cores in all): real-time
    factor, start-up, CPU and PSS by role, bytes per step between nodes (root: namespaces)."""
    from swarm.bench.cluster_run import bench_cluster_run
    from swarm.bench.filter import machine_info
    from swarm.outputs import write_json

    rows = bench_cluster_run([int(x) for x in nodes.split(",") if x.strip()], [int(x) for x in sats.split(",") if x.strip()],
                             duration, estimator, graph, log=lambda s: console.print(s, highlight=False),
                             workdir=out.parent / (out.stem + "-runs"), agent_commands=rust_agent, scenario=scenario,
                             out_json=out.with_suffix(".partial.json"))
    write_json(out, {"machine": machine_info(), "rows": rows})
    t = Table(title="swarm over a Ray cluster on this machine")
    for col in ("nodes", "n", "real-time ×", "start-up s", "PSS GiB", "CPU ms/step", "Zenoh B/step between nodes"):
        t.add_column(col)
    for r in rows:
        t.add_row(str(r["nodes"]), str(r["n"]), f"{r['realtime_factor'] or 0:.2f}", f"{r['startup_s'] or 0:.1f}",
                  f"{r['pss_peak_gib']:.2f}", f"{r.get('cpu_ms_per_step_total') or 0:.0f}",
                  f"{r.get('zenoh_bytes_per_step_between_nodes') or 0:.0f}")
    console.print(t)
    console.print(f"wrote {out}")


@bench_app.command("selection")
def bench_selection_cmd(
    sats: str = typer.Option("10,50", help="comma-separated swarm sizes"),
    budgets: str = typer.Option("5", help="comma-separated budgets m"),
    strategies: str = typer.Option(",".join(STRATEGIES), help="comma-separated selection strategies"),
    scenario: Path | None = typer.Option(Path("scenarios/selection.yaml"), help="base scenario (n_sats is overridden; the cube grows as n^(1/3))"),
    reps: int | None = typer.Option(None, help="timed steps per case (default: 30 for n ≤ 20, else 10)"),
    out: Path = typer.Option(Path("bench-selection.json"), "--out", "-o", help="JSON file to write"),
    sets: list[str] | None = SetOpt,
):
    """Median ms per selection step (select_for_scenario) per swarm size, budget and strategy."""
    from swarm.bench.selection import bench_selection

    sc = _load(scenario, sets)
    rows = bench_selection(
        [int(s) for s in sats.split(",") if s.strip()],
        [int(m) for m in budgets.split(",") if m.strip()],
        [s.strip() for s in strategies.split(",") if s.strip()],
        reps=reps,
        scenario=sc,
        out=out,
        log=lambda s: console.print(s, highlight=False),
    )
    console.print(f"{len(rows)} rows · wrote {out}")


@bench_app.command("vision")
def bench_vision_cmd(
    out: Path = typer.Option(Path("bench-vision.json"), "--out", "-o", help="JSON file to write"),
    repeats: int = typer.Option(10, min=1, help="timed frames per measurement"),
    scenarios: str = typer.Option(
        "scenarios/mono-5sat.yaml,scenarios/stereo-4sat.yaml", help="rendered scenarios whose real-time factor to measure ('' to skip)"
    ),
    steps: int = typer.Option(5, min=1, help="steps of each scenario to time"),
):
    """ms per rendered frame (default resolution), per monocular detection + pose, per
    stereo pair, and the real-time factor of the rendered scenarios."""
    from swarm.bench.filter import machine_info
    from swarm.outputs import write_json
    from swarmvision.bench import bench_vision, scenario_rtf

    def log(s):
        console.print(s, highlight=False)

    res = bench_vision(repeats=repeats, log=log)
    paths = [Path(p) for p in scenarios.split(",") if p.strip()]
    res["scenarios"] = scenario_rtf([(p, _load(p, None)) for p in paths], steps, log=log) if paths else []
    res["machine_info"] = machine_info()
    write_json(out, res)
    console.print(f"wrote {out}")
