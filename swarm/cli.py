"""``swarm``: the command line of the cooperative-localisation emulator.

Every command that takes a SCENARIO accepts ``--set dotted.key=value`` (repeatable) to
override any field, e.g. ``--set n_sats=6 --set filter.gate.enabled=false``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from .scenario_files import ScenarioError, load_scenario

app = typer.Typer(
    help="Cooperative localization of satellite swarms: simulate, Monte Carlo, benchmark.\n\n"
    "Scenarios are YAML files (see scenarios/); any field can be overridden with "
    "--set dotted.key=value.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks: print numbers and write JSON.", no_args_is_help=True)
scenario_app = typer.Typer(help="Inspect scenarios: resolved values and the schema.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
app.add_typer(scenario_app, name="scenario")

console = Console(stderr=True)
SetOpt = typer.Option(None, "--set", help="override a scenario field: dotted.key=value (repeatable)")


def _load(path: Optional[Path], sets, seed=None):
    try:
        return load_scenario(path, sets or (), seed)
    except ScenarioError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2)


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal and not _force_progress(),
    )


def _force_progress() -> bool:
    import os

    return os.environ.get("SWARM_PROGRESS", "") == "1"


def _summary_table(summary: dict, title: str) -> Table:
    t = Table(title=title)
    t.add_column("error (time RMS)")
    t.add_column("self att [rad]", justify="right")
    t.add_column("self pos [m]", justify="right")
    t.add_column("others att [rad]", justify="right")
    t.add_column("others pos [m]", justify="right")
    for key, label in (("rms", "full run"), ("rms_second_half", "second half")):
        r = summary[key]
        t.add_row(
            label,
            f"{r['self']['att_rad']:.3g}",
            f"{r['self']['pos_m']:.3g}",
            f"{r['others']['att_rad']:.3g}",
            f"{r['others']['pos_m']:.3g}",
        )
    return t


@app.command()
def sim(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder to write"),
    seed: Optional[int] = typer.Option(None, help="override the scenario seed"),
    sets: Optional[List[str]] = SetOpt,
    arrays: bool = typer.Option(True, help="write truth.npz and estimates.npz"),
):
    """Run every satellite's filter in this process (fast, no bus).

    Writes OUT/summary.json, OUT/truth.npz, OUT/estimates.npz and OUT/scenario.yaml.
    """
    from swarmcore.sim import simulate

    from .outputs import write_run

    sc = _load(scenario, sets, seed)
    with _progress() as prog:
        task = prog.add_task(f"sim {sc.name} n={sc.n_sats}", total=sc.steps)
        res = simulate(sc, progress=lambda k, K: prog.update(task, completed=k))
    summary = write_run(res, out, arrays=arrays)
    console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed}"))
    console.print(
        f"NEES mean {summary['nees']['mean']:.2f} (dof 6) · gate accepted {summary['gate']['accepted']}, "
        f"rejected {summary['gate']['rejected']} · filter step median "
        f"{summary['timing']['filter_step_ms_median']:.3f} ms · wrote {out}"
    )


@app.command()
def mc(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    runs: int = typer.Option(..., "--runs", "-r", min=1, help="number of runs (run i has seed S + i)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for run_XXXX/ and mc.json"),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: Optional[int] = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: Optional[List[str]] = SetOpt,
    arrays: bool = typer.Option(False, help="also write each run's npz arrays"),
):
    """Monte Carlo: R runs in parallel processes; writes each run's summary and mc.json."""
    from .mc import run_mc

    sc = _load(scenario, sets)
    with _progress() as prog:
        task = prog.add_task(f"mc {sc.name} ×{runs}", total=runs)
        res = run_mc(sc, runs, out, seed=seed, workers=workers, arrays=arrays, progress=lambda k, K: prog.update(task, completed=k))
    st = res["stats"]
    t = Table(title=f"{sc.name}: {runs} runs (mean ± std)")
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
        t.add_row(key, f"{st[key]['mean']:.4g} ± {st[key]['std']:.2g}")
    console.print(t)
    console.print(f"wrote {out / 'mc.json'}")


