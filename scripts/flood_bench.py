"""A stolen agent credential floods its own keys for a whole run: what the router's ingress
gate (``swarm.supervise.gate``: a rate limit per identity with a burst allowance) and its size
limits (``swarmrt.security.size_limits``, Zenoh ``low_pass_filter``) change.

For each cell it runs the same lockstep swarm on loopback, security on, the gate on or off
(``SWARM_ROUTER_GATE``): quiet, or while a process holding agent 1's credential, connected
where agent 1 connects, puts as fast as it can on ``est/1`` and ``health/1`` (the keys that
identity may put; every other key the access rules already refuse it) garbage exactly at the
size limits (it passes the router's size filter), one byte over them (the filter drops it), or
16 bytes (the most messages per byte), from before the world starts to the run's end (every
step is flooded; the run's wall is also given from the world's start). The flooder runs at ``--nice`` (19 by default: it
stands for a machine elsewhere, whose CPU the swarm would not share). Printed and written
(``--out``): puts offered and bytes, what the gate let in and how long it held agent 1 back,
whether it held anyone else, the recording's size, malformed messages recorded and over the
recorder's flood cap, the run's wall time, and whether the numbers equal the in-process
run's bit for bit. ``--repeat R`` interleaves the cells R times and reports each cell's median.

    .venv/bin/python scripts/flood_bench.py --duration 10 --repeat 3 --out runs/bench/flood.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from swarm.simulation import simulate_scenario
from swarm.supervise.launch import LocalSwarm
from swarm.supervise.outcome import run_outcome
from swarmrt.bus.messages import Keys
from swarmrt.bus.session import BusConfig
from swarmrt.scenario_files import load_scenario
from swarmrt.security import size_limit_of

NUMBERS = ("rms", "rms_second_half", "per_pair", "nees", "gate")


def _flooder(spec: dict) -> None:
    """The flood, in a process of its own (``--flooder SPEC``): puts as fast as it can until
    SIGTERM, then prints its counts as JSON."""
    sent = {"puts": 0, "bytes": 0}

    def on_term(*_) -> None:
        # Say the counts and go, without closing the session: its queue may be held by the
        # gate, and a close that drains it would lengthen the run's teardown, not the run.
        print(json.dumps(sent), flush=True)
        os._exit(0)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, on_term)
    bus = BusConfig(mode="client", connect=spec["connect"], credential_file=spec["credential"])
    with zenoh.open(bus.zenoh_config()) as s:
        pubs = [(s.declare_publisher(k), bytes([0xFF - i]) * n) for i, (k, n) in enumerate(spec["targets"])]
        first = True
        while not stop.is_set():
            for pub, payload in pubs:
                pub.put(payload)
                sent["puts"] += 1
                sent["bytes"] += len(payload)
            if first:  # the bench starts the world once the flood is on
                print("FLOODING", flush=True)
                first = False
    print(json.dumps(sent), flush=True)


def _start_flooder(sw: LocalSwarm, n_sats: int, over: int | None, nice: int) -> subprocess.Popen:
    """``over``: bytes over each key's size limit (1: every put dropped by the router's size
    filter; 0: at the limit, every put passes it and reaches the recorder, which takes it for
    malformed: its flood cap bounds what it writes); None: tiny puts (16 bytes), the most
    messages per byte. The flooder holds agent 1's credential and connects where agent 1 does."""
    keys = Keys(sw.run)
    if over is None:
        targets = [(keys.est(1), 16), (keys.health(1), 16)]
    else:
        targets = [(keys.est(1), size_limit_of("est", n_sats) + over), (keys.health(1), size_limit_of("health", n_sats) + over)]
    bus = sw.bus_as("agent-1")
    spec = {"connect": bus.connect, "credential": bus.credential_file, "targets": targets}
    return subprocess.Popen([sys.executable, __file__, "--flooder", json.dumps(spec)], stdout=subprocess.PIPE, text=True,
                            preexec_fn=lambda: os.nice(nice))


class _FloodedSwarm(LocalSwarm):
    """A local run whose flood starts before its world does (``before_world``, called once
    as the world is spawned: every step of the run is flooded, not only those after a
    flooder has started up); ``t_world`` is when the world was spawned."""

    before_world: Callable[[], None] | None = None
    t_world: float | None = None

    def _spawn(self, name: str, args: list[str], env_extra: dict[str, str] | None = None) -> subprocess.Popen:
        if name == "world" and self.before_world is not None:
            start, self.before_world = self.before_world, None
            start()
        if name == "world":
            self.t_world = time.monotonic()
        return super()._spawn(name, args, env_extra)


