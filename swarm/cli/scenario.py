"""``swarm scenario show|schema``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from swarm.cli.common import SetOpt, _load, scenario_app


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