@app.command()
def run(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder: run.mcap, summary.json, logs/"),
    seed: Optional[int] = typer.Option(None, help="override the scenario seed"),
    sets: Optional[List[str]] = SetOpt,
    timeout: Optional[float] = typer.Option(None, help="stop the run after this many wall seconds"),
):
    """Run the swarm as real processes on a local Zenoh bus (router, recorder, world,
    selector, one agent per satellite) and compute summary.json from the recording.

    While it runs, `swarm fault --run-dir OUT ...` injects faults.
    """
    from .launch import LocalSwarm
    from .outputs import write_json
    from .recording import load_recording

    sc = _load(scenario, sets, seed)
    try:
        swarm = LocalSwarm(sc, out, log=lambda s: console.print(s))
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2)
    code = 1
    try:
        swarm.start()
        console.print(f"run {swarm.run}: {sc.n_sats} agents on {swarm.endpoint}; faults: swarm fault --run-dir {out} ...")
        with _progress() as prog:
            task = prog.add_task(f"run {sc.name} n={sc.n_sats} ({sc.emulator.time_mode})", total=sc.steps)
            code = swarm.run_to_end(progress=lambda k, K: prog.update(task, completed=k), timeout=timeout)
    finally:
        swarm.stop()
    rec = load_recording(out / "run.mcap", sc.n_sats, sc.steps)
    summary = rec.summary(sc)
    summary["run"] = swarm.run
    summary["world_exit_code"] = code
    write_json(out / "summary.json", summary)
    console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed} (from the recording)"))
    if summary["faults"]:
        t = Table(title="faults")
        for col in ("k", "action", "target", "phase", "sender", "detail"):
            t.add_column(col)
        for f in summary["faults"]:
            t.add_row(*(str(f.get(c, "")) for c in ("k", "action", "target", "phase", "sender", "detail")))
        console.print(t)
    console.print(f"wrote {out / 'run.mcap'} and {out / 'summary.json'}")
    if code != 0:
        raise typer.Exit(code)


fault_app = typer.Typer(
    help="Inject faults into a running swarm: `swarm fault --run-dir DIR kill-agent 2` (local, "
    "from `swarm run --out DIR`) or `swarm fault --compose kill-agent 2` (docker compose).",
    no_args_is_help=True,
)
app.add_typer(fault_app, name="fault")


@fault_app.callback()
def fault_target(
    ctx: typer.Context,
    run_dir: Optional[Path] = typer.Option(None, "--run-dir", help="the run folder of `swarm run` (has run.json)"),
    compose: bool = typer.Option(False, "--compose", help="the swarm of `docker compose up` (docker CLI for process and network faults)"),
    connect: Optional[str] = typer.Option(None, "--connect", help="bus endpoint (default with --compose: tcp/127.0.0.1:$SWARM_BUS_PORT or 7447)"),
    run_id: Optional[str] = typer.Option(None, "--run", help="run id (default with --compose: $SWARM_RUN or 'compose')"),
    project: Optional[str] = typer.Option(None, "--project", help="compose project name (default: any)"),
    network: Optional[str] = typer.Option(None, "--network", help="compose bus network for partition/heal (default: *_bus)"),
):
    """Where the swarm is."""
    ctx.obj = dict(run_dir=run_dir, compose=compose, connect=connect, run_id=run_id, project=project, network=network)


def _send_fault(ctx: typer.Context, **fields):
    from .faults import send_fault

    try:
        result = send_fault(**ctx.obj, **fields)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2)
    typer.echo(result)


@fault_app.command("kill-agent")
def fault_kill_agent(ctx: typer.Context, sat: int):
    """SIGKILL satellite SAT's agent. Its satellite keeps flying and being seen."""
    _send_fault(ctx, action="kill-agent", target=sat)


@fault_app.command("stop-agent")
def fault_stop_agent(ctx: typer.Context, sat: int):
    """Stop satellite SAT's agent cleanly (SIGTERM; `docker stop` under compose)."""
    _send_fault(ctx, action="stop-agent", target=sat)


@fault_app.command("restart-agent")
def fault_restart_agent(ctx: typer.Context, sat: int):
    """Start a new agent for SAT; it initialises from a live peer's estimate."""
    _send_fault(ctx, action="restart-agent", target=sat)


