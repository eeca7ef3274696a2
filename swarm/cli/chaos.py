"""``swarm chaos``: a seeded random fault campaign against a distributed run
(:mod:`swarm.chaos.campaign` draws the schedule and checks the run; this only wires and prints)."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import typer
from rich.table import Table

from swarm.cli.common import SetOpt, _load, _progress, app, console


@app.command()
def chaos(
    scenario: Path = typer.Argument(..., help="scenario YAML file (its own faults are kept)"),
    faults: int = typer.Option(8, "--faults", min=0, help="fault episodes to draw (each a fault and its recovery)"),
    seed: int = typer.Option(0, "--seed", min=0, help="the campaign's seed: the same seed draws the same schedule"),
    duration: float | None = typer.Option(None, "--duration", min=1.0, help="the run's simulated duration (s; duration_s)"),
    out: Path = typer.Option(Path("runs/chaos"), "--out", "-o", help="campaign folder: chaos.json, run/ (swarm run's folder)"),
    kinds: list[str] | None = typer.Option(None, "--kind", help="draw only these kinds (repeatable): kill-agent, stop-agent, "
                                           "camera, drop, selector, router, failover, stall, link, isolate; under --compose "
                                           "also netem, partition; under --cluster also kill-node, partition-nodes (no failover)"),
    settle: int | None = typer.Option(None, "--settle", min=1, help="steps after the last recovery (default: max(4, steps/6))"),
    sets: list[str] | None = SetOpt,
    timeout: float | None = typer.Option(None, help="stop the run after this many wall seconds"),
    schedule_only: bool = typer.Option(False, "--schedule-only", help="draw and print the schedule; run nothing"),
    routers: int = typer.Option(1, "--routers", min=1, max=2, help="Zenoh routers of the run (2: a mesh the clients fail over "
                                "in; adds the failover kind: one router killed, then restarted)"),
    twice: bool = typer.Option(False, "--twice", help="run the campaign a second time (OUT/run-2) and check both give "
                               "the same numbers, bit for bit"),
    compose: bool = typer.Option(False, "--compose", help="run the swarm of `docker compose up` (the image: make image) and "
                                 "send every fault as `swarm fault --compose` does (Docker: kill, stop, restart, pause, tc "
                                 "netem, network disconnect); adds the netem and partition kinds; SCENARIO must be a file of "
                                 "scenarios/"),
    cluster: str | None = typer.Option(
        None, "--cluster", metavar="ray://HOST:PORT|local-ray[:N]", help="run the campaign over a Ray cluster (as `swarm run "
        "--cluster`); adds the kill-node kind (a node other than the head's taken down, its agents moved to the survivors) "
        "and, on local-ray:N (namespaced nodes, root), partition-nodes (two nodes cut apart for a while); docs/cluster.md"),
):
    """Draw a seeded schedule of faults (agents killed, stopped and restarted, cameras off,
    dropped messages, the selector killed, the router restarted, a role stalled; with
    --routers 2 one of two routers killed and restarted while the clients fail over; with the
    link model on, links made dead, slow or lossy; under --compose a container's network
    delayed and lossy (tc netem) or cut; under --cluster a Ray node killed, two nodes cut
    apart), run the swarm with it (as `swarm run`, `swarm run --cluster`, or as `docker
    compose up`), and check the invariants: every process ended; never finished with agents
    gone; the recording readable and every fired fault in summary.json; every step complete
    and the filters within 3σ once reconverged (recovery time per kind, p50/p99); the same
    seed, the same schedule. Writes OUT/chaos.json; exit 1 if an invariant fails."""
    from swarm.chaos.campaign import (
        CLUSTER_KINDS,
        COMPOSE_KINDS,
        KINDS,
        chaos_scenario,
        check_run,
        draw_schedule,
        same_numbers,
        schedule_digest,
    )

    sets = [*(sets or ()), *([f"duration_s={duration}"] if duration is not None else [])]
    nodes, partitions = 0, False
    if cluster is not None:
        if compose or routers != 1:
            console.print("[red]error:[/red] --cluster runs a router per node (no --routers) and its own processes (no --compose)",
                          highlight=False)
            raise typer.Exit(2)
        from swarm.cli.distributed import _cluster_errors
        from swarm.cluster.swarm import cluster_shape

        errors: tuple[type[BaseException], ...] = (ValueError, *_cluster_errors())
        try:
            nodes, partitions = cluster_shape(cluster)
        except errors as exc:
            console.print(f"[red]error:[/red] {exc}", highlight=False)
            raise typer.Exit(2) from None
    if compose:
        from swarm.chaos.compose import PACE

        if routers != 1 or twice:
            console.print("[red]error:[/red] --compose runs one router, once (its faults come from outside the swarm: "
                          "not reproducible bit for bit, so no --twice)", highlight=False)
            raise typer.Exit(2)
        if not any(x.startswith("emulator.lockstep_max_realtime_factor=") for x in sets):
            sets.append(f"emulator.lockstep_max_realtime_factor={PACE:g}")
    sc = _load(scenario, sets)
    known = COMPOSE_KINDS if compose else CLUSTER_KINDS if cluster is not None else KINDS
    if bad := [k for k in kinds or () if k not in known]:
        why = (" (it acts on the nodes of a Ray cluster: add --cluster local-ray:N or ray://HOST:PORT)"
               if bad[0] in CLUSTER_KINDS and cluster is None else "")
        console.print(f"[red]error:[/red] --kind {bad[0]!r}: one of {', '.join(known)}{why}", highlight=False)
        raise typer.Exit(2)
    try:
        episodes = draw_schedule(sc, faults, seed, settle, tuple(kinds) if kinds else None, routers=nodes or routers, compose=compose,
                                 nodes=nodes, partitions=partitions)
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    on = f" over {nodes} Ray node(s)" if cluster is not None else ""
    t = Table(title=f"chaos schedule: {len(episodes)} faults, seed {seed}, {sc.steps} steps{on} (sha256 {schedule_digest(episodes)[:12]})")
    for col in ("from step", "to step", "kind", "target", "detail"):
        t.add_column(col)
    for e in episodes:
        detail = (f"{e.role}{'' if e.router is None else f' {e.router}'} stopped {e.down_s} s" if e.kind == "stall"
                  else "every link dead" if e.kind == "isolate"
                  else f"node {e.target}: agents {', '.join(map(str, e.sats or ()))} move" if e.kind == "kill-node"
                  else f"nodes {e.target} and {e.peer} cut apart {e.down_s} s" if e.kind == "partition-nodes"
                  else f"-> {e.peer} " + ("dead" if e.impair == "dead" else f"+{e.delay_s} s" if e.impair == "delay"
                                          else f"loss {e.rate}") if e.kind == "link"
                  else f"camera {e.camera}" if e.camera is not None else f"rate {e.rate}" if e.rate is not None
                  else f"down {e.down_s} s" if e.down_s is not None else f"router {e.router}" if e.router is not None else "")
        t.add_row(str(e.start), str(e.end), e.kind, "" if e.target is None else str(e.target), detail)
    console.print(t)
    if schedule_only:
        return
    from swarm.api import run as run_swarm

    out.mkdir(parents=True, exist_ok=True)
    if compose:
        return _compose_campaign(scenario, sets, sc, episodes, seed, faults, settle, kinds, out, timeout)
    sc_chaos = chaos_scenario(sc, episodes)
    where = {"cluster": cluster} if cluster is not None else {"routers": routers}
    t0 = time.monotonic()

    def fly(folder: Path, what: str):
        with _progress() as prog:
            task = prog.add_task(what, total=sc.steps)
            try:
                return run_swarm(sc_chaos, out=folder, timeout=timeout, progress=lambda k, K: prog.update(task, completed=k),
                                 log=lambda s: console.print(s, highlight=False), **where)
            except _start_errors(cluster) as exc:  # the cluster could not run it at all: no run to check
                console.print(f"[red]error:[/red] {exc}", highlight=False)
                raise typer.Exit(2) from None

    result = fly(out / "run", f"chaos {sc.name} n={sc.n_sats}{on}")
    wall_s = time.monotonic() - t0
    assert result.outcome is not None
    _stop_if_signalled(result, out / "run")
    report = check_run(out / "run", sc_chaos, episodes, seed, result.outcome.exit_code, n_faults=faults, settle=settle,
                       kinds=tuple(kinds) if kinds else None, routers=nodes or routers, nodes=nodes, partitions=partitions)
    report.extra["wall_s"] = round(wall_s, 1)
    if cluster is not None:
        report.extra["cluster"] = {"address": cluster, "nodes": nodes, "partitions": partitions,
                                   "node_faults": _node_faults(result.summary)}
    if twice:
        second = fly(out / "run-2", f"chaos {sc.name} n={sc.n_sats}{on}, again")
        _stop_if_signalled(second, out / "run-2")
        report.invariants.append(same_numbers(result.summary, second.summary))
    if cluster is not None:
        _print_node_faults(report.extra["cluster"]["node_faults"])
    _finish(report, out, wall_s)


def _stop_if_signalled(result, folder: Path) -> None:
    """A run stopped by a signal (the user, or a parent that ended) ends the campaign here,
    with the run's status, neither checked nor flown again (--twice started a second run)."""
    assert result.outcome is not None
    if result.outcome.signal is not None:
        console.print(f"[yellow]{result.outcome.signal.name}: the campaign stops (run in {folder})[/yellow]", highlight=False)
        raise typer.Exit(result.outcome.exit_code)


