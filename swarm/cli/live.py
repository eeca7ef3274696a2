"""The live 3-D view: ``swarm live layout`` and ``swarm live attach`` (``swarm run --live``
starts it with a run; ``swarm bench live`` measures its cost)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from swarm.cli.common import app, console

live_app = typer.Typer(help="The live 3-D view (Foxglove): its layout, and joining a running swarm.", no_args_is_help=True)
app.add_typer(live_app, name="live")


@live_app.command("layout")
def live_layout(
    out: Path = typer.Option(Path("foxglove-layout.json"), "--out", "-o", help="layout file to write"),
    sats: int = typer.Option(10, "--sats", min=1, max=1000, help="the swarm's size (one plot series and 3D topic per filter)"),
):
    """Write the Foxglove layout of the swarm's scene (docs/foxglove-layout.json is the one
    for 10 satellites): in Foxglove, Layouts → Import from file. It opens the live view,
    run.mcap and swarm sim's scene.mcap alike."""
    from swarm.live.layout import write_layout

    write_layout(out, sats)
    console.print(f"wrote {out} (layout for {sats} satellites)", highlight=False)


@live_app.command("attach")
def live_attach(
    run_dir: Path = typer.Option(..., "--run-dir", help="the run folder of a running `swarm run` (has run.json)"),
    ws: str = typer.Option("127.0.0.1:8765", "--ws", metavar="HOST:PORT", help="where to serve the Foxglove WebSocket protocol"),
    max_rate: float = typer.Option(20.0, "--max-rate", help="draw at most this many times a wall second"),
):
    """Serve the live view of a swarm that is already running (the process `swarm run --live`
    starts), as the run's read-only viewer; Ctrl-C stops it, never the run."""
    from swarm.live.server import main as serve

    try:
        info = json.loads((run_dir / "run.json").read_text())
    except (OSError, ValueError) as exc:
        console.print(f"[red]error:[/red] {run_dir / 'run.json'}: {exc}", highlight=False)
        raise typer.Exit(2) from None
    args = ["--run", info["run"], "--scenario", info["scenario"], "--ws", ws, "--max-rate", str(max_rate), "--mode", "client"]
    for e in info.get("endpoints") or [info["endpoint"]]:
        args += ["--connect", e]
    if info.get("keys"):
        cred = Path(info["keys"]) / "viewer.json"
        if not cred.exists():
            console.print(f"[red]error:[/red] {cred}: no viewer credential (a run started before the live view existed)",
                          highlight=False)
            raise typer.Exit(2)
        args += ["--credential", str(cred)]
    raise typer.Exit(serve(args))
