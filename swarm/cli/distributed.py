"""The distributed swarm: ``run``, ``fault``, ``keys``, ``recover``, ``report``."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from swarm.cli.common import SetOpt, _links_table, _load, _progress, _summary_table, app, console, fault_app


@app.command()
def run(
    scenario: Path = typer.Argument(..., help="scenario YAML file"),
    out: Path = typer.Option(..., "--out", "-o", help="run folder: run.mcap, summary.json, logs/"),
    seed: int | None = typer.Option(None, help="override the scenario seed"),
    sets: list[str] | None = SetOpt,
    timeout: float | None = typer.Option(None, help="stop the run after this many wall seconds"),
    routers: int = typer.Option(1, "--routers", min=1, max=2, help="Zenoh routers: 2 = two meshed routers, every role given both endpoints (fails over)"),
    agents: list[str] | None = typer.Option(
        None, "--agent", metavar="I=COMMAND", help="satellite I flown by COMMAND, a program of any language instead of the "
        "Python sat_agent (repeatable; docs/agent-contract.md says what it is given and owes)"),
    live: str | None = typer.Option(
        None, "--live", metavar="[HOST:PORT]", help="serve the live 3-D view (Foxglove WebSocket protocol) at HOST:PORT; "
        "--live alone: 127.0.0.1:8765. Open it in Foxglove with docs/foxglove-layout.json"),
    cluster: str | None = typer.Option(
        None, "--cluster", metavar="ray://HOST:PORT|local-ray[:N]", help="run over a Ray cluster: ray://HOST:PORT is the head's "
        "Ray Client address (ray start --head; port 10001), local-ray[:N] starts N nodes here for the run (each in a network "
        "namespace of its own as root). A Zenoh router per node; docs/cluster.md"),
):
    """Run the swarm as real processes on a local Zenoh bus (router, recorder, world,
    selector, one agent per satellite) and compute summary.json from the recording.

    While it runs, `swarm fault --run-dir OUT ...` injects faults, and with --live Foxglove
    shows it (ws://HOST:PORT). Exit status: 0, the world's status, 128 + signal when
    interrupted, 3 when the bus was lost (no router within emulator.bus_lost_after_s), 4
    when the world died, 5 when an agent left by itself (not by a fault) before the end.
    """
    from swarm.api import run as run_swarm

    sc = _load(scenario, sets, seed)
    if agents:
        sc = _with_agent_commands(sc, agents)
    if live is not None:
        live = _check_live_address(live)
    if (why := sc.vision.distributed_refusal()) is not None:
        console.print(f"[red]error:[/red] {why}", highlight=False)
        raise typer.Exit(2)
    if cluster is not None:
        from swarm.cluster.swarm import parse_cluster

        try:
            parse_cluster(cluster)
            if live is not None or routers != 1:
                raise ValueError("--cluster runs a router per node (no --routers) and has no live view yet (no --live)")
        except ValueError as exc:
            console.print(f"[red]error:[/red] {exc}", highlight=False)
            raise typer.Exit(2) from None

    def started(swarm) -> None:
        console.print(f"run {swarm.run}: {sc.n_sats} agents on {swarm.endpoint}; faults: swarm fault --run-dir {out} ...")
        if live is not None:
            _print_live(out)

    # SIGINT (Ctrl-C), SIGTERM and SIGHUP interrupt the run: every process is stopped, the
    # recording closed, and the summary of the steps recorded so far marked as interrupted.
    with _progress() as prog:
        task = prog.add_task(f"run {sc.name} n={sc.n_sats} ({sc.emulator.time_mode})", total=sc.steps)
        try:
            result = run_swarm(sc, out=out, live=live, timeout=timeout, routers=routers,
                               progress=lambda k, K: prog.update(task, completed=k),
                               log=lambda s: console.print(s, highlight=False), on_start=started, cluster=cluster)
        except _cluster_errors() as exc:
            console.print(f"[red]error:[/red] {exc}", highlight=False)
            raise typer.Exit(2) from None
    res = result.outcome
    assert res is not None
    summary = res.summary
    if summary["steps"]:
        console.print(_summary_table(summary, f"{sc.name}: n={sc.n_sats}, {summary['steps']} steps, seed {sc.seed} (from the recording)"))
    for g in summary.get("bus_gaps") or []:
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
    if res.signal is not None:
        when = f"after step {summary['steps'] - 1} of {sc.steps - 1}" if summary["steps"] else "before the first step"
        console.print(
            f"[bold red]INTERRUPTED[/bold red] by {res.signal.name} {when}: every process stopped, the recording closed; "
            "summary.json covers the steps recorded and says \"interrupted\"",
            highlight=False,
        )
    elif res.broken is not None:
        console.print(f"[bold red]BROKEN RUN[/bold red] at step {summary['interrupted']['last_step']} of {sc.steps - 1}: {res.broken}; "
                      "every process stopped, the recording closed; summary.json says \"interrupted\"", highlight=False)
    if res.exit_code != 0:
        raise typer.Exit(res.exit_code)


def _cluster_errors() -> tuple[type[BaseException], ...]:
    """What a cluster run raises when the cluster cannot run it (one line each)."""
    from swarm.cluster.netns import NetnsError
    from swarm.cluster.versions import ClusterError

    return (ClusterError, NetnsError)


def _check_live_address(text: str) -> str:
    """``HOST:PORT`` checked (and the port free, unless 0), or exit 2 saying why."""
    import socket

    from swarm.live import parse_address

    try:
        host, port = parse_address(text)
    except ValueError as exc:
        console.print(f"[red]error:[/red] --live {exc}", highlight=False)
        raise typer.Exit(2) from None
    if port:
        try:
            family = socket.AF_INET6 if ":" in host else socket.AF_INET
            with socket.socket(family, socket.SOCK_STREAM) as s:
                s.bind((host, port))
        except OSError as exc:
            console.print(f"[red]error:[/red] --live {text}: cannot serve there ({exc.strerror}); try another port, or "
                          "--live 127.0.0.1:0 for any free one", highlight=False)
            raise typer.Exit(2) from None
    return text


def _print_live(out: Path) -> None:
    info = out / "live.json"
    try:
        url = json.loads(info.read_text())["url"]
    except (OSError, ValueError, KeyError):
        console.print(f"[yellow]live view: not serving[/yellow] (see {out / 'logs' / 'live.log'}); the run goes on", highlight=False)
        return
    layout = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"
    console.print(f"live view: {url} — in Foxglove: Open connection → Foxglove WebSocket → {url}; layout: "
                  f"{layout if layout.exists() else 'swarm live layout'}", highlight=False)


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
    from swarm.supervise.faults import send_fault

    try:
        result = send_fault(**ctx.obj, **fields)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    typer.echo(result)


def _sat_fault(action: str, doc: str) -> None:
    """``swarm fault ACTION SAT``: a fault that takes nothing but its satellite (``doc``: its help)."""

    def command(ctx: typer.Context, sat: int) -> None:
        _send_fault(ctx, action=action, target=sat)

    command.__doc__ = doc
    command.__name__ = "fault_" + action.replace("-", "_")
    fault_app.command(action)(command)


# (Registered in the order `swarm fault --help` lists them.)
_sat_fault("kill-agent", "SIGKILL satellite SAT's agent. Its satellite keeps flying and being seen.")
_sat_fault("stop-agent", "Stop satellite SAT's agent cleanly (SIGTERM; `docker stop` under compose).")
_sat_fault("restart-agent", "Start a new agent for SAT; it initialises from a live peer's estimate.")


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


_STALL_HELP = ("wall seconds the process stays stopped; past the Zenoh lease (10 s) its router drops its session: a world "
               "or router stall is survived, an agent's, the selector's or the recorder's breaks the run (exit 5)")


@fault_app.command("stall-agent")
def fault_stall_agent(ctx: typer.Context, sat: int,
                      down_s: float = typer.Option(..., "--down-s", min=0.001, max=3600.0, help=_STALL_HELP)):
    """Stop satellite SAT's agent (SIGSTOP; `docker pause` under compose) for --down-s
    seconds, then continue it: a stall, not a death (a VM pause, a long GC, a starved CPU)."""
    _send_fault(ctx, action="stall-agent", target=sat, down_s=down_s)


def _role_stall(role: str) -> None:
    def command(ctx: typer.Context, down_s: float = typer.Option(..., "--down-s", min=0.001, max=3600.0, help=_STALL_HELP)):
        _send_fault(ctx, action=f"stall-{role}", down_s=down_s)

    command.__doc__ = (f"Stop the {role} (SIGSTOP; `docker pause` under compose) for --down-s seconds, then continue it.")
    command.__name__ = f"fault_stall_{role}"
    fault_app.command(f"stall-{role}")(command)


_role_stall("world")
_role_stall("selector")
_role_stall("recorder")


@fault_app.command("stall-router")
def fault_stall_router(ctx: typer.Context, router: int = typer.Argument(0, help="the router's index (0; 0 or 1 with --routers 2)"),
                       down_s: float = typer.Option(..., "--down-s", min=0.001, max=3600.0, help=_STALL_HELP)):
    """Stop a Zenoh router (SIGSTOP; `docker pause` under compose) for --down-s seconds,
    then continue it: every client's link to it hangs instead of closing."""
    _send_fault(ctx, action="stall-router", target=router, down_s=down_s)


@fault_app.command("link")
def fault_link(
    ctx: typer.Context,
    sat: int = typer.Argument(..., help="the transmitting satellite"),
    peer: int | None = typer.Argument(None, help="the receiving satellite (none: every link of SAT, both ways)"),
    state: str | None = typer.Option(None, "--state", help="off: the link carries nothing; on: the scenario's parameters "
                                     "back (undoes every fault on it)"),
    delay_s: float | None = typer.Option(None, "--delay-s", min=0.0, max=3600.0, help="latency (s) added to its fixed latency"),
    loss: float | None = typer.Option(None, "--loss", min=0.0, max=1.0, help="its loss rate (Bernoulli) from now on"),
):
    """Impair a radio link (the world's link model; scenarios with links.enabled): `link 2 3
    --state off` (dead), `link 2 --state off` (satellite 2 cut off from the swarm), `link 2 3
    --delay-s 1.5`, `link 2 3 --loss 0.4`, `link 2 3 --state on` (as the scenario has it)."""
    if state not in (None, "on", "off") or (state is None and delay_s is None and loss is None) or \
            (state == "on" and (delay_s is not None or loss is not None)):
        console.print("[red]error:[/red] link: --state off|on, --delay-s or --loss (--state on alone)", highlight=False)
        raise typer.Exit(2)
    _send_fault(ctx, action="link", target=sat, peer=peer, state=state, delay_s=delay_s, rate=loss)


@fault_app.command("kill-node")
def fault_kill_node(ctx: typer.Context, node: int = typer.Argument(..., min=0, help="the node's index (0: the head; run.json lists them)")):
    """Take a node of a cluster run down (swarm run --cluster): its raylet and everything on it
    killed; its agents are started again on the surviving nodes (warm) and the faults table
    says where each went. Killing the node of the world or the recorder breaks the run."""
    _send_fault(ctx, action="kill-node", target=node)


@fault_app.command("partition-nodes")
def fault_partition_nodes(
    ctx: typer.Context,
    node: int = typer.Argument(..., min=0, help="a node's index"),
    peer: int = typer.Argument(..., min=0, help="the other node's index"),
    down_s: float = typer.Option(..., "--down-s", min=0.001, max=3600.0, help="wall seconds until the cut is healed"),
):
    """Cut two nodes of a local cluster run (--cluster local-ray:N as root) apart: every packet
    between their addresses dropped (iptables in their namespaces), healed --down-s later."""
    _send_fault(ctx, action="partition-nodes", target=node, peer=peer, down_s=down_s)


_sat_fault("partition", "Cut satellite SAT's container off the bus network (compose only).")
_sat_fault("heal", "Reconnect satellite SAT's container to the bus network (compose only).")


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
    from swarmrt.netem import CLEAR, Netem, NetemError

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

    docker compose uses ./keys (SWARM_KEYS moves it) and makes it on first use (TLS for
    router, localhost, 127.0.0.1); make it yourself first for other TLS names, or replace
    it with --force (the next `docker compose up` hands the new keys out)."""
    from swarmrt.security import DEFAULT_TLS_HOSTS, acl_config, make_keys

    if rules is not None:
        typer.echo(json.dumps(acl_config(rules, n_sats), indent=1))
        return
    if (out / "passwords").exists() and not force:
        console.print(f"[red]error:[/red] {out} already holds keys (--force replaces them; running swarms keep the old ones)",
                      highlight=False)
        raise typer.Exit(2)
    hosts = [] if no_tls else list(tls or DEFAULT_TLS_HOSTS)
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
    from swarm.record.mcaplog import recover as _recover

    n = _recover(recording, out)
    console.print(f"recovered {n} messages")


@app.command()
def report(
    run: Path = typer.Argument(..., help="a run folder (swarm sim / swarm run), an MCAP file, or a Monte Carlo / comparison / links-study / chaos-campaign folder"),
    out: Path | None = typer.Option(None, "--out", "-o", help="folder for the figures and report.html (default: RUN/report)"),
):
    """Figures and one self-contained HTML page: errors against ±3σ per filter, NEES with
    its χ² band, gate rejections, the measurement schedule, faults on every time axis; with
    links, the link table, latencies, per-step link events, queues and late measurements;
    for a chaos campaign's folder, its faults, recovery times and invariants first."""
    from swarm.studies.report import make_report

    try:
        page = make_report(run, out)
    except (FileNotFoundError, ValueError) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    console.print(f"wrote {page} ({len(list(page.parent.glob('*.png')))} figures)")


def _with_agent_commands(sc, specs: list[str]):
    """The scenario with ``--agent I=COMMAND`` added to emulator.agent_commands."""
    from pydantic import ValidationError

    cmds = dict(sc.emulator.agent_commands)
    for spec in specs:
        sat, sep, cmd = spec.partition("=")
        if not sep or not sat.strip().isdigit() or not cmd.strip():
            console.print(f"[red]error:[/red] --agent {spec!r}: expected I=COMMAND (a satellite id, then the command line)",
                          highlight=False)
            raise typer.Exit(2)
        cmds[int(sat)] = cmd.strip()
    try:
        return sc.model_validate({**sc.model_dump(), "emulator": {**sc.emulator.model_dump(), "agent_commands": cmds}})
    except ValidationError as exc:
        console.print(f"[red]error:[/red] --agent: {exc.errors()[0]['msg']}", highlight=False)
        raise typer.Exit(2) from None
