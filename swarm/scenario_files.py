"""Scenario files: YAML in, validated :class:`swarmcore.scenario.Scenario` out.

``--set dotted.key=value`` overrides any field; values are parsed as YAML (numbers,
booleans, lists). Every failure names the file and the field.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from swarmcore.scenario import Scenario

__all__ = ["ScenarioError", "load_scenario", "parse_overrides", "apply_overrides", "scenario_from_dict"]


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names the field and the problem."""


def parse_overrides(items: Iterable[str]) -> list[tuple[list[str], Any]]:
    out = []
    for item in items or ():
        if "=" not in item:
            raise ScenarioError(f"--set {item!r}: expected dotted.key=value")
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key or any(not part for part in key.split(".")):
            raise ScenarioError(f"--set {item!r}: empty key")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ScenarioError(f"--set {key}: value {raw!r} is not valid YAML ({exc})") from None
        out.append((key.split("."), value))
    return out


def apply_overrides(data: dict, overrides: list[tuple[list[str], Any]]) -> dict:
    data = dict(data)
    for path, value in overrides:
        node = data
        for i, part in enumerate(path[:-1]):
            child = node.get(part)
            if child is None:
                child = {}
            elif not isinstance(child, dict):
                raise ScenarioError(f"--set {'.'.join(path)}: {'.'.join(path[: i + 1])} is not a section")
            else:
                child = dict(child)
            node[part] = child
            node = child
        node[path[-1]] = value
    return data


def _format_validation(exc: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid scenario"]
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        msg = err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if err["type"] == "extra_forbidden":
            msg = "unknown field (check the spelling; see `swarm scenario schema`)"
        got = err.get("input")
        got_s = "" if isinstance(got, dict) or got is None else f" (got {got!r})"
        lines.append(f"  {loc}: {msg}{got_s}")
    return "\n".join(lines)


def scenario_from_dict(data: dict, source: str = "scenario") -> Scenario:
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(_format_validation(exc, source)) from None


def load_scenario(path: str | Path | None, overrides: Iterable[str] = (), seed: int | None = None) -> Scenario:
    """Read a YAML scenario (or the defaults when ``path`` is None), apply overrides."""
    data: dict = {}
    source = "defaults"
    if path is not None:
        p = Path(path)
        source = str(p)
        if not p.is_file():
            raise ScenarioError(f"{p}: no such scenario file")
        try:
            loaded = yaml.safe_load(p.read_text())
        except yaml.YAMLError as exc:
            raise ScenarioError(f"{p}: not valid YAML: {exc}") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ScenarioError(f"{p}: a scenario must be a mapping of fields, got {type(loaded).__name__}")
        data = loaded
    data = apply_overrides(data, parse_overrides(overrides))
    if seed is not None:
        data["seed"] = seed
    return scenario_from_dict(data, source)
