"""A Zenoh router in Python (the bus of a swarm; no plugins needed).

python -m swarm.supervise.router --listen tcp/0.0.0.0:7447 --keys DIR --run RUN --scenario FILE

With ``--keys`` (a keys directory of ``swarm keys``, or the one ``swarm run`` makes) the
router authenticates every session and enforces run RUN's access rules, generated from
the key space (:mod:`swarmrt.security`); the scenario says how many satellites and whether
the radio is on (``emulator.security: off`` there, or no ``--keys``, leaves the bus open,
with a warning).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import sys
import threading
from pathlib import Path

import zenoh


def _raise_open_files(n_entries: int) -> None:
    """A gate listens on a port per identity and holds two sockets per connection: at 1,000
    satellites more than the usual soft limit of 1,024 open files. Raised to the hard limit."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = 4 * n_entries + 256
    if soft != resource.RLIM_INFINITY and soft < want:
        new = want if hard == resource.RLIM_INFINITY else min(want, hard)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Zenoh router for a swarm")
    p.add_argument("--listen", action="append", default=None, help="endpoint, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p.add_argument("--connect", action="append", default=None,
                   help="another router's endpoint to mesh with (repeatable): clients given both endpoints fail over")
    p.add_argument("--config", default=None, help="a Zenoh JSON5 configuration file")
    p.add_argument("--exit-when-done", metavar="RUN", default=None, help="exit once run RUN's world reports its last step (and the recorder has left)")
    p.add_argument("--keys", default=None, help="keys directory (swarm keys): authenticate every session, enforce the run's access rules")
    p.add_argument("--run", default=None, help="the run whose access rules to enforce (default: --exit-when-done's)")
    p.add_argument("--scenario", default=None, help="the run's scenario (its size, radio and emulator.security; SWARM_SET applies)")
    p.add_argument("--n-sats", type=int, default=None, help="the swarm's size, without --scenario")
    p.add_argument("--links", action="store_true", help="the radio is on (without --scenario)")
    p.add_argument("--index", type=int, default=0, help="this router's place in a mesh (0, 1, ...; with --keys: its fixed "
                   "Zenoh id, and its peers', which its access rules let through)")
    p.add_argument("--gate", metavar="PLAN", default=None,
                   help="an ingress gate plan (JSON, swarm.supervise.gate): listen only on the plan's Unix socket and let "
                        "the gate, at one port per identity, rate-limit what each identity sends in")
    p.add_argument("--gate-listen", metavar="ENDPOINT", action="append", default=None,
                   help="listen here (tcp/HOST:PORT or tls/HOST:PORT, repeatable) through an ingress gate that knows each "
                        "connection's identity from its Zenoh handshake and rate-limits what it sends in, sized from --scenario "
                        "(a TLS endpoint speaks TLS with the router's certificate); the router itself listens on a private "
                        "Unix socket only. Compose's router. Needs --keys and --scenario")
    p.add_argument("--gate-counts", metavar="FILE", default=None,
                   help="where the gate writes its counts per identity (JSON; with --gate-listen a file of this process's "
                        "own beside it, NAME.<start ms>.json, so that a folder reused by the next run never adds its counts up)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s router %(levelname)s %(message)s", stream=sys.stderr)
    cfg = zenoh.Config.from_file(a.config) if a.config else zenoh.Config()
    cfg.insert_json5("mode", json.dumps("router"))
    gate = None
    listen = a.listen or ["tcp/0.0.0.0:7447"]
    if a.gate:
        from swarm.supervise.gate import Gate, read_plan, write_plan

        entries, upstream = read_plan(a.gate)
        _raise_open_files(len(entries))
        Path(upstream).unlink(missing_ok=True)  # ours: a killed predecessor's socket file
        listen = [f"unixsock-stream/{upstream}", *(a.listen or [])]
        gate = Gate(entries, upstream)
    elif a.gate_listen:
        gate, upstream = _handshake_gate(a, p)
        if gate is not None:
            listen = [f"unixsock-stream/{upstream}", *(a.listen or [])]
        else:  # the gate off (emulator.gate: false): the router listens there itself
            listen = [*a.gate_listen, *(a.listen or [])]
    cfg.insert_json5("listen/endpoints", json.dumps(listen))
    if a.connect:
        cfg.insert_json5("connect/endpoints", json.dumps(a.connect))
        # Keep trying: the other router may start later, or come back after a fault.
        cfg.insert_json5("connect/timeout_ms", "-1")
        cfg.insert_json5("connect/retry", json.dumps({"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    from swarmrt.bus.session import apply_shared_memory

    apply_shared_memory(cfg)
    _secure(cfg, a, p)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with zenoh.open(cfg) as session:
        logging.info("router %s listening on %s", session.zid(), listen)
        counts = None
        if gate is not None:
            from swarm.supervise.gate import CountsFile

            gate.start()
            if a.gate:
                write_plan(a.gate, gate.entries, gate.upstream)  # the ports it bound, for the supervisor and a restart
            logging.info("ingress gate: %s", ", ".join(f"{e.identity} on {e.port}" for e in gate.entries[:4])
                         + (f" and {len(gate.entries) - 4} more" if len(gate.entries) > 4 else ""))
            counts = CountsFile(gate, a.gate_counts, own=bool(a.gate_listen)) if a.gate_counts else None
        handles = []
        if a.exit_when_done:
            handles = _watch_run(session, a.exit_when_done, stop, _world_hold_s(a.scenario))
        print("READY", flush=True)
        # Wake now and then: the kernel may deliver SIGTERM to one of Zenoh's threads, and
        # then a wait without a timeout in this thread never returns to run the handler
        # (seen: a router that outlived its test by minutes, the signal caught, never handled).
        ticks = 0
        while not stop.wait(0.5):
            ticks += 1
            if counts is not None and ticks % 2 == 0:
                counts.write()
        if counts is not None:
            counts.write()
        if gate is not None:
            gate.stop()
        for h in handles:
            h.undeclare()
    return 0


def _handshake_gate(a, p):
    """The gate of ``--gate-listen`` (:func:`swarm.supervise.gate.handshake_plan`) and the
    router's Unix socket, in a private directory of its own (removed at exit); (None, None)
    when the scenario turns the gate off."""
    import atexit
    import shutil
    import tempfile

    from swarm.supervise.gate import Gate, handshake_plan
    from swarmrt.node import load_role_scenario
    from swarmrt.security import load_router_keys

    if not (a.keys and a.scenario):
        p.error("--gate-listen needs --keys and --scenario (the gate is sized from the scenario and knows the run's identities)")
    meta, _, _ = load_router_keys(a.keys)
    cert = str((Path(a.keys) / meta["certificate"]).resolve()) if "certificate" in meta else ""
    key = str((Path(a.keys) / meta["private_key"]).resolve()) if "private_key" in meta else ""
    sc = load_role_scenario(a.scenario)
    if not sc.emulator.security:
        logging.warning("no ingress gate: emulator.security is off (no identities to hold apart)")
        return None, None
    try:
        entries = handshake_plan(sc, a.gate_listen, cert, key)
    except ValueError as exc:
        p.error(str(exc))
    if entries is None:
        return None, None
    _raise_open_files(len(entries))
    d = tempfile.mkdtemp(prefix="swarm-router-gate-")  # 0700
    atexit.register(shutil.rmtree, d, True)
    upstream = str(Path(d) / "r.sock")
    return Gate(entries, upstream, host="0.0.0.0"), upstream


def _secure(cfg, a, p) -> None:
    n, links, on = a.n_sats, a.links, True
    if a.scenario:
        from swarmrt.node import load_role_scenario

        sc = load_role_scenario(a.scenario)
        n, links, on = sc.n_sats, sc.links.enabled, sc.emulator.security
    run = a.run or a.exit_when_done
    if not on or not a.keys:
        why = "emulator.security is off in the scenario" if not on else "no --keys given"
        logging.warning("SECURITY OFF (%s): no authentication, no access control; any process that reaches this "
                        "router may publish anything, fault commands included", why)
        return
    if run is None or n is None:
        p.error("--keys needs the run (--run) and the swarm's size (--scenario or --n-sats)")
    from swarmrt.security import apply_router_security

    tls = apply_router_security(cfg, a.keys, run, n, links, index=a.index)
    logging.info("security on: user/password authentication, access rules of run %s (%d satellites%s)%s",
                 run, n, ", radio" if links else "", ", TLS certificate loaded" if tls else "")


def _world_hold_s(scenario: str | None) -> float:
    """How long the world's token may be gone before the run is over: the scenario's
    ``emulator.bus_lost_after_s`` (the world may only be stalled, SIGSTOP or ``docker
    pause``: its session dropped at the lease, it comes back; everyone else waits as long),
    30 s without a scenario."""
    if not scenario:
        return 30.0
    from swarmrt.node import load_role_scenario

    return float(load_role_scenario(scenario).emulator.bus_lost_after_s)


def _watch_run(session, run: str, stop: threading.Event, world_hold_s: float = 30.0):
    """Stop when the run's world has said ``done`` (or is gone: a broken run) and no
    recorder is alive any more."""
    from swarmrt.bus.messages import Keys, MessageError
    from swarmrt.bus.receive import receive

    keys = Keys(run)
    state = {"done": False, "world": False}
    recorders: set[str] = set()  # the run's live recorders' tokens
    lock = threading.Lock()

    def world_gone() -> None:
        with lock:
            if not state["world"] and not state["done"]:
                logging.info("run %s: the world is gone", run)
                state["done"] = True
                check()

    def on_world(sample):
        with lock:
            state["world"] = sample.kind == zenoh.SampleKind.PUT
        if sample.kind != zenoh.SampleKind.PUT:
            t = threading.Timer(world_hold_s, world_gone)
            t.daemon = True
            t.start()

    def check():
        if state["done"] and not recorders:
            logging.info("run %s is over; router exits", run)
            stop.set()

    def on_clock(sample):
        try:
            msg = receive(str(sample.key_expr), sample.payload.to_bytes(), run, expect="clock").msg
        except MessageError:
            return
        if msg.done:
            with lock:
                state["done"] = True
                check()

    def on_alive(sample):
        key = str(sample.key_expr)
        with lock:
            if sample.kind == zenoh.SampleKind.PUT:
                recorders.add(key)
            else:
                recorders.discard(key)
            check()

    return [
        session.declare_subscriber(keys.clock(), on_clock),
        session.liveliness().declare_subscriber(keys.alive("recorder"), on_alive, history=True),
        session.liveliness().declare_subscriber(keys.alive("world"), on_world, history=True),
    ]


if __name__ == "__main__":
    sys.exit(main())
