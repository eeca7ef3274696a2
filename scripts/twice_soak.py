#!/usr/bin/env python3
"""The repeat benchmark (issue 35, item 2): `swarm chaos --twice` over many seeds, every
kind of fault a local run has (stalls of every role, link faults, failovers with two
routers), and one table: per seed the faults fired per kind, invariants a–e of the first
run, a–d checked again on the second run, and whether the two runs' numbers are equal — with,
when they are not, the first step at which their recordings differ (scripts/twice_diff.py).

    python scripts/twice_soak.py --seeds 1-20 --faults 40 --duration 40 --jobs 2 --out runs/soak/twice

Writes OUT/twice.json (the table and the command) and prints the table as Markdown; each
campaign's folder is OUT/seed-S (chaos.json, run/, run-2/, its log). Exit 1 when any
invariant failed or any two runs differ. ``--set`` entries are passed on (the defaults are
the default swarm with a greedy selector and the radio's link model on).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SETS = ["links.enabled=true", "links.latency.speed_of_light=false", "selection.strategy=greedy", "selection.budget=4"]


def _seeds(spec: str) -> list[int]:
    out: list[int] = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


# The read end of a pipe whose write end only this process holds: each campaign runs under
# swarm.supervise.lifeline on it, so it stops (cleanly: SIGTERM) when this script ends,
# however it ends (seen: a `swarm chaos` orphaned by a SIGTERMed benchmark ran on).
_LIFELINE_R, _LIFELINE_W = os.pipe()


def _campaign(seed: int, a) -> dict:
    out = a.out / f"seed-{seed}"
    cmd = [sys.executable, "-m", "swarm.supervise.lifeline", "--fd", str(_LIFELINE_R), "--grace-s", "60", "swarm.cli", "chaos", str(a.scenario), "--faults", str(a.faults), "--seed", str(seed),
           "--duration", str(a.duration), "--routers", str(a.routers), "--twice", "--out", str(out)]
    for s in a.sets:
        cmd += ["--set", s]
    out.mkdir(parents=True, exist_ok=True)
    if a.no_run:  # the campaign ran before: check and compare its folder again
        before = json.loads((out / "row.json").read_text()) if (out / "row.json").exists() else {}
        code, wall = before.get("exit", -1), before.get("wall_s", float("nan"))
    else:
        t0 = time.monotonic()
        with open(out / "chaos.log", "w") as log:
            code = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=dict(os.environ, COLUMNS="200"),
                                  pass_fds=(_LIFELINE_R,)).returncode
        wall = time.monotonic() - t0
        (out / "row.json").write_text(json.dumps({"exit": code, "wall_s": round(wall, 1)}) + "\n")
    row: dict = {"seed": seed, "exit": code, "wall_s": round(wall, 1)}
    try:
        report = json.loads((out / "chaos.json").read_text())
    except (OSError, ValueError) as exc:
        row["error"] = f"no chaos.json ({exc}); see {out / 'chaos.log'}"
        return row
    kinds = Counter()
    for e in report["schedule"]:
        kinds[e["kind"] if e["kind"] != "stall" else f"stall-{e['role']}"] += 1
    row["faults"] = dict(sorted(kinds.items()))
    row["fired"] = sum(d["fired"] for d in report["fired"].values())
    row["invariants"] = {inv["name"].split(".")[0] + ("2" if "run twice" in inv["name"] else ""): inv["ok"] for inv in report["invariants"]}
    row["evidence"] = {inv["name"]: inv["evidence"] for inv in report["invariants"] if not inv["ok"]}
    row["second_run"] = _check_second(out, report, a.routers)
    row["numbers_equal"] = next((inv["ok"] for inv in report["invariants"] if "run twice" in inv["name"]), None)
    row["gate"] = _gate(out)
    first, second = out / "run" / "run.mcap", out / "run-2" / "run.mcap"
    if first.exists() and second.exists():
        diff = subprocess.run([sys.executable, str(ROOT / "scripts" / "twice_diff.py"), str(first), str(second)],
                              capture_output=True, text=True, cwd=ROOT)
        row["recordings_equal"] = diff.returncode == 0
        if diff.returncode != 0:
            row["first_difference"] = diff.stdout.strip().splitlines()[:12]
    return row


def _gate(out: Path) -> dict:
    """What the routers' ingress gates did to honest roles over both runs (``router_gate`` of
    each summary.json): connections held back, cut and refused, summed over identities; the
    identities it cut. Any of it means a role sent more than its bucket under faults (the
    supervisor's resends did: a command sent it was lost while it was cut)."""
    tot = {"held": 0, "cut": 0, "refused": 0, "cut_identities": []}
    for run in ("run", "run-2"):
        try:
            gate = json.loads((out / run / "summary.json").read_text()).get("router_gate") or {}
        except (OSError, ValueError):
            continue
        for name, c in gate.items():
            if not isinstance(c, dict):
                continue
            for k in ("held", "cut", "refused"):
                tot[k] += int(c.get(k) or 0)
            if c.get("cut") and name not in tot["cut_identities"]:
                tot["cut_identities"].append(name)
    return tot


def _check_second(out: Path, report: dict, routers: int) -> dict:
    """Invariants a–d of the second run (the command checks the first run's)."""
    from swarm.chaos.campaign import Episode, check_run
    from swarmrt.scenario_files import load_scenario

    run2 = out / "run-2"
    try:
        sc = load_scenario(run2 / "scenario.yaml")
        summary = json.loads((run2 / "summary.json").read_text())
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    # swarm run's exit status: 0 for a finished run, non-zero for one declared broken (its world's, or 1).
    code = int(summary.get("world_exit_code") or 0) if not summary.get("interrupted") else int(summary.get("world_exit_code") or 1) or 1
    episodes = [Episode(**e) for e in report["schedule"]]
    rep = check_run(run2, sc, episodes, report["seed"], code, n_faults=report["n_faults"], routers=routers)
    return {inv.name.split(".")[0]: inv.ok for inv in rep.invariants} | {
        "evidence": {inv.name: inv.evidence for inv in rep.invariants if not inv.ok}}


def _table(rows: list[dict]) -> str:
    kinds = sorted({k for r in rows for k in r.get("faults", {})})
    head = ["seed", "faults (by kind)", "run 1: a b c d e", "run 2: a b c d", "numbers (e, twice)", "recordings",
            "gate: held / cut / refused", "wall"]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join("---" for _ in head) + " |"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['seed']} | {r['error']} |" + " |" * (len(head) - 2))
            continue
        f = ", ".join(f"{k} {r['faults'][k]}" for k in kinds if k in r["faults"])
        inv = r["invariants"]
        one = " ".join(("pass" if inv.get(x) else "FAIL") for x in ("a", "b", "c", "d", "e"))
        two = r["second_run"]
        two_s = "error" if "error" in two else " ".join(("pass" if two.get(x) else "FAIL") for x in ("a", "b", "c", "d"))
        eq = "equal" if r.get("numbers_equal") else "DIFFERENT"
        rec = "equal" if r.get("recordings_equal") else ("DIFFER from " + (r.get("first_difference") or ["?"])[0])
        g = r.get("gate") or {}
        gate = f"{g.get('held', '?')} / {g.get('cut', '?')} / {g.get('refused', '?')}" + (
            f" ({', '.join(g['cut_identities'])})" if g.get("cut_identities") else "")
        lines.append(f"| {r['seed']} | {sum(r['faults'].values())} ({f}) | {one} | {two_s} | {eq} | {rec} | {gate} | {r['wall_s']:.0f} s |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", type=Path, default=Path("scenarios/demo.yaml"))
    p.add_argument("--seeds", default="1-20", help="e.g. 1-20 or 1,4,7-9")
    p.add_argument("--faults", type=int, default=40)
    p.add_argument("--duration", type=float, default=40.0)
    p.add_argument("--routers", type=int, default=2)
    p.add_argument("--jobs", type=int, default=1, help="campaigns at once")
    p.add_argument("--set", dest="sets", action="append", default=None, help="scenario override (repeatable; replaces the defaults)")
    p.add_argument("--out", type=Path, default=Path("runs/soak/twice"))
    p.add_argument("--no-run", action="store_true", help="run nothing: check and compare the campaigns already in OUT again")
    a = p.parse_args(argv)
    a.sets = a.sets if a.sets is not None else DEFAULT_SETS
    a.out = (ROOT / a.out) if not a.out.is_absolute() else a.out
    seeds = _seeds(a.seeds)
    t0 = time.monotonic()
    rows: list[dict] = []
    with ThreadPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        for row in pool.map(lambda s: _campaign(s, a), seeds):
            rows.append(row)
            print(json.dumps(row), flush=True)
            _write(a, argv, rows, t0)  # as it goes: a benchmark cut short keeps what it measured
    doc = _write(a, argv, rows, t0)
    print(_table(rows))
    print(f"\n{len(rows)} seeds, {doc['invariant_failures']} with an invariant failure, {doc['differences']} with a difference; "
          f"{doc['wall_s']:.0f} s; wrote {a.out / 'twice.json'}")
    return 1 if doc["invariant_failures"] or doc["differences"] else 0


def _write(a, argv, rows: list[dict], t0: float) -> dict:
    doc = {"command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
           "scenario": str(a.scenario), "sets": a.sets, "faults": a.faults, "duration_s": a.duration, "routers": a.routers,
           "jobs": a.jobs, "wall_s": round(time.monotonic() - t0, 1), "rows": rows,
           "invariant_failures": sum(1 for r in rows if "error" in r or not all(r["invariants"].values())
                                     or "error" in r["second_run"] or not all(v for k, v in r["second_run"].items() if k != "evidence")),
           "differences": sum(1 for r in rows if "error" in r or not r.get("numbers_equal") or not r.get("recordings_equal"))}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "twice.json").write_text(json.dumps(doc, indent=1) + "\n")
    (a.out / "twice.md").write_text(_table(rows) + "\n")
    return doc


if __name__ == "__main__":
    sys.exit(main())
