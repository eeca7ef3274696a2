#!/usr/bin/env python3
"""Where two recordings of the same lockstep run part: step by step, every message the
numbers depend on (clocks' live sets, selections, batches, deliveries, estimates, fault
reports, rejoins), wall-time fields left out.

    python scripts/twice_diff.py runs/chaos-1/run/run.mcap runs/chaos-1/run-2/run.mcap [--n 4] [--all]

Prints the first step at which the two differ and what differs there (with ``--all``, every
differing step). Exit 1 when they differ, 0 when every compared message is equal.

Two kinds of record are compared for what the run did with them, not for when they came: a
stall's ``done`` report (the supervisor's, made when it sent SIGCONT after ``down_s`` wall
seconds: its step is the world's step at that wall time) is compared without its step; and
at a step where the world fell back (its own selection recorded), a selection the selector
sent for that step too (late: the world had gone on without it) is not what the run used,
and is left out.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

# Fields that measure wall time, CPU or a process's counters, not the run's numbers.
_WALL = {"step_ms", "step_cpu_ms", "codec_cpu_ms", "select_ms", "recorder_waited_steps", "recorder_waited_s", "malformed",
         "key_mismatch", "host", "detail", "log_time_ns", "batches_late", "batches_missing_total", "run"}
# Message kinds whose content the numbers depend on.
KINDS = ("clock", "select", "meas", "est", "rx", "batches", "fault", "rejoin", "links", "sensors", "cam", "health")


def _plain(x):
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in sorted(x.items()) if k not in _WALL}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, bytes):
        return x.hex()
    return x


def messages(path: Path, n: int) -> dict[int, dict[tuple[str, str], set[str]]]:
    """Step → (kind, topic) → the set of canonical contents recorded there."""
    from google.protobuf.json_format import MessageToDict

    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.codec import decode
    from swarmrt.bus.messages import MessageError, parse_key

    out: dict[int, dict[tuple[str, str], set[str]]] = defaultdict(lambda: defaultdict(set))
    for topic, _schema, data, _log, _pub in iter_messages(path):
        try:
            _run, kind, _sat = parse_key(topic)
        except MessageError:
            continue
        if kind not in KINDS:
            continue
        try:
            m = decode(kind, data, n_sats=n)
        except MessageError:
            continue
        d = MessageToDict(m, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)
        if kind == "fault" and d.get("phase") == "command" and d.get("sender") not in ("world",):
            continue  # the supervisor's own commands (a restart's) carry wall-time details
        k = int(d.get("k", -1))
        if kind == "fault" and d.get("sender") == "supervisor" and str(d.get("action", "")).startswith("stall-"):
            d.pop("k", None)
            d.pop("t_s", None)
            k = -1  # when a stall ended, in steps, is wall time: compared without its step
        topic_tail = topic.split("/", 2)[-1] if "/" in topic else topic
        out[k][(kind, topic_tail)].add(json.dumps(_plain(d), sort_keys=True))
    for step in out.values():
        sel = step.get(("select", "select"))
        if sel and any(json.loads(x).get("sender") == "world" for x in sel):
            step[("select", "select")] = {x for x in sel if json.loads(x).get("sender") == "world"}
    return out


def _first_field_difference(a: str, b: str) -> str:
    da, db = json.loads(a), json.loads(b)
    diff = [f for f in sorted(set(da) | set(db)) if da.get(f) != db.get(f)]
    parts = []
    for f in diff[:6]:
        va, vb = json.dumps(da.get(f))[:160], json.dumps(db.get(f))[:160]
        parts.append(f"{f}: {va} | {vb}")
    return "; ".join(parts)


def compare(a: Path, b: Path, n: int, every: bool = False) -> list[str]:
    ma, mb = messages(a, n), messages(b, n)
    lines: list[str] = []
    for k in sorted(set(ma) | set(mb)):
        sa, sb = ma.get(k, {}), mb.get(k, {})
        here = []
        for key in sorted(set(sa) | set(sb)):
            xa, xb = sa.get(key, set()), sb.get(key, set())
            if xa == xb:
                continue
            if not xa or not xb:
                here.append(f"  {key[0]} {key[1]}: only in {'first' if xa else 'second'} ({len(xa or xb)})")
                continue
            only_a, only_b = sorted(xa - xb), sorted(xb - xa)
            if len(only_a) == 1 and len(only_b) == 1:
                here.append(f"  {key[0]} {key[1]}: {_first_field_difference(only_a[0], only_b[0])}")
            else:
                here.append(f"  {key[0]} {key[1]}: {len(only_a)} versions only in the first, {len(only_b)} only in the second")
        if here:
            lines.append(f"step {k}:")
            lines += here
            if not every:
                break
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("first", type=Path)
    p.add_argument("second", type=Path)
    p.add_argument("--n", type=int, default=None, help="satellites (default: run.json's scenario, or 4)")
    p.add_argument("--all", action="store_true", help="every differing step, not just the first")
    a = p.parse_args(argv)
    n = a.n
    if n is None:
        try:
            n = int(json.loads((a.first.parent / "summary.json").read_text())["n_sats"])
        except (OSError, ValueError, KeyError):
            n = 4
    lines = compare(a.first, a.second, n, a.all)
    print("\n".join(lines) if lines else "no difference in any compared message")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
