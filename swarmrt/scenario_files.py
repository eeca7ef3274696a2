"""Scenario files: YAML in, validated :class:`swarmcore.scenario.Scenario` out.

``--set dotted.key=value`` overrides any field; values are parsed as YAML (numbers,
booleans, lists). Every failure names the file and the field.
"""

from __future__ import annotations

import reprlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from swarmcore.scenario import Scenario

__all__ = ["ScenarioError", "MAX_SCENARIO_BYTES", "load_scenario", "parse_overrides", "apply_overrides", "scenario_from_dict"]


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names the field and the problem."""


#: The largest scenario file read (a 200-satellite graph.matrix is ~120 KB of YAML).
MAX_SCENARIO_BYTES = 16 << 20
#: The most values (and the deepest nesting) a scenario may hold once YAML's aliases are
#: expanded: a few aliases can name 10⁹ values (a "billion laughs") that validation would walk.
MAX_SCENARIO_VALUES = 1_000_000
MAX_SCENARIO_DEPTH = 32


def _check_size(data, source: str) -> None:
    """Refuse a scenario whose values, counted as validation would walk them (every alias
    expanded), exceed MAX_SCENARIO_VALUES or nest deeper than MAX_SCENARIO_DEPTH (a
    recursive alias does both)."""
    count = 0
    stack = [(data, 0)]
    while stack:
        v, depth = stack.pop()
        count += 1
        if count > MAX_SCENARIO_VALUES:
            raise ScenarioError(f"{source}: more than {MAX_SCENARIO_VALUES} values once its aliases are expanded, not a scenario")
        if depth > MAX_SCENARIO_DEPTH:
            raise ScenarioError(f"{source}: lists or mappings nested deeper than {MAX_SCENARIO_DEPTH} levels, not a scenario")
        if isinstance(v, dict):
            stack.extend((x, depth + 1) for kv in v.items() for x in kv)
        elif isinstance(v, (list, tuple, set)):
            stack.extend((x, depth + 1) for x in v)


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
        except (yaml.YAMLError, ValueError) as exc:
            raise ScenarioError(f"--set {key}: value {raw[:200]!r} is not valid YAML ({exc})") from None
        except RecursionError:
            raise ScenarioError(f"--set {key}: value nested too deeply") from None
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


_REPR = reprlib.Repr()  # what an error shows of a value: bounded, whatever the value's size
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxother = 2, 6, 6, 80, 80
_MAX_LINES = 20


def _format_validation(exc: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid scenario"]
    errors = exc.errors()
    for err in errors[:_MAX_LINES]:
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        msg = err["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        if err["type"] == "extra_forbidden":
            msg = "unknown field (check the spelling; see `swarm scenario schema`)"
        got = err.get("input")
        got_s = "" if isinstance(got, dict) or got is None else f" (got {_REPR.repr(got)})"
        lines.append(f"  {loc}: {msg}{got_s}")
    if len(errors) > _MAX_LINES:
        lines.append(f"  ... and {len(errors) - _MAX_LINES} more")
    return "\n".join(lines)


def scenario_from_dict(data: dict, source: str = "scenario") -> Scenario:
    """A validated scenario; its estimator (a built-in or an installed plug-in) checked too:
    its kind, its parameters and whether it can fly this scenario (errors name the field)."""
    try:
        sc = Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(_format_validation(exc, source)) from None
    from swarmrt.estimators import IncompatibleScenario, check_estimator

    try:
        check_estimator(sc)
    except IncompatibleScenario as exc:
        raise ScenarioError(f"{source}: {exc}") from None
    return sc


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
            with open(p, "rb") as f:
                raw = f.read(MAX_SCENARIO_BYTES + 1)
            if len(raw) > MAX_SCENARIO_BYTES:
                raise ScenarioError(f"{p}: larger than {MAX_SCENARIO_BYTES} bytes, not a scenario file")
            loaded = yaml.safe_load(raw.decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ScenarioError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        except OSError as exc:
            raise ScenarioError(f"{p}: cannot read it ({exc.strerror or exc})") from None
        except (yaml.YAMLError, ValueError) as exc:  # ValueError: an integer of more than 4300 digits
            raise ScenarioError(f"{p}: not valid YAML: {exc}") from None
        except RecursionError:
            raise ScenarioError(f"{p}: not a scenario: lists or mappings nested too deeply") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ScenarioError(f"{p}: a scenario must be a mapping of fields, got {type(loaded).__name__}")
        data = loaded
    data = apply_overrides(data, parse_overrides(overrides))
    _check_size(data, source)
    if seed is not None:
        data["seed"] = seed
    return scenario_from_dict(data, source)