def _start_errors(cluster: str | None) -> tuple[type[BaseException], ...]:
    if cluster is None:
        return ()
    from swarm.cli.distributed import _cluster_errors

    return _cluster_errors()


def _node_faults(summary: dict) -> list[dict]:
    """What the cluster's node faults did, as the run's faults table says it (each moved
    agent's new node, the node's end, a partition's cut and heal)."""
    return [{k: f.get(k) for k in ("k", "action", "target", "peer", "phase", "sender", "detail") if f.get(k) is not None}
            for f in summary.get("faults") or [] if f.get("action") in ("kill-node", "partition-nodes") and f.get("phase") != "command"]


def _print_node_faults(rows: list[dict]) -> None:
    if not rows:
        return
    t = Table(title="node faults (where each agent went)")
    for col in ("k", "action", "target", "phase", "detail"):
        t.add_column(col)
    for f in rows:
        t.add_row(*(str(f.get(c, "")) for c in ("k", "action", "target", "phase", "detail")))
    console.print(t)


def _compose_campaign(scenario: Path, sets: list[str], sc, episodes, seed: int, faults: int, settle, kinds, out: Path,
                      timeout) -> None:
    """The campaign under docker compose (swarm/chaos/compose.py runs it)."""
    from swarm.chaos.campaign import check_run
    from swarm.chaos.compose import run_compose_campaign

    root = Path(__file__).resolve().parents[2]
    commands = sorted((c for e in episodes for c in e.commands()), key=lambda c: c.at_step)
    t0 = time.monotonic()
    try:
        with _progress() as prog:
            task = prog.add_task(f"chaos (compose) {sc.name} n={sc.n_sats}", total=sc.steps)
            code = run_compose_campaign(root, scenario, sets, commands, sc.n_sats, sc.steps, sc.dt_s, out,
                                        log=lambda s: console.print(s, highlight=False),
                                        progress=lambda k, K: prog.update(task, completed=k), timeout_s=timeout)
    except (RuntimeError, ValueError, subprocess.TimeoutExpired) as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    wall_s = time.monotonic() - t0
    report = check_run(out / "run", sc, episodes, seed, -1 if code is None else code, n_faults=faults, settle=settle,
                       kinds=tuple(kinds) if kinds else None, compose=True)
    report.extra["wall_s"] = round(wall_s, 1)
    report.extra["compose"] = True
    _finish(report, out, wall_s)


