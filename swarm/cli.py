"""``swarm``: the command line of the cooperative-localisation emulator.

Every command that takes a SCENARIO accepts ``--set dotted.key=value`` (repeatable) to
override any field, e.g. ``--set n_sats=6 --set filter.gate.enabled=false``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

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
ClusterOpt = typer.Option(
    None,
    "--cluster",
    envvar="SWARM_CLUSTER",
    help="run the study's tasks on the Dask scheduler at this address (tcp://HOST:8786) instead of the local "
    "pool; --workers is then ignored",
)
ResumeOpt = typer.Option(False, "--resume", help="keep the finished runs in OUT/results.jsonl and run only the others")


def _load(path: Path | None, sets, seed=None):
    try:
        return load_scenario(path, sets or (), seed)
    except ScenarioError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None


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


def _study(fn, *args, **kw):
    """Run a study function; a Dask scheduler that cannot be reached is a usage error (2)."""
    from .executor import ClusterError

    try:
        return fn(*args, **kw)
    except ClusterError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None


def _report_failed(rows: list[tuple[str, str]], what: str, out: Path, header: str) -> None:
    """Print the failed runs (label, error) and exit 1: the study finished the others."""
    if not rows:
        return
    t = Table(title=f"failed {what}: {len(rows)}")
    t.add_column(header)
    t.add_column("error")
    for label, err in rows:
        t.add_row(label, err)
    console.print(t)
    console.print(f"[red]failed {what}: {len(rows)}[/red]; the others finished and are in {out} "
                  "(run again with --resume to retry only the failed ones)", highlight=False)
    raise typer.Exit(1)


def _force_progress() -> bool:
    import os

    return os.environ.get("SWARM_PROGRESS", "") == "1"


def number(x, spec: str = ".3g") -> str:
    """A value for a table: "no data" rather than nan (:func:`swarm.outputs.number`)."""
    from .outputs import number as fmt

    return fmt(x, spec)


def _summary_table(summary: dict, title: str) -> Table:
    from .outputs import NO_DATA, no_data_reason

    t = Table(title=title)
    t.add_column("error (time RMS)")
    t.add_column("self att [rad]", justify="right")
    t.add_column("self pos [m]", justify="right")
    t.add_column("others att [rad]", justify="right")
    t.add_column("others pos [m]", justify="right")
    for key, label in (("rms", "full run"), ("rms_second_half", "second half")):
        r = summary[key]
        t.add_row(label, *(number(r[w][u]) for w in ("self", "others") for u in ("att_rad", "pos_m")))
    if any(number(summary[key][w][u]) == NO_DATA for key in ("rms", "rms_second_half") for w in ("self", "others")
           for u in ("att_rad", "pos_m")):
        t.caption = f"{NO_DATA}: {no_data_reason(summary)}"
    return t


def _links_table(summary: dict) -> Table | None:
    """The radio in one table (runs with links): what became of the copies sent, the
    latency of the delivered ones and what the filters did with the late ones."""
    lk = summary.get("links")
    if not lk:
        return None
    tot, lat, late = lk["totals"], lk.get("latency_s"), summary.get("late") or {}
    t = Table(title="links (all directed links)")
    for col in ("sent", "delivered", "late", "lost", "dropped (queue)", "unreachable", "kB delivered", "latency mean / p95 [s]",
                "late used / dropped / replayed"):
        t.add_column(col, justify="right")
    t.add_row(
        *(str(tot[k]) for k in ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")),
        f"{tot['bytes_delivered'] / 1e3:.1f}",
        f"{lat['mean']:.3g} / {lat['p95']:.3g}" if lat else "—",
        f"{late.get('used', 0)} / {late.get('dropped', 0)} / {late.get('replayed_steps', 0)}",
    )
    return t


@app.command()
def sim(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder to write"),
    seed: int | None = typer.Option(None, help="override the scenario seed"),
    sets: list[str] | None = SetOpt,
    arrays: bool = typer.Option(True, help="write truth.npz and estimates.npz"),
    measurements: bool = typer.Option(
        False, "--measurements", help="rendered scenarios: also write OUT/measurements.npz (every vision "
        "measurement's camera-frame error, the variances attached, what the error model read) and their "
        "normalised statistics and autocorrelation in summary.json (measurement_residuals)"),
):
    """Run every satellite's filter in this process (fast, no bus).

    Writes OUT/summary.json, OUT/truth.npz, OUT/estimates.npz and OUT/scenario.yaml.
    """
    from .models import simulate_scenario
    from .outputs import write_run

    sc = _load(scenario, sets, seed)
    records: list | None = [] if measurements and sc.vision.pipeline != "none" else None
    with _progress() as prog:
        task = prog.add_task(f"sim {sc.name} n={sc.n_sats}", total=sc.steps)
        res = simulate_scenario(sc, progress=lambda k, K: prog.update(task, completed=k), measurements=records)
    extra = None
    if records is not None:
        from swarmvision.residuals import residuals, summarize_residuals, write_residuals

        rr = residuals(records, res.truth, res.t, sc.orbit.mean_motion_rad_s)
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
    summary = write_run(res, out, arrays=arrays, extra_summary=extra)
    console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed}"))
    if (lt := _links_table(summary)) is not None:
        console.print(lt)
    console.print(
        f"NEES mean {number(summary['nees']['mean'], '.2f')} (dof 6) · gate accepted {summary['gate']['accepted']}, "
        f"rejected {summary['gate']['rejected']} · filter step median "
        f"{summary['timing']['filter_step_ms_median']:.3f} ms · wrote {out}"
    )


def _fmt3(v) -> str:
    return "/".join(f"{x:.2f}" for x in v)


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
    from .mc import run_mc

    sc = _load(scenario, sets)
    with _progress() as prog:
        task = prog.add_task(f"mc {sc.name} ×{runs}", total=runs)
        res = _study(run_mc, sc, runs, out, seed=seed, workers=workers, arrays=arrays, cluster=cluster, resume=resume,
                     progress=lambda k, K: prog.update(task, completed=k), log=lambda m: console.print(m, highlight=False))
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
def run(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder: run.mcap, summary.json, logs/"),
    seed: int | None = typer.Option(None, help="override the scenario seed"),
    sets: list[str] | None = SetOpt,
    timeout: float | None = typer.Option(None, help="stop the run after this many wall seconds"),
    routers: int = typer.Option(1, "--routers", min=1, max=2, help="Zenoh routers: 2 = two meshed routers, every role given both endpoints (fails over)"),
):
    """Run the swarm as real processes on a local Zenoh bus (router, recorder, world,
    selector, one agent per satellite) and compute summary.json from the recording.

    While it runs, `swarm fault --run-dir OUT ...` injects faults. Exit status: 0, the
    world's status, 128 + signal when interrupted, 3 when the bus was lost (no router
    within emulator.bus_lost_after_s), 4 when the world died.
    """
    from .launch import Interrupted, LocalSwarm
    from .outputs import write_json
    from .recording import load_recording

    sc = _load(scenario, sets, seed)
    try:
        swarm = LocalSwarm(sc, out, log=lambda s: console.print(s), routers=routers)
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    code: int | None = 1
    # SIGINT (Ctrl-C), SIGTERM and SIGHUP interrupt the run: every process is stopped, the
    # recording closed, and the summary of the steps recorded so far marked as interrupted.
    with swarm.handling_signals():
        try:
            swarm.start()
            console.print(f"run {swarm.run}: {sc.n_sats} agents on {swarm.endpoint}; faults: swarm fault --run-dir {out} ...")
            with _progress() as prog:
                task = prog.add_task(f"run {sc.name} n={sc.n_sats} ({sc.emulator.time_mode})", total=sc.steps)
                code = swarm.run_to_end(progress=lambda k, K: prog.update(task, completed=k), timeout=timeout)
        except Interrupted:
            code = None
        finally:
            swarm.stop()
    sig = swarm.interrupted if code is None else None
    broken = swarm.broken if sig is None else None
    if sig is None and broken is None:
        summary = load_recording(out / "run.mcap", sc.n_sats, sc.steps).summary(sc)
    else:
        summary = _interrupted_summary(out / "run.mcap", sc)
        last = _last_step(summary)
        if sig is not None:
            summary["interrupted"] = {"reason": sig.name, "signal": int(sig), "last_step": last, "steps_planned": sc.steps}
        else:
            summary["interrupted"] = {"reason": broken, "world_exit_code": code, "last_step": last, "steps_planned": sc.steps}
    # Router faults the bus could not carry (no router left to carry the report).
    known = {(f.get("action"), f.get("target"), f.get("phase")) for f in summary.get("faults", [])}
    for f in swarm.router_faults:
        if (f["action"], f["target"], f["phase"]) not in known:
            summary.setdefault("faults", []).append({k: v for k, v in f.items() if not k.endswith("_unix_s")})
    summary["run"] = swarm.run
    summary["world_exit_code"] = code
    write_json(out / "summary.json", summary)
    if summary["steps"]:
        console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed} (from the recording)"))
    if summary.get("bus_gaps"):
        for g in summary["bus_gaps"]:
            if g["duration_s"] is None:
                console.print(f"bus gap: no router reachable after step {g['last_step_before']}; it never came back", highlight=False)
            else:
                console.print(f"bus gap: {g['duration_s']:.2f} s with no router (after step {g['last_step_before']}, "
                              f"resumed at step {g['first_step_after']})", highlight=False)
        if (lt := _links_table(summary)) is not None:
            console.print(lt)
    if summary.get("faults"):
        t = Table(title="faults")
        for col in ("k", "action", "target", "phase", "sender", "detail"):
            t.add_column(col)
        for f in summary["faults"]:
            t.add_row(*(str(f.get(c, "")) for c in ("k", "action", "target", "phase", "sender", "detail")))
        console.print(t)
    wrote = [f for f in (out / "run.mcap", out / "summary.json") if f.exists()]
    console.print(f"wrote {' and '.join(map(str, wrote))}")
    if sig is not None:
        when = f"after step {summary['steps'] - 1} of {sc.steps - 1}" if summary["steps"] else "before the first step"
        console.print(
            f"[bold red]INTERRUPTED[/bold red] by {sig.name} {when}: every process stopped, the recording closed; "
            "summary.json covers the steps recorded and says \"interrupted\"",
            highlight=False,
        )
        raise typer.Exit(128 + int(sig))
    if broken is not None:
        console.print(f"[bold red]BROKEN RUN[/bold red] at step {summary['interrupted']['last_step']} of {sc.steps - 1}: {broken}; "
                      "every process stopped, the recording closed; summary.json says \"interrupted\"", highlight=False)
        from .protocol import EXIT_BUS_LOST, EXIT_WORLD_LOST

        raise typer.Exit(EXIT_BUS_LOST if code == EXIT_BUS_LOST else EXIT_WORLD_LOST)
    if code != 0:
        raise typer.Exit(code)


def _last_step(summary: dict) -> int:
    """The last step the recording holds an estimate of (or its last truth step)."""
    return int(summary.get("last_estimated_step", summary["steps"] - 1))


def _interrupted_summary(path: Path, sc) -> dict:
    """The summary of an interrupted run over the steps it recorded (0..last truth step),
    or an empty one if it never got to step 0."""
    from .recording import load_recording

    try:
        return load_recording(path, sc.n_sats, None).summary(sc)  # K from the recorded truth
    except (ValueError, FileNotFoundError) as exc:
        console.print(f"no step to summarise: {exc}", highlight=False)
        return {"scenario": sc.name, "n_sats": sc.n_sats, "seed": sc.seed, "steps": 0, "faults": []}


fault_app = typer.Typer(
    help="Inject faults into a running swarm: `swarm fault --run-dir DIR kill-agent 2` (local, "
    "from `swarm run --out DIR`) or `swarm fault --compose kill-agent 2` (docker compose).",
    no_args_is_help=True,
)
app.add_typer(fault_app, name="fault")


@fault_app.callback()
def fault_target(
    ctx: typer.Context,
    run_dir: Path | None = typer.Option(None, "--run-dir", help="the run folder of `swarm run` (has run.json)"),
    compose: bool = typer.Option(False, "--compose", help="the swarm of `docker compose up` (docker CLI for process and network faults)"),
    connect: str | None = typer.Option(None, "--connect", help="bus endpoint (default with --compose: tcp/127.0.0.1:$SWARM_BUS_PORT or 7447)"),
    run_id: str | None = typer.Option(None, "--run", help="run id (default with --compose: $SWARM_RUN or 'compose')"),
    project: str | None = typer.Option(None, "--project", help="compose project name (default: any)"),
    network: str | None = typer.Option(None, "--network", help="compose bus network for partition/heal (default: *_bus)"),
    credential: str | None = typer.Option(None, "--credential", help="the fault CLI's credential (default: the run's keys with "
                                          "--run-dir, else $SWARM_KEYS/cli.json, SWARM_KEYS defaulting to ./keys)"),
):
    """Where the swarm is."""
    ctx.obj = dict(run_dir=run_dir, compose=compose, connect=connect, run_id=run_id, project=project, network=network,
                   credential=credential)


def _send_fault(ctx: typer.Context, **fields):
    from .faults import send_fault

    try:
        result = send_fault(**ctx.obj, **fields)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
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


@fault_app.command("kill-router")
def fault_kill_router(ctx: typer.Context, router: int = typer.Argument(0, help="the router's index (0; 0 or 1 with --routers 2)")):
    """SIGKILL a Zenoh router (`docker kill` under compose). With one router the bus is gone:
    the run pauses, and ends broken after emulator.bus_lost_after_s; with two, clients fail over."""
    _send_fault(ctx, action="kill-router", target=router)


@fault_app.command("restart-router")
def fault_restart_router(
    ctx: typer.Context,
    router: int = typer.Argument(0, help="the router's index (0; 0 or 1 with --routers 2)"),
    down_s: float = typer.Option(0.0, "--down-s", min=0.0, max=3600.0, help="wall seconds the router stays down"),
):
    """Kill a Zenoh router and start a new one on the same endpoint (`docker restart`
    under compose); every role reconnects and the run goes on where it was."""
    _send_fault(ctx, action="restart-router", target=router, down_s=down_s)


@fault_app.command("drop")
def fault_drop(ctx: typer.Context, sat: int, rate: float = typer.Option(..., "--rate", min=0.0, max=1.0, help="fraction of SAT's outgoing messages lost")):
    """Lose a fraction of satellite SAT's outgoing measurement batches and estimates.

    The agent makes the draws (seeded by satellite, step and message); its report says
    from which step, and the world's radio, knowing the same draws, never waits for a
    batch that was lost."""
    _send_fault(ctx, action="drop", target=sat, rate=rate)


@fault_app.command("partition")
def fault_partition(ctx: typer.Context, sat: int):
    """Cut satellite SAT's container off the bus network (compose only)."""
    _send_fault(ctx, action="partition", target=sat)