@fault_app.command("camera")
def fault_camera(
    ctx: typer.Context,
    sat: int,
    cam: int = typer.Argument(..., min=0, max=5, help="camera 0..5 (+z,+x,+y,-x,-y,-z)"),
    state: str = typer.Argument(..., help="on or off"),
):
    """Turn camera CAM of satellite SAT off (it produces nothing) or back on."""
    if state not in ("on", "off"):
        console.print("[red]error:[/red] state must be 'on' or 'off'")
        raise typer.Exit(2)
    _send_fault(ctx, action="camera", target=sat, camera=cam, state=state)


@fault_app.command("kill-selector")
def fault_kill_selector(ctx: typer.Context):
    """SIGKILL the selector; the world falls back to a state-free strategy."""
    _send_fault(ctx, action="kill-selector")


@fault_app.command("restart-selector")
def fault_restart_selector(ctx: typer.Context):
    """Start a new selector."""
    _send_fault(ctx, action="restart-selector")


@fault_app.command("drop")
def fault_drop(ctx: typer.Context, sat: int, rate: float = typer.Option(..., "--rate", min=0.0, max=1.0, help="fraction of SAT's outgoing messages lost")):
    """Lose a fraction of satellite SAT's outgoing measurement batches and estimates."""
    _send_fault(ctx, action="drop", target=sat, rate=rate)


@fault_app.command("partition")
def fault_partition(ctx: typer.Context, sat: int):
    """Cut satellite SAT's container off the bus network (compose only)."""
    _send_fault(ctx, action="partition", target=sat)


@fault_app.command("heal")
def fault_heal(ctx: typer.Context, sat: int):
    """Reconnect satellite SAT's container to the bus network (compose only)."""
    _send_fault(ctx, action="heal", target=sat)


@app.command()
def recover(recording: Path = typer.Argument(..., help="a damaged MCAP file"), out: Optional[Path] = typer.Option(None, "--out")):
    """Salvage every complete message of a damaged recording into a clean MCAP."""
    from .mcaplog import recover as _recover

    n = _recover(recording, out)
    console.print(f"recovered {n} messages")


@app.command()
def report(
    run: Path = typer.Argument(..., help="a run folder (swarm sim / swarm run), an MCAP file, or a Monte Carlo / comparison folder"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="folder for the figures and report.html (default: RUN/report)"),
):
    """Figures and one self-contained HTML page: errors against ±3σ per filter, NEES with
    its χ² band, gate rejections, the measurement schedule, faults on every time axis."""
    from .report import make_report

    try:
        page = make_report(run, out)
    except (FileNotFoundError, ValueError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2)
    console.print(f"wrote {page} ({len(list(page.parent.glob('*.png')))} figures)")


@bench_app.command("filter")
def bench_filter_cmd(
    sats: str = typer.Option("3,6,12,25,50,100", help="comma-separated swarm sizes"),
    graph: str = typer.Option("complete", help="complete, star, chain or duplex_chain"),
    out: Path = typer.Option(Path("bench-filter.json"), "--out", "-o", help="JSON file to write"),
    steps: Optional[int] = typer.Option(None, help="timed steps per size (default: by size)"),
    stacked_max_n: int = typer.Option(25, help="largest n for the stacked reference"),
):
    """Median ms per filter step (predict + update, one filter), fast form vs stacked reference."""
    from .bench import bench_filter, machine_info
    from .outputs import write_json

    sizes = [int(s) for s in sats.split(",") if s.strip()]
    rows = bench_filter(sizes, graph, steps, stacked_max_n, log=lambda s: console.print(s, highlight=False))
    write_json(out, rows)
    write_json(out.with_suffix(".meta.json"), machine_info())
    console.print(f"wrote {out}")


