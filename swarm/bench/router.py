"""``swarm bench router``: how long each role takes to notice that the bus is gone and to
be back on it, measured on real runs (``swarm run``'s processes on loopback).

Two cases, each over several runs (a 4-satellite lockstep swarm with a greedy selector,
the fault at step 8, sent as ``swarm fault`` sends it):

- ``restart``: one router, SIGKILLed and started again on the same endpoint after
  ``down_s`` (restart-router). *notice* = a role's "bus lost" log line − the kill;
  *back* = its "bus back" log line − the new router's "listening" log line; *resumed* =
  the recorder's receipt of the first clock of a step the world had not begun when the
  router was killed − that same moment.
- ``failover``: two meshed routers, router 0 SIGKILLed for good (kill-router). The roles
  connected to it notice and are on router 1 again; *back* counts from the kill.

The times come from each role's log (millisecond timestamps, one clock: one host) and from
the recording; the supervisor notes when it killed and restarted the router.
"""

from __future__ import annotations

import re
import statistics
import threading
import time
from datetime import datetime
from pathlib import Path

__all__ = ["bench_router"]

_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) (\S+) WARNING bus (lost|back)")


def _events(log: Path) -> list[tuple[float, str]]:
    """(Unix time, "lost" | "back") of every bus line of a role's log."""
    out = []
    for line in log.read_text(errors="replace").splitlines():
        m = _LINE.match(line)
        if m:
            out.append((datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp(), m.group(3)))
    return out


def _listening(log: Path) -> list[float]:
    """Unix times of a router log's "listening on" lines (each start of the router)."""
    out = []
    for line in log.read_text(errors="replace").splitlines():
        if " listening on " in line:
            out.append(datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp())
    return out


def _role(name: str) -> str:
    return "agent" if name.startswith("agent-") else name


def _one(case: str, i: int, workdir: Path, down_s: float) -> dict:
    import zenoh

    from swarm.record.mcaplog import iter_messages
    from swarm.supervise.faults import send_fault
    from swarm.supervise.launch import LocalSwarm
    from swarmcore.scenario import Scenario
    from swarmrt.bus.messages import Clock, Keys

    sc = Scenario(name=f"bench-router-{case}", seed=i, n_sats=4, duration_s=20,
                  selection={"strategy": "greedy", "budget": 4}, emulator={"step_timeout_s": 20.0})
    out = workdir / f"{case}-{i}"
    sw = LocalSwarm(sc, out, log=lambda s: None, routers=2 if case == "failover" else 1)

    def during():
        reached = threading.Event()
        with zenoh.open(sw.bus_as("observer").zenoh_config()) as s:
            def on_clock(smp) -> None:
                if Clock.FromString(smp.payload.to_bytes()).k >= 8:
                    reached.set()

            sub = s.declare_subscriber(Keys(sw.run).clock(), on_clock)
            reached.wait(120)
            sub.undeclare()
        if case == "restart":
            send_fault(run_dir=out, action="restart-router", target=0, down_s=down_s)
        else:
            send_fault(run_dir=out, action="kill-router", target=0)

    th = threading.Thread(target=during, daemon=True)
    try:
        sw.start()
        th.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
        th.join(60)
    [f] = sw.router_faults
    t_kill = f["t_down_unix_s"]
    t_ref = t_kill
    if case == "restart":
        # The new router listens a moment before it says READY: its own log line counts.
        ups = [t for t in _listening(out / "logs" / "router.log") if t >= t_kill]
        t_ref = ups[0] if ups else f["t_up_unix_s"]
    row: dict = {"case": case, "run": i, "world_exit": code, "notice_ms": {}, "back_ms": {}}
    for log in sorted((out / "logs").glob("*.log")):
        if log.stem.startswith("router"):
            continue
        ev = [(t, kind) for t, kind in _events(log) if t >= t_kill - 0.01]
        lost = next((t for t, kind in ev if kind == "lost"), None)
        back = next((t for t, kind in ev if kind == "back" and lost is not None and t >= lost), None)
        if lost is not None:
            row["notice_ms"][log.stem] = round((lost - t_kill) * 1e3, 1)
        if back is not None:
            row["back_ms"][log.stem] = round((back - t_ref) * 1e3, 1)
    # The run resumed: the recorder's first clock of a step the world had not yet published
    # when the router was killed (publish time: the world's own Zenoh timestamp).
    clocks = [(Clock.FromString(data).k, pub_ns / 1e9, log_ns / 1e9)
              for topic, _schema, data, log_ns, pub_ns in iter_messages(out / "run.mcap") if topic.endswith("/clock")]
    last_k = max((k for k, pub, _log in clocks if pub < t_kill), default=None)
    resumed = min((log for k, _pub, log in clocks if last_k is not None and k > last_k), default=None)
    row["resumed_ms"] = None if resumed is None else round((resumed - t_ref) * 1e3, 1)
    return row


def bench_router(runs: int = 5, down_s: float = 1.0, workdir: Path = Path("runs/bench/router-runs"), log=print) -> dict:
    rows = []
    for case in ("restart", "failover"):
        for i in range(runs):
            t0 = time.monotonic()
            r = _one(case, i, Path(workdir), down_s)
            rows.append(r)
            log(f"{case} run {i}: world exit {r['world_exit']}, notice {r['notice_ms']}, back {r['back_ms']}, "
                f"resumed {r['resumed_ms']} ms ({time.monotonic() - t0:.0f} s)")
    medians: dict = {}
    for case in ("restart", "failover"):
        mine = [r for r in rows if r["case"] == case]
        per: dict = {}
        for what in ("notice_ms", "back_ms"):
            pooled: dict[str, list[float]] = {}
            for r in mine:
                for name, v in r[what].items():
                    pooled.setdefault(_role(name), []).append(v)
            for role, vals in pooled.items():
                per.setdefault(role, {})[what.replace("_ms", "_median_ms")] = round(statistics.median(vals), 1)
                per[role]["n"] = len(vals)
        res = [r["resumed_ms"] for r in mine if r["resumed_ms"] is not None]
        medians[case] = {"roles": per, "resumed_median_ms": round(statistics.median(res), 1) if res else None,
                         "runs": len(mine), "all_completed": all(r["world_exit"] == 0 for r in mine)}
    return {"down_s": down_s, "medians": medians, "rows": rows}