@fault_app.command("heal")
def fault_heal(ctx: typer.Context, sat: int):
    """Reconnect satellite SAT's container to the bus network (compose only)."""
    _send_fault(ctx, action="heal", target=sat)


@fault_app.command("netem")
def fault_netem(
    ctx: typer.Context,
    sat: int,
    clear: str | None = typer.Argument(None, metavar="[clear]", help="'clear' removes the impairment"),
    delay: str | None = typer.Option(None, "--delay", help="one-way delay added to what SAT sends, e.g. 200ms (s, ms, us)"),
    jitter: str | None = typer.Option(None, "--jitter", help="± spread around the delay (uniform), e.g. 50ms"),
    loss: str | None = typer.Option(None, "--loss", help="packets lost, e.g. 10%"),
    rate: str | None = typer.Option(None, "--rate", help="egress rate cap, e.g. 1mbit (bit, kbit, mbit, gbit; bps = bytes/s)"),
):
    """Impair satellite SAT's network with Linux traffic control (compose only): `netem 3
    --delay 200ms --jitter 50ms --loss 10% --rate 1mbit`, or `netem 3 clear`."""
    from .netem import CLEAR, Netem, NetemError

    try:
        if clear is not None:
            if clear != CLEAR:
                raise NetemError(f"unexpected argument {clear!r}: the only word after SAT is 'clear'")
            if any(v is not None for v in (delay, jitter, loss, rate)):
                raise NetemError("'clear' takes no --delay, --jitter, --loss or --rate")
            args = CLEAR
        else:
            args = Netem.from_cli(delay, jitter, loss, rate).args()
    except NetemError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    _send_fault(ctx, action="netem", target=sat, netem=args)


