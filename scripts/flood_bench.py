"""A stolen agent credential floods its own keys for a whole run: what the router's size
limits (``swarmrt.security.size_limits``, Zenoh ``low_pass_filter``) change.

For each setting (limits on, the default; off, ``SWARM_ROUTER_SIZE_LIMITS=off``) it runs
the same lockstep swarm twice on loopback, security on: once quiet, once while a session
holding agent 1's credential puts, as fast as it can, garbage one byte over its estimate
limit on ``est/1`` and over the report limit on ``health/1`` (the keys that identity may put;
every other key the access rules already refuse it), and once more with garbage exactly at
the limits (it passes the router; the recorder's flood cap bounds what it writes). Printed
and written (``--out``): puts
sent and bytes, the recording's size, messages the recorder counted malformed, the run's
wall time, and whether the flooded run's numbers equal the in-process run's bit for bit.

    .venv/bin/python scripts/flood_bench.py --duration 30 --out runs/bench/flood.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from swarm.simulation import simulate_scenario
from swarm.supervise.launch import LocalSwarm
from swarm.supervise.outcome import run_outcome
from swarmrt.bus.messages import Keys
from swarmrt.scenario_files import load_scenario
from swarmrt.security import size_limit_of

NUMBERS = ("rms", "rms_second_half", "per_pair", "nees", "gate")


def _flood(sw: LocalSwarm, n_sats: int, stop: threading.Event, sent: dict, over: int) -> None:
    """``over``: bytes over each key's size limit (1: every put dropped by the router; 0: at
    the limit, every put passes the router and reaches the recorder, which takes it for
    malformed: its flood cap bounds what it writes)."""
    keys = Keys(sw.run)
    targets = [(keys.est(1), b"\xff" * (size_limit_of("est", n_sats) + over)),
               (keys.health(1), b"\xfe" * (size_limit_of("health", n_sats) + over))]
    with zenoh.open(sw.bus_as("agent-1").zenoh_config()) as s:
        pubs = [(s.declare_publisher(k), p) for k, p in targets]
        while not stop.is_set() and sw.procs["world"].poll() is None:
            for pub, payload in pubs:
                pub.put(payload)
                sent["puts"] += 1
                sent["bytes"] += len(payload)


def one_run(sc, out: Path, limits: bool, flood: bool, over: int = 1, rate_hz: float | None = None) -> dict:
    os.environ["SWARM_ROUTER_SIZE_LIMITS"] = "on" if limits else "off"
    if rate_hz:
        os.environ["SWARM_ROUTER_RATE_LIMIT_HZ"] = f"{rate_hz:g}"
    else:
        os.environ.pop("SWARM_ROUTER_RATE_LIMIT_HZ", None)
    sw = LocalSwarm(sc, out, log=lambda s: None)
    stop = threading.Event()
    sent = {"puts": 0, "bytes": 0}
    th = threading.Thread(target=_flood, args=(sw, sc.n_sats, stop, sent, over), daemon=True) if flood else None
    t0 = time.monotonic()
    code = None
    try:
        sw.start()
        if th is not None:
            th.start()
        code = sw.run_to_end(timeout=1800)
    finally:
        stop.set()
        sw.stop()
        if th is not None:
            th.join(30)
    wall = time.monotonic() - t0
    summary = run_outcome(sc, out / "run.mcap", run=sw.run, world_exit_code=code, interrupted=sw.interrupted, broken=sw.broken,
                          broken_code=sw.broken_code, router_faults=sw.router_faults).summary
    return {"limits": limits, "rate_limit_hz": rate_hz, "flood": ("over the limit" if over > 0 else "at the limit") if flood else None,
            "world_exit_code": code, "wall_s": round(wall, 2),
            "puts_sent": sent["puts"], "bytes_sent": sent["bytes"],
            "recording_bytes": (out / "run.mcap").stat().st_size if (out / "run.mcap").exists() else None,
            "malformed_recorded": summary.get("messages", {}).get("_malformed", 0),
            "not_recorded_over_the_flood_cap": sum(summary.get("messages", {}).get("not_recorded_over_the_flood_cap", {}).values()),
            "numbers": {k: summary.get(k) for k in NUMBERS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="scenarios/demo.yaml")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--out", default="runs/bench/flood.json")
    ap.add_argument("--rate-limit-hz", type=float, default=None,
                    help="instead: the quiet and the at-the-limit runs with a router rate limit (Zenoh downsampling) of "
                         "this many puts per second on every agent key (swarmrt.security.rate_limits)")
    a = ap.parse_args()
    sc = load_scenario(a.scenario, [f"duration_s={a.duration}", "emulator.security=true"])
    ref = simulate_scenario(sc).summary()
    ref_numbers = json.loads(json.dumps({k: ref.get(k) for k in NUMBERS}))
    work = Path(a.out).with_suffix("")
    rows = []
    # (limits, flood, bytes over the limit): quiet; garbage over the size limit; garbage at it.
    cells = [(True, False, 1), (True, True, 1), (True, True, 0), (False, False, 1), (False, True, 1)]
    if a.rate_limit_hz:
        cells = [(True, False, 1), (True, True, 0)]
    for limits, flood, over in cells:
        name = f"limits-{'on' if limits else 'off'}-" + ("quiet" if not flood else "flood-over" if over else "flood-at-limit")
        if a.rate_limit_hz:
            name += f"-rate-{a.rate_limit_hz:g}hz"
        r = one_run(sc, work / name, limits, flood, over, a.rate_limit_hz)
        r["numbers_equal_in_process"] = r.pop("numbers") == ref_numbers
        rows.append(r)
        rate = f" + rate {a.rate_limit_hz:g} Hz" if a.rate_limit_hz else ""
        print(f"limits {'on ' if limits else 'off'}{rate} {r['flood'] or 'quiet'}: world exit {r['world_exit_code']}, "
              f"{r['wall_s']:.1f} s, {r['puts_sent']} puts ({r['bytes_sent'] / 1e6:.1f} MB) by agent-1's credential, "
              f"recording {r['recording_bytes'] / 1e6:.2f} MB, {r['malformed_recorded']} malformed recorded, "
              f"{r['not_recorded_over_the_flood_cap']} over the recorder's flood cap not recorded, "
              f"numbers equal in-process: {r['numbers_equal_in_process']}", flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"scenario": sc.name, "n_sats": sc.n_sats, "duration_s": a.duration, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