@bench_app.command("bus")
def bench_bus_cmd(
    out: Path = typer.Option(Path("bench-bus.json"), "--out", "-o", help="JSON file to write"),
    samples: int = typer.Option(400, help="round trips of each measurement batch"),
    batch_sats: str = typer.Option("10,40", "--batch-sats", help="swarm sizes whose measurement batch to send"),
):
    """Bus latency p50/p99 of measurement batches and of a 1 MB payload (loopback, via a router),
    and the CPU cost of encoding and decoding a batch."""
    from .bench import machine_info
    from .bench_bus import bench_latency
    from .outputs import write_json

    sizes = [int(x) for x in batch_sats.split(",") if x.strip()]
    rows = bench_latency(samples=samples, log=lambda s: console.print(s, highlight=False), batch_sizes=sizes)
    write_json(out, {"machine": machine_info(), "rows": rows})
    console.print(f"wrote {out}")


@bench_app.command("run")
def bench_run_cmd(
    sats: str = typer.Option("5,10", help="comma-separated swarm sizes"),
    duration: float = typer.Option(60.0, help="simulated seconds per run"),
    out: Path = typer.Option(Path("bench-run.json"), "--out", "-o", help="JSON file to write"),
):
    """Real-time factor of `swarm run` in lockstep (synthetic measurements, complete graph)."""
    from .bench import machine_info
    from .bench_bus import bench_realtime
    from .outputs import write_json

    sizes = [int(s) for s in sats.split(",") if s.strip()]
    rows = bench_realtime(sizes, duration, log=lambda s: console.print(s, highlight=False), workdir=out.parent / (out.stem + "-runs"))
    write_json(out, {"machine": machine_info(), "rows": rows})
    console.print(f"wrote {out}")