@app.command()
def keys(
    out: Path = typer.Option(Path("keys"), "--out", "-o", help="keys directory to make (owner-only; keep it out of version control)"),
    n_sats: int = typer.Option(100, "--n-sats", min=1, max=10_000, help="make agent credentials agent-0 .. agent-(N-1)"),
    tls: list[str] | None = typer.Option(None, "--tls", help="host name or address agents use to reach the router: the "
                                         "router's certificate is valid for these (repeatable; default: router, localhost, "
                                         "127.0.0.1, what compose and compose.remote.yaml use)"),
    no_tls: bool = typer.Option(False, "--no-tls", help="no CA and router certificate (one host, no compose)"),
    rules: str | None = typer.Option(None, "--rules", metavar="RUN", help="print the router's access rules for run RUN "
                                     "(of --n-sats satellites) as JSON, and make nothing"),
    force: bool = typer.Option(False, "--force", help="replace the credentials of an existing keys directory"),
):
    """Credentials for a swarm on several hosts or under compose: one per identity (world,
    selector, recorder, cli, supervisor, observer, claimant, agent-0..N-1), the router's
    password dictionary and, with --tls, certificates. `swarm run` makes its own per run.

    docker compose reads ./keys (SWARM_KEYS moves it): `swarm keys` once (TLS for router,
    localhost, 127.0.0.1), then `docker compose up`."""
    from .security import acl_config, make_keys

    if rules is not None:
        typer.echo(json.dumps(acl_config(rules, n_sats), indent=1))
        return
    if (out / "passwords").exists() and not force:
        console.print(f"[red]error:[/red] {out} already holds keys (--force replaces them; running swarms keep the old ones)",
                      highlight=False)
        raise typer.Exit(2)
    hosts = [] if no_tls else list(tls or ["router", "localhost", "127.0.0.1"])
    try:
        make_keys(out, n_sats, tls_hosts=hosts)
    except RuntimeError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    console.print(f"wrote {out}: credentials of {n_sats} agents and the other roles"
                  + (f", a CA and a router certificate for {', '.join(hosts)}" if hosts else ""), highlight=False)