class _CpuCap:
    """The flooder held to a fraction of one core (a cgroup of its own, root only; v1 ``cpu``
    or v2 ``cpu.max``): it stands for a machine elsewhere that sends as fast as its share lets
    it, instead of taking this machine's cores and memory bandwidth from the swarm. Removed
    after the run."""

    def __init__(self, fraction: float):
        self.fraction = fraction
        self.path: Path | None = None

    def add(self, pid: int) -> None:
        period = 100_000
        quota = max(1000, int(period * self.fraction))
        v1 = Path("/sys/fs/cgroup/cpu")
        if v1.is_dir():
            self.path = v1 / f"swarm-flooder-{os.getpid()}-{pid}"
            self.path.mkdir()
            (self.path / "cpu.cfs_period_us").write_text(str(period))
            (self.path / "cpu.cfs_quota_us").write_text(str(quota))
        else:
            self.path = Path("/sys/fs/cgroup") / f"swarm-flooder-{os.getpid()}-{pid}"
            self.path.mkdir()
            (self.path / "cpu.max").write_text(f"{quota} {period}")
        (self.path / "cgroup.procs").write_text(str(pid))

    def remove(self) -> None:
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.rmdir()
            self.path = None


def one_run(sc, out: Path, limits: bool, flood: bool, over: int | None = 1, rate_hz: float | None = None, gate: bool = True,
            nice: int = 19, cpu: float | None = None) -> dict:
    os.environ["SWARM_ROUTER_SIZE_LIMITS"] = "on" if limits else "off"
    os.environ["SWARM_ROUTER_GATE"] = "on" if gate else "off"
    if rate_hz:
        os.environ["SWARM_ROUTER_RATE_LIMIT_HZ"] = f"{rate_hz:g}"
    else:
        os.environ.pop("SWARM_ROUTER_RATE_LIMIT_HZ", None)
    sw = _FloodedSwarm(sc, out, log=lambda s: None)
    cap = _CpuCap(cpu) if cpu is not None else _CpuCap(0.0)
    flooder: subprocess.Popen | None = None
    sent = {"puts": 0, "bytes": 0}
    t0 = t_end = time.monotonic()
    code = None

    flooder_startup_s = 0.0

    def start_flood() -> None:
        nonlocal flooder, flooder_startup_s
        t = time.monotonic()
        flooder = _start_flooder(sw, sc.n_sats, over, nice)
        if cpu is not None:
            cap.add(flooder.pid)
        assert flooder.stdout is not None
        line = flooder.stdout.readline()  # its first puts are out (or it died: an empty line)
        if line.strip() != "FLOODING":
            raise RuntimeError(f"the flooder did not start flooding (it said {line!r})")
        # The bench waits here, with the swarm's start-up paused before its world, for its own
        # flooder to start (an interpreter, Zenoh, a session, its first puts): not the swarm's
        # time; the whole run's wall is also given without it (wall_s_swarm).
        flooder_startup_s = time.monotonic() - t

    try:
        if flood:
            sw.before_world = start_flood
        sw.start()
        code = sw.run_to_end(timeout=1800)
        t_end = time.monotonic()  # the run's end: the flooder's and the processes' teardown after it are not the run
    finally:
        if flooder is not None:
            flooder.terminate()
            try:
                sent = json.loads(flooder.communicate(timeout=30)[0] or "{}") or sent
            except (subprocess.TimeoutExpired, ValueError):
                flooder.kill()
                flooder.wait()
        cap.remove()
        sw.stop()
    wall = (t_end if code is not None else time.monotonic()) - t0
    steps_wall = None if sw.t_world is None or code is None else t_end - sw.t_world
    summary = run_outcome(sc, out / "run.mcap", run=sw.run, world_exit_code=code, interrupted=sw.interrupted, broken=sw.broken,
                          broken_code=sw.broken_code, router_faults=sw.router_faults).summary
    gate_counts = sw.gate_counts()
    what = None if not flood else "tiny puts" if over is None else "over the limit" if over > 0 else "at the limit"
    return {"limits": limits, "gate": gate, "rate_limit_hz": rate_hz, "flood": what, "flooder_nice": nice if flood else None,
            "flooder_cpu": cpu if flood else None,
            "world_exit_code": code, "wall_s": round(wall, 2), "flooder_startup_s": round(flooder_startup_s, 2),
            "wall_s_swarm": round(wall - flooder_startup_s, 2),
            "world_wall_s": None if steps_wall is None else round(steps_wall, 2),
            "puts_sent": sent["puts"], "bytes_sent": sent["bytes"],
            "recording_bytes": (out / "run.mcap").stat().st_size if (out / "run.mcap").exists() else None,
            "malformed_recorded": summary.get("messages", {}).get("_malformed", 0),
            "not_recorded_over_the_flood_cap": sum(summary.get("messages", {}).get("not_recorded_over_the_flood_cap", {}).values()),
            "gate_agent_1": gate_counts.get("agent-1"),
            "gate_held_others": {k: c["held"] for k, c in gate_counts.items() if k != "agent-1" and c.get("held")},
            "numbers": {k: summary.get(k) for k in NUMBERS}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="scenarios/demo.yaml")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--out", default="runs/bench/flood.json", help="the JSON file the results go to")
    ap.add_argument("--repeat", type=int, default=1, help="run the whole list of cells this many times, interleaved "
                    "(a busy machine's drift falls on every cell alike); the table gives each cell's median")
    ap.add_argument("--nice", type=int, default=19, help="the flooder's nice value (19: it stands for a machine elsewhere, "
                    "whose CPU this one's swarm would not share; 0: it competes for this machine's cores)")
    ap.add_argument("--flooder-cpu", type=float, default=None, help="hold the flooder to this fraction of one core "
                    "(a cgroup of its own; root): a sender elsewhere, as fast as its share lets it")
    ap.add_argument("--rate-limit-hz", type=float, default=None,
                    help="instead: the quiet and the at-the-limit runs, gate off, with a router rate limit (Zenoh "
                         "downsampling) of this many puts per second on every agent key (swarmrt.security.rate_limits)")
    ap.add_argument("--flooder", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if Path(a.out).is_dir():  # checked before the minutes of runs, not after them
        ap.error(f"--out {a.out}: a directory; give the JSON file's path (e.g. {Path(a.out) / 'flood.json'})")
    if a.flooder:
        _flooder(json.loads(a.flooder))
        return
    # SIGTERM ends the bench as Ctrl-C does: through the finally blocks (the swarm stopped,
    # the flooder ended, its cgroup removed), not by dying with them left behind.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    sc = load_scenario(a.scenario, [f"duration_s={a.duration}", "emulator.security=true"])
    ref = simulate_scenario(sc).summary()
    ref_numbers = json.loads(json.dumps({k: ref.get(k) for k in NUMBERS}))
    work = Path(a.out).with_suffix("")
    rows = []
    # (gate, flood, bytes over the limit or None for tiny puts), router size limits on.
    cells = [(False, False, 1), (False, True, 0), (False, True, None),
             (True, False, 1), (True, True, 0), (True, True, None), (True, True, 1)]
    if a.rate_limit_hz:
        cells = [(False, False, 1), (False, True, 0)]
    for rep in range(a.repeat):
        for gate, flood, over in cells:
            what = "quiet" if not flood else "flood-tiny" if over is None else "flood-over" if over else "flood-at-limit"
            name = f"gate-{'on' if gate else 'off'}-{what}" + (f"-rate-{a.rate_limit_hz:g}hz" if a.rate_limit_hz else "") + f"-{rep}"
            r = one_run(sc, work / name, True, flood, over, a.rate_limit_hz, gate=gate, nice=a.nice, cpu=a.flooder_cpu)
            r["numbers_equal_in_process"] = r.pop("numbers") == ref_numbers
            r["repeat"] = rep
            rows.append(r)
            held = r["gate_agent_1"] or {}
            print(f"gate {'on ' if gate else 'off'} {r['flood'] or 'quiet'}: world exit {r['world_exit_code']}, {r['wall_s']:.1f} s, "
                  f"{r['puts_sent']} puts ({r['bytes_sent'] / 1e6:.1f} MB) by agent-1's credential, gate held agent-1 "
                  f"{held.get('held', 0)} times ({held.get('held_s', 0):.1f} s), others held {r['gate_held_others'] or 0}, "
                  f"recording {r['recording_bytes'] / 1e6:.2f} MB, {r['malformed_recorded']} malformed recorded, "
                  f"{r['not_recorded_over_the_flood_cap']} over the flood cap, numbers equal in-process: "
                  f"{r['numbers_equal_in_process']}", flush=True)
    table: dict[str, list[float]] = {}
    swarm: dict[str, list[float]] = {}
    world: dict[str, list[float]] = {}
    for r in rows:
        cell = f"gate {'on' if r['gate'] else 'off'}, {r['flood'] or 'quiet'}"
        table.setdefault(cell, []).append(r["wall_s"])
        swarm.setdefault(cell, []).append(r["wall_s_swarm"])
        if r["world_wall_s"] is not None:
            world.setdefault(cell, []).append(r["world_wall_s"])
    print("median wall (s) per cell: the whole run / the whole run without the bench's wait for its flooder to start / "
          "from the world's start (the flood already on) to the run's end:")
    for k, v in table.items():
        w = world.get(k, [])
        print(f"  {k}: {statistics.median(v):.2f} / {statistics.median(swarm[k]):.2f} / {statistics.median(w) if w else float('nan'):.2f} "
              f"(of {', '.join(f'{x:.2f}' for x in v)} / {', '.join(f'{x:.2f}' for x in swarm[k])} / {', '.join(f'{x:.2f}' for x in w)})")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"scenario": sc.name, "n_sats": sc.n_sats, "duration_s": a.duration, "flooder_nice": a.nice,
                                       "flooder_cpu": a.flooder_cpu,
                                       "median_wall_s": {k: statistics.median(v) for k, v in table.items()},
                                       "median_wall_s_swarm": {k: statistics.median(v) for k, v in swarm.items()},
                                       "median_world_wall_s": {k: statistics.median(v) for k, v in world.items()}, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
