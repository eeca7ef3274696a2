"""``swarm conformance``: the agent contract's kit (docs/agent-contract.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from swarm.cli.common import SetOpt, _load, app, console


@app.command()
def conformance(
    agent: str = typer.Option(..., "--agent", metavar="'COMMAND ...'", help="the agent under test: a command line, run as "
                              "satellite ID with the contract's environment (SWARM_SAT_ID, SWARM_RUN, SWARM_CONNECT, ...)"),
    sat: int = typer.Option(1, "--id", min=0, help="the satellite it flies"),
    scenario: Path | None = typer.Option(None, "--scenario", help="the swarm every case starts from (default: 4 satellites, "
                                         "20 s, lockstep, the full-swarm estimator); at least 15 steps, synthetic cameras"),
    sets: list[str] | None = SetOpt,
    out: Path = typer.Option(Path("runs/conformance"), "--out", "-o", help="one run folder per case, and conformance.json"),
    claims: str = typer.Option("", "--claims", help="optional clauses the agent claims, comma-separated: warm-rejoin, late-replay"),
    cases: str = typer.Option("", "--cases", help="run only these cases, comma-separated (clean always runs: the reference): "
                              "clean, inputs, faults, links, restart, router, bus-lost, world-gone, sigterm"),
):
    """Check an agent of any language against the agent contract: run it as one satellite
    of small local swarms through scripted cases (a clean run, malformed and forged
    inputs, camera and drop faults, late and lost radio deliveries, SIGKILL and restart,
    a router restart, the bus lost for good, the world killed, SIGTERM) and print one line
    per clause — pass, fail or not claimed — with its evidence. Writes OUT/conformance.json.

    Exit status: 0 when every clause checked passed; 1 when a mandatory clause, or a
    claimed optional one, failed; 2 for bad arguments."""
    from swarm.conformance import run_conformance

    sc = _load(scenario, sets) if scenario is not None else _default_with(sets) if sets else None
    split = lambda s: [x.strip() for x in s.split(",") if x.strip()]  # noqa: E731
    try:
        report = run_conformance(agent, out, sat=sat, scenario=sc, claims=split(claims), cases=split(cases) or None,
                                 log=lambda s: console.print(s, highlight=False))
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
    except KeyboardInterrupt as exc:
        console.print(f"[red]interrupted[/red]: {exc}", highlight=False)
        raise typer.Exit(130) from None
    for line in report.lines():
        typer.echo(line)
    typer.echo(f"wrote {out / 'conformance.json'}")
    raise typer.Exit(report.exit_code)


def _default_with(sets: list[str]):
    """The kit's default swarm with ``--set`` overrides."""
    from swarm.conformance.kit import DEFAULT_SCENARIO
    from swarmrt.scenario_files import ScenarioError, apply_overrides, parse_overrides, scenario_from_dict

    try:
        return scenario_from_dict(apply_overrides(DEFAULT_SCENARIO, parse_overrides(sets)), "the kit's default scenario")
    except ScenarioError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False)
        raise typer.Exit(2) from None