@app.command()
def recover(recording: Path = typer.Argument(..., help="a damaged MCAP file"), out: Path | None = typer.Option(None, "--out")):
    """Salvage every complete message of a damaged recording into a clean MCAP."""
    from .mcaplog import recover as _recover

    n = _recover(recording, out)
    console.print(f"recovered {n} messages")


@app.command()
def report(
    run: Path = typer.Argument(..., help="a run folder (swarm sim / swarm run), an MCAP file, or a Monte Carlo / comparison / links-study folder"),
    out: Path | None = typer.Option(None, "--out", "-o", help="folder for the figures and report.html (default: RUN/report)"),
):
    """Figures and one self-contained HTML page: errors against ±3σ per filter, NEES with
    its χ² band, gate rejections, the measurement schedule, faults on every time axis; with
    links, the link table, latencies, per-step link events, queues and late measurements."""
    from .report import make_report

    try:
        page = make_report(run, out)
    except (FileNotFoundError, ValueError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    console.print(f"wrote {page} ({len(list(page.parent.glob('*.png')))} figures)")


@bench_app.command("filter")
def bench_filter_cmd(
    sats: str = typer.Option("3,6,12,25,50,100", help="comma-separated swarm sizes"),
    graph: str = typer.Option("complete", help="complete, star, chain or duplex_chain"),
    out: Path = typer.Option(Path("bench-filter.json"), "--out", "-o", help="JSON file to write"),
    steps: int | None = typer.Option(None, help="timed steps per size (default: by size)"),
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


@bench_app.command("late")
def bench_late_cmd(
    n: int = typer.Option(10, "--sats", help="swarm size"),
    history_s: float = typer.Option(10.0, help="filter.history_s of the replaying agent"),
    lags: str = typer.Option("0,1,2,5,10", help="comma-separated lateness of every peer batch (steps)"),
    out: Path = typer.Option(Path("bench-late.json"), "--out", "-o", help="JSON file to write"),
):
    """ms per filter step when every peer batch arrives late and is replayed (filter.late: replay)."""
    from .bench import bench_late, machine_info
    from .outputs import write_json

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
    from .bench import machine_info
    from .bench_bus import bench_latency
    from .outputs import write_json

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
    from .bench import machine_info
    from .bench_router import bench_router
    from .outputs import write_json

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
):
    """Real-time factor of `swarm run` in lockstep (synthetic measurements, complete graph)."""
    from .bench import machine_info
    from .bench_bus import bench_realtime
    from .outputs import write_json

    sizes = [int(s) for s in sats.split(",") if s.strip()]
    rows = bench_realtime(sizes, duration, log=lambda s: console.print(s, highlight=False), workdir=out.parent / (out.stem + "-runs"),
                          security=_security_modes(security))
    write_json(out, {"machine": machine_info(), "rows": rows})
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
    from .bench import machine_info
    from .bench_cluster import bench_cluster
    from .outputs import write_json

    sc = _load(scenario, sets)
    res = bench_cluster(sc, runs=runs, workers=workers, noop_tasks=noop_tasks, repeats=repeats,
                        log=lambda s: console.print(s, highlight=False))
    write_json(out, {"machine": machine_info(), **res})
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
        res = _study(run_compare, sc, runs, out, strategies=names, seed=seed, workers=workers, cluster=cluster, resume=resume,
                     progress=lambda k, K: prog.update(task, completed=k), log=lambda m: console.print(m, highlight=False))
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
    selection under the cap (paired seeds). The sweep is defined in swarm/links_study.py
    (DEFAULT_SWEEP, FULL_SWEEP); the options replace parts of it.

    Writes OUT/links_study.md (the table), OUT/links_study.json and latency.png, loss.png, cap.png.
    """
    from dataclasses import replace

    from .links_study import DEFAULT_SWEEP, FULL_SWEEP, METRICS, run_links_study

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
    from .executor import ResultStore, StudyMapper, open_executor

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


@bench_app.command("selection")
def bench_selection_cmd(
    sats: str = typer.Option("10,50", help="comma-separated swarm sizes"),
    budgets: str = typer.Option("5", help="comma-separated budgets m"),
    strategies: str = typer.Option(
        "complete,random,random_tree,greedy,swarm_greedy,fast_swarm_greedy,logdet_greedy", help="comma-separated selection strategies"
    ),
    scenario: Path | None = typer.Option(Path("scenarios/selection.yaml"), help="base scenario (n_sats is overridden; the cube grows as n^(1/3))"),
    reps: int | None = typer.Option(None, help="timed steps per case (default: 30 for n ≤ 20, else 10)"),
    out: Path = typer.Option(Path("bench-selection.json"), "--out", "-o", help="JSON file to write"),
    sets: list[str] | None = SetOpt,
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
    scenario: Path | None = typer.Option(None, help="take cameras, lighting and noise from this scenario's vision section"),
    sets: list[str] | None = SetOpt,
    ranges: str = typer.Option("3,6,9,12,15,18,21,24,27,30,33", help="comma-separated ranges (m)"),
    orientations: int = typer.Option(6, min=1, help="target attitudes (Fibonacci sphere; the dissertation: 20)"),
    suns: int = typer.Option(6, min=1, help="Sun directions (Fibonacci sphere; the dissertation: 20)"),
    illumination: str = typer.Option("solar,global", help="solar (Sun only) and/or global (Sun + ambient)"),
    seed: int = typer.Option(0, help="seed of the Monte Carlo draws"),
    workers: int = typer.Option(1, "--workers", "-w", min=1, help="parallel worker processes (each renders on its own)"),
    cluster: str | None = ClusterOpt,
    resume: bool = ResumeOpt,
):
    """Monte Carlo error characterisation of a pose pipeline (range × attitude × Sun).

    Writes OUT/characterization-<pipeline>-<W>x<H>-f<focal>.json (usable as
    vision.covariance.table) and OUT/fig5_7_<pipeline>.png, OUT/success_<pipeline>.png.
    The work is cut into cells (one illumination at one range) that run in this process,
    in --workers processes or on a Dask cluster; each cell's samples are appended to
    OUT/results.jsonl as it finishes. A failed cell is listed with its error, the table is
    written without it ("missing_cells"), and the exit status is 1.
    """
    if pipeline not in ("mono", "stereo"):
        console.print("[red]error:[/red] --pipeline must be mono or stereo")
        raise typer.Exit(2)
    from swarmvision.characterize import run_cli

    from .executor import ResultStore, StudyMapper, open_executor

    def log(m):
        console.print(m, highlight=False)

    vision = None
    if scenario is not None:
        from swarmvision.characterize import flown_geometry

        sc = _load(scenario, sets)
        vision = sc.vision
        fg = flown_geometry(sc)
        log(f"{sc.name} flies ranges {fg['range_m'][0]:.1f}–{fg['range_m'][2]:.1f} m (median {fg['range_m'][1]:.1f}), "
            f"Sun angles {fg['sun_deg'][0]:.0f}–{fg['sun_deg'][2]:.0f}°: the design should cover them")
    store = ResultStore(out / "results.jsonl", resume=resume)
    try:
        with _study(open_executor, workers, cluster) as ex, _progress() as prog:
            mapper = StudyMapper(ex, store, log=log)
            task = prog.add_task(f"characterize {pipeline}", total=None)
            run_cli(
                pipeline,
                out,
                vision=vision,
                ranges=[float(x) for x in ranges.split(",") if x.strip()],
                orientations=orientations,
                suns=suns,
                illuminations=[x.strip() for x in illumination.split(",") if x.strip()],
                seed=seed,
                log=log,
                progress=lambda k, K: prog.update(task, completed=k, total=K),
                mapper=mapper,
            )
    finally:
        store.close()
    _report_failed(sorted(mapper.result.errors.items()), "cells", out, "illumination@range index")


@app.command("fit-noise")
def fit_noise(
    table: Path = typer.Argument(..., help="a characterization JSON (or .json.gz) with its samples (swarm characterize "
                                 "--out DIR; shipped: swarmvision/data/*-samples.json.gz)"),
    out: Path = typer.Option(..., "--out", "-o", help="error-model JSON to write (vision.covariance.model)"),
    residuals: list[Path] | None = typer.Option(
        None, "--residuals", help="measurements.npz of runs (swarm sim --measurements): the temporal inflation τ "
        "per axis from their normalised errors' autocorrelation (repeatable)"),
    illumination: str | None = typer.Option(None, help="the samples' illumination to fit (default: the first)"),
    max_lag: int = typer.Option(10, min=1, help="longest lag of the autocorrelation (steps)"),
    window: int | None = typer.Option(
        None, min=2, help="the filter's memory W (steps): τ is the variance factor of a W-step mean "
        "(Bartlett weights) instead of the sum of the positive autocorrelations"),
    flight_scale: bool = typer.Option(
        False, "--flight-scale", help="also re-centre each axis's σ on the runs' errors (median (e/σ)² = χ²₁ median), keeping the "
        "characterisation's dependence on the features"),
):
    """Fit the log-linear measurement-noise model of a pose pipeline from characterisation
    samples (and its temporal inflation from runs' residuals); write it and its plots."""
    import json

    import numpy as np

    from swarmvision.characterize import fit_error_model, plot_error_model
    from swarmvision.residuals import read_residuals, summarize_residuals

    def log(m):
        console.print(m, highlight=False)

    try:
        raw = Path(table).read_bytes()
        if Path(table).suffix == ".gz":
            import gzip

            raw = gzip.decompress(raw)
        res = json.loads(raw)
        if "samples" not in res:
            raise ValueError(f"{table}: no samples (a shipped statistics-only table?): run swarm characterize")
        m = fit_error_model(res, illumination, log=log)
    except (OSError, ValueError, KeyError, EOFError) as e:
        console.print(f"[red]error:[/red] {table}: {e}")
        raise typer.Exit(2) from e
    ss = [s for s in res["samples"] if s.get("ok") and s.get("q") and s["illumination"] == m.meta["illumination"]]
    plots = [plot_error_model(m, [s["q"] for s in ss], np.array([s["err"] for s in ss]), out.with_name(out.stem + "-fit.png"),
                              f"{m.pipeline}: fitted error model vs characterisation errors ({len(ss)} samples)")]
    if residuals:
        from swarmvision.error_model import autocorrelation
        from swarmvision.residuals import normalised_series

        runs = [read_residuals(p) for p in residuals]
        if flight_scale:
            from swarmvision.error_model import CHI2_1_MEDIAN

            E = np.concatenate([rr["err"] for rr in runs])
            V = np.concatenate([m.var_C_single(rr["q"]) for rr in runs])
            z2 = E**2 / V
            ok = np.all(np.isfinite(z2), axis=1)
            shift = np.log(np.median(z2[ok], axis=0) / CHI2_1_MEDIAN)
            m.coef[:, 0] += shift
            m.min_var = m.min_var * np.exp(shift)
            m.max_var = m.max_var * np.exp(shift)
            m.meta["flight_scale"] = {"runs": [str(p) for p in residuals], "var_factor": np.exp(shift).tolist()}
            log(f"re-centred on the runs' errors: variance × {'/'.join(f'{x:.3g}' for x in np.exp(shift))}")
        series, per_run, allq, allE, allV = [], [], [], [], []
        for p, rr in zip(residuals, runs, strict=True):
            v = m.var_C_single(rr["q"])
            series += normalised_series(rr, v)
            st = summarize_residuals(rr, v, max_lag)
            per_run.append({"run": str(p), "n": st["n"], "mean_z2": st["mean_z2"], "median_z2": st["median_z2"],
                            "lag1": st["lag1"], "tau": st["tau"]})
            allq += rr["q"]
            allE.append(rr["err"])
            allV.append(v)
        ac = autocorrelation(series, max_lag, window)
        m.temporal_inflation = np.maximum(np.asarray(ac["tau"]), 1.0)
        m.meta["temporal"] = {"runs": per_run, "lag1": ac["lag1"], "tau": ac["tau"], "max_lag": max_lag, "window": window,
                              "rho": ac["rho"]}
        log("in flight, normalised by the fitted σ (one measurement alone): " + "; ".join(
            f"{r['run']}: n {r['n']}, mean (e/σ)² {'/'.join(f'{x:.2f}' for x in r['mean_z2'])}" for r in per_run))
        log(f"lag-1 autocorrelation {'/'.join(f'{x:.2f}' for x in ac['lag1'])} → temporal inflation τ "
            f"{'/'.join(f'{x:.2f}' for x in m.temporal_inflation)}")
        plots.append(plot_error_model(m, allq, np.concatenate(allE), out.with_name(out.stem + "-flight.png"),
                                      f"{m.pipeline}: fitted error model (one measurement) vs errors in flight", var=np.concatenate(allV)))
    m.write(out)
    log(f"wrote {out} and {', '.join(map(str, plots))}")


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
    res["scenarios"] = scenario_rtf([(p, _load(p, None)) for p in paths], steps, log=log) if paths else []
    res["machine_info"] = machine_info()
    write_json(out, res)
    console.print(f"wrote {out}")


@scenario_app.command("show")
def scenario_show(
    scenario: Path | None = typer.Argument(None, help="scenario YAML (default: all defaults)"),
    sets: list[str] | None = SetOpt,
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
