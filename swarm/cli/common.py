"""What every ``swarm`` command shares: the Typer apps, the console, options, scenario
loading with errors that name the field, progress bars, tables."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from swarmrt.scenario_files import ScenarioError, load_scenario

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

fault_app = typer.Typer(
    help="Inject faults into a running swarm: `swarm fault --run-dir DIR kill-agent 2` (local, "
    "from `swarm run --out DIR`) or `swarm fault --compose kill-agent 2` (docker compose).",
    no_args_is_help=True,
)

app.add_typer(fault_app, name="fault")

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
    from swarm.studies.executor import ClusterError

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
    return os.environ.get("SWARM_PROGRESS", "") == "1"


def number(x, spec: str = ".3g") -> str:
    """A value for a table: "no data" rather than nan (:func:`swarm.outputs.number`)."""
    from swarm.outputs import number as fmt

    return fmt(x, spec)


def _summary_table(summary: dict, title: str) -> Table:
    from swarm.outputs import NO_DATA, no_data_reason

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


def _fmt3(v) -> str:
    return "/".join(f"{x:.2f}" for x in v)