@app.command()
def compare(
    scenario: Path = typer.Argument(..., help="scenario YAML file (e.g. scenarios/selection.yaml)"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for compare.json, compare.md and heatmap_<strategy>.png"),
    runs: int = typer.Option(10, "--runs", "-r", min=1, help="paired runs per strategy (run i has seed S + i)"),
    strategies: str = typer.Option(
        "complete,random,random_tree,greedy,swarm_greedy,fast_swarm_greedy,logdet_greedy", help="comma-separated selection strategies"
    ),
    workers: int = typer.Option(2, "--workers", "-w", min=1, help="parallel worker processes"),
    seed: Optional[int] = typer.Option(None, help="base seed S (default: the scenario's)"),
    sets: Optional[List[str]] = SetOpt,
):
    """Paired comparison of selection strategies over the same seeds (dissertation Table 6.1, Figure 6.3).

    Writes OUT/compare.json, OUT/compare.md (per-run table, ratios, paired wins) and one
    heat map per strategy of how often each (observer, target) pair was chosen.
    """
    from swarmcore.selection import STRATEGIES

    from .compare import METRICS, run_compare

    sc = _load(scenario, sets)
    names = [s.strip() for s in strategies.split(",") if s.strip()]
    bad = [s for s in names if s not in STRATEGIES]
    if bad or not names:
        console.print(f"[red]error:[/red] --strategies: unknown {bad}; expected some of {list(STRATEGIES)}", highlight=False)
        raise typer.Exit(2)
    with _progress() as prog:
        task = prog.add_task(f"compare {sc.name} {len(names)}×{runs}", total=len(names) * runs)
        res = run_compare(sc, runs, out, strategies=names, seed=seed, workers=workers, progress=lambda k, K: prog.update(task, completed=k))
    t = Table(title=f"{sc.name}: n={sc.n_sats}, budget {sc.selection.budget}, {runs} paired runs (mean)")
    t.add_column("strategy")
    for key, _ in METRICS:
        t.add_column(key, justify="right")
    t.add_column("att/random", justify="right")
    t.add_column("pos/random", justify="right")
    t.add_column("select ms", justify="right")
    for s in names:
        sm = res["summary"][s]
        ratios = [f"{sm[k]['vs_random']['ratio_of_means']:.3f}" if "vs_random" in sm[k] else "—" for k in ("att_full", "pos_full")]
        t.add_row(s, *[f"{sm[k]['mean']:.3g}" for k, _ in METRICS], *ratios, f"{sm['select_ms_median']:.2f}")
    console.print(t)
    console.print(f"wrote {out / 'compare.md'}, {out / 'compare.json'} and {len(names)} heat maps")


@bench_app.command("selection")
def bench_selection_cmd(
    sats: str = typer.Option("10,50", help="comma-separated swarm sizes"),
    budgets: str = typer.Option("5", help="comma-separated budgets m"),
    strategies: str = typer.Option(
        "complete,random,random_tree,greedy,swarm_greedy,fast_swarm_greedy,logdet_greedy", help="comma-separated selection strategies"
    ),
    scenario: Optional[Path] = typer.Option(Path("scenarios/selection.yaml"), help="base scenario (n_sats is overridden; the cube grows as n^(1/3))"),
    reps: Optional[int] = typer.Option(None, help="timed steps per case (default: 30 for n ≤ 20, else 10)"),
    out: Path = typer.Option(Path("bench-selection.json"), "--out", "-o", help="JSON file to write"),
    sets: Optional[List[str]] = SetOpt,
):
    """Median ms per selection step (select_for_scenario) per swarm size, budget and strategy."""
    from .bench_selection import bench_selection

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


@app.command()
def characterize(
    pipeline: str = typer.Option(..., "--pipeline", help="mono or stereo"),
    out: Path = typer.Option(..., "--out", "-o", help="folder for the JSON table and the Figure 5.7 plots"),
    scenario: Optional[Path] = typer.Option(None, help="take cameras, lighting and noise from this scenario's vision section"),
    sets: Optional[List[str]] = SetOpt,
    ranges: str = typer.Option("3,6,9,12,15,18,21,24,27,30,33", help="comma-separated ranges (m)"),
    orientations: int = typer.Option(6, min=1, help="target attitudes (Fibonacci sphere; the dissertation: 20)"),
    suns: int = typer.Option(6, min=1, help="Sun directions (Fibonacci sphere; the dissertation: 20)"),
    illumination: str = typer.Option("solar,global", help="solar (Sun only) and/or global (Sun + ambient)"),
    seed: int = typer.Option(0, help="seed of the Monte Carlo draws"),
):
    """Monte Carlo error characterisation of a pose pipeline (range × attitude × Sun).

    Writes OUT/characterization-<pipeline>-<W>x<H>-f<focal>.json (usable as
    vision.covariance.table) and OUT/fig5_7_<pipeline>.png, OUT/success_<pipeline>.png.
    """
    if pipeline not in ("mono", "stereo"):
        console.print("[red]error:[/red] --pipeline must be mono or stereo")
        raise typer.Exit(2)
    from swarmvision.characterize import run_cli

    with _progress() as prog:
        task = prog.add_task(f"characterize {pipeline}", total=None)
        run_cli(
            pipeline,
            out,
            scenario=scenario,
            sets=sets or (),
            ranges=[float(x) for x in ranges.split(",") if x.strip()],
            orientations=orientations,
            suns=suns,
            illuminations=[x.strip() for x in illumination.split(",") if x.strip()],
            seed=seed,
            log=lambda s: console.print(s, highlight=False),
            progress=lambda k, K: prog.update(task, completed=k, total=K),
        )


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
    from swarmvision.bench import bench_vision, scenario_rtf

    from .bench import machine_info
    from .outputs import write_json

    def log(s):
        console.print(s, highlight=False)

    res = bench_vision(repeats=repeats, log=log)
    paths = [Path(p) for p in scenarios.split(",") if p.strip()]
    res["scenarios"] = scenario_rtf(paths, steps, log=log) if paths else []
    res["machine_info"] = machine_info()
    write_json(out, res)
    console.print(f"wrote {out}")


@scenario_app.command("show")
def scenario_show(
    scenario: Optional[Path] = typer.Argument(None, help="scenario YAML (default: all defaults)"),
    sets: Optional[List[str]] = SetOpt,
):
    """Print the fully resolved scenario (every default filled in) as YAML."""
    import yaml

    sc = _load(scenario, sets)
    sys.stdout.write(yaml.safe_dump(sc.model_dump(mode="json"), sort_keys=False))


@scenario_app.command("schema")
def scenario_schema():
    """Print the scenario JSON schema (field names, types, units, defaults)."""
    from swarmcore.scenario import Scenario

    sys.stdout.write(json.dumps(Scenario.model_json_schema(), indent=2) + "\n")


def main() -> None:  # console-script entry point
    app()


if __name__ == "__main__":
    main()