def _finish(report, out: Path, wall_s: float) -> None:
    """A campaign's end, local or compose: chaos.json, the tables, the report page; exit 1
    if an invariant failed."""
    (out / "chaos.json").write_text(json.dumps(report.to_json(), indent=1) + "\n")
    _print_report(report)
    console.print(f"wrote {out / 'chaos.json'} (run folder {out / 'run'}; {wall_s:.0f} s)", highlight=False)
    _write_report(out)
    if not report.ok:
        raise typer.Exit(1)


def _print_report(report) -> None:
    from swarm.chaos.campaign import FIRED_COLUMNS, fired_rows

    t = Table(title=f"faults fired ({report.scenario}, seed {report.seed})")
    for col in FIRED_COLUMNS:
        t.add_column(col)
    for row in fired_rows(report.fired, report.recovery):
        t.add_row(*row)
    console.print(t)
    t = Table(title="invariants")
    t.add_column("invariant")
    t.add_column("")
    t.add_column("evidence")
    for inv in report.invariants:
        t.add_row(inv.name, "[green]pass[/green]" if inv.ok else "[bold red]FAIL[/bold red]", inv.evidence)
    console.print(t)


def _write_report(out: Path) -> None:
    """The campaign's report page (``swarm report OUT`` writes the same): its tables, then its
    run's. A run too broken to plot still leaves chaos.json, which is the verdict."""
    from swarm.studies.report import make_report

    try:
        page = make_report(out)
    except (OSError, ValueError) as exc:
        console.print(f"[yellow]no report page:[/yellow] {exc} (chaos.json holds the verdict)", highlight=False)
        return
    console.print(f"wrote {page}", highlight=False)
