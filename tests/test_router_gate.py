"""The router's ingress gate (swarm.supervise.gate): a rate limit per identity with a burst
allowance, that holds a sender back instead of dropping (issue 35).

Unit: the bucket (a clock given, no waiting) and the sizing. Integration: a real router
(``python -m swarm.supervise.router --gate PLAN``) on loopback with the run's keys, real
sessions with real credentials: a flood through agent 1's port reaches the subscriber at no
more than the bucket allows, while every put of an honest agent on its own port arrives;
and a real local swarm run goes through the gate with its numbers equal to ``swarm sim``'s
and nobody honest held back.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from forgery import _open, end_router

from swarm.supervise.gate import OTHER, Entry, _Bucket, gate_limits, gate_message_limits, merged_counts, read_plan, write_plan
from swarmcore.scenario import Emulator
from swarmrt.bus import messages as M
from swarmrt.protocol import outbox_steps
from swarmrt.security import agent_identities, make_keys, size_limit_of

RUN = "gate-1"


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_bucket_lets_a_burst_through_then_the_rate():
    clock = _Clock()
    b = _Bucket(rate=1000.0, burst=5000.0, clock=clock)
    assert [b.charge(1000) for _ in range(5)] == [0.0] * 5  # the burst, at once
    assert b.charge(500) == pytest.approx(0.5)  # 500 bytes below zero: half a second at 1000 B/s
    clock.t += 0.5
    assert b.charge(1000) == pytest.approx(1.0)  # back at zero, 1000 more: one second
    clock.t += 100.0  # a long quiet: full again, never above the burst
    assert b.charge(5000) == 0.0 and b.charge(1) > 0.0


def test_an_unlimited_bucket_never_holds():
    b = _Bucket(rate=float("inf"), burst=float("inf"), clock=_Clock())
    assert all(b.charge(64 * 1024) == 0.0 for _ in range(1000))


@pytest.mark.parametrize("n_sats", [4, 100])
def test_the_gate_is_sized_from_the_scenarios_size_limits(n_sats):
    lag = 4
    names = [*M.IDENTITIES, *agent_identities(n_sats)]
    limits = gate_limits(n_sats, lag, False, names, steps_per_s=50.0)
    # An agent puts a measurement batch (counted as an estimate), an estimate, a health
    # report and fault reports: its step budget is their size limits.
    budget = 2 * size_limit_of("est", n_sats) + size_limit_of("health", n_sats) + size_limit_of("fault", n_sats)
    assert limits["agent-3"] == (50.0 * budget, (lag + 3) * budget)
    # What a role sends at once when its bus comes back (its last lag + 2 steps, all at the
    # size limits) fits in its burst, with a step to spare.
    assert outbox_steps(Emulator(recorder_max_lag_steps=lag)) * budget < limits["agent-3"][1]
    # The world's radio and images are unbounded: the world is never held back.
    assert limits["world"] == (float("inf"), float("inf"))
    assert all(0 < r < float("inf") and 0 < b < float("inf") for name, (r, b) in limits.items() if name != "world")


def test_counts_of_every_router_add_up(tmp_path):
    (tmp_path / "gate-router.json").write_text(json.dumps({"agent-1": {"bytes_in": 10, "held": 1, "held_s": 0.5}}))
    (tmp_path / "gate-router-1.json").write_text(json.dumps({"agent-1": {"bytes_in": 5, "held": 0, "held_s": 0.25},
                                                             "world": {"bytes_in": 7}}))
    (tmp_path / "gate-broken.json").write_text("{not json")
    got = merged_counts(sorted(tmp_path.glob("gate-*.json")))
    assert got == {"agent-1": {"bytes_in": 15, "held": 1, "held_s": 0.75}, "world": {"bytes_in": 7}}


@pytest.fixture
def gated_router(tmp_path):
    """A real router behind a gate: agent 1's buckets small (200 kB/s, 100 kB burst; 200
    messages/s, 100 at once) so a flood shows within a second or two; everyone else as sized
    for a 4-satellite run."""
    keys = make_keys(tmp_path / "keys", 4)
    names = [*(i for i in M.IDENTITIES if i != "mesh"), *agent_identities(4)]
    limits = gate_limits(4, 4, False, names, 50.0)
    limits["agent-1"] = (200e3, 100e3)
    limits[OTHER] = limits["agent-0"]
    msg_limits = gate_message_limits(4, 4, False, names, 50.0)
    msg_limits["agent-1"] = (200.0, 100.0)
    msg_limits[OTHER] = msg_limits["agent-0"]
    sockdir = tmp_path / "s"
    sockdir.mkdir(mode=0o700)
    plan = tmp_path / "plan.json"
    write_plan(plan, [Entry(k, 0, r, b, *msg_limits[k]) for k, (r, b) in limits.items()], str(sockdir / "r.sock"))
    counts = tmp_path / "gate-router.json"
    log = tmp_path / "router.log"
    with log.open("wb") as err:
        p = subprocess.Popen([sys.executable, "-m", "swarm.supervise.router", "--gate", str(plan), "--gate-counts", str(counts),
                              "--keys", str(keys), "--run", RUN, "--n-sats", "4"], stdout=subprocess.PIPE, stderr=err)
    stopped = False

    def stop() -> None:
        nonlocal stopped
        if not stopped:
            stopped = True
            end_router(p, log)

    try:
        assert b"READY" in p.stdout.readline(), log.read_text()
        bound, _ = read_plan(plan)  # the gate wrote back the ports it bound for the plan's 0s
        assert all(e.port > 0 for e in bound) and len({e.port for e in bound}) == len(bound)
        # Below the kernel's ephemeral range: no outgoing connection of the machine can take
        # one while its router is down for a restart.
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
        assert all(e.port < low for e in bound), sorted(e.port for e in bound)
        yield {e.identity: f"tcp/127.0.0.1:{e.port}" for e in bound}, keys, counts, stop, limits, msg_limits
    finally:
        stop()


HONEST = [f"honest {i}".encode() for i in range(20)]


def _honest_puts(session, key: str) -> None:
    """The honest agent's 20 puts, made while (or after) the thief floods."""
    for payload in HONEST:
        session.put(key, payload)


def _all_honest_arrive(got: dict, arrived: threading.Condition) -> None:
    """Wait (30 s at most) until the subscriber has every honest put (it notifies ``arrived``)."""
    with arrived:
        ok = arrived.wait_for(lambda: set(HONEST) <= got["honest"], 30.0)
        assert ok, f"the honest agent's puts did not all arrive: {len(got['honest'])} of {len(HONEST)}"


@pytest.mark.integration
def test_a_flood_is_held_to_its_identitys_rate_and_an_honest_agent_still_gets_through(gated_router):
    ports, keys, counts, stop, limits, _ = gated_router
    k = M.Keys(RUN)
    rate, burst = limits["agent-1"]
    payload = b"\xff" * 60_000  # under est's size limit: the router's size filter lets it through
    got = {"flood_bytes": 0, "honest": set()}
    first_flood = threading.Event()
    lock = threading.Condition()

    def on_sample(sample) -> None:
        with lock:
            if str(sample.key_expr) == k.est(1):
                got["flood_bytes"] += len(sample.payload.to_bytes())
                first_flood.set()
            else:
                got["honest"].add(sample.payload.to_bytes())
                lock.notify_all()

    with _open(ports["recorder"], str(keys / "recorder.json")) as rec, \
            _open(ports["agent-1"], str(keys / "agent-1.json")) as thief, \
            _open(ports["agent-2"], str(keys / "agent-2.json")) as honest:
        sub = rec.declare_subscriber(k.est(), on_sample)
        # A subscription takes a moment to reach the router: put until the first arrives.
        pub = thief.declare_publisher(k.est(1), congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 30
        while not first_flood.is_set() and time.monotonic() < deadline:
            pub.put(payload)
            first_flood.wait(0.05)
        assert first_flood.is_set(), "nothing of agent 1's reached the recorder"
        # The flood, from its own thread, for 3 s of wall time; the honest agent puts 20
        # messages meanwhile.
        t0 = time.monotonic()
        stop_flood = threading.Event()

        def flood() -> None:
            while not stop_flood.is_set() and time.monotonic() - t0 < 3.0:
                pub.put(payload)

        th = threading.Thread(target=flood, daemon=True)
        th.start()
        _honest_puts(honest, k.est(2))
        th.join(60)
        stop_flood.set()
        elapsed = time.monotonic() - t0
        _all_honest_arrive(got, lock)
        sub.undeclare()
    stop()
    c = json.loads(counts.read_text())
    # What came in through agent 1's port: never more than the burst, the rate for as long
    # as the connection lived (bounded by the whole test: the flood's 3 s and the probing
    # before it, 30 s at most), and one read beyond.
    assert c["agent-1"]["held"] > 0 and c["agent-1"]["held_s"] > 0, c["agent-1"]
    assert c["agent-1"]["bytes_in"] <= burst + rate * (elapsed + 35) + 64 * 1024, c["agent-1"]
    # The flood offered far more than that in 3 s (a loopback session puts hundreds of MB/s):
    # what the subscriber got is what the gate let in.
    assert got["flood_bytes"] <= c["agent-1"]["bytes_in"]
    assert c["agent-2"]["held"] == 0 and c["recorder"]["held"] == 0


def _tiny_flood(recorder, thief, honest_agent):
    """Agent 1's credential (``thief``: endpoint, credential file) floods tiny puts on its
    estimate at full speed for 2 s while the recorder subscribes and agent 2 puts its 20
    honest messages; returns what arrived ({"flood": count, "honest": payloads}), its lock,
    and how many puts were offered. Every honest put arrives (or it fails)."""
    k = M.Keys(RUN)
    got = {"flood": 0, "honest": set()}
    first_flood = threading.Event()
    lock = threading.Condition()

    def on_sample(sample) -> None:
        with lock:
            if str(sample.key_expr) == k.est(1):
                got["flood"] += 1
                first_flood.set()
            else:
                got["honest"].add(sample.payload.to_bytes())
                lock.notify_all()

    with _open(recorder[0], str(recorder[1])) as rec, _open(thief[0], str(thief[1])) as flooder, \
            _open(honest_agent[0], str(honest_agent[1])) as honest:
        sub = rec.declare_subscriber(k.est(), on_sample)
        pub = flooder.declare_publisher(k.est(1))
        deadline = time.monotonic() + 30
        while not first_flood.is_set() and time.monotonic() < deadline:
            pub.put(b"\x01")
            first_flood.wait(0.05)
        assert first_flood.is_set(), "nothing of agent 1's reached the recorder"
        offered = 0
        t_flood = time.monotonic()
        while time.monotonic() - t_flood < 2.0:  # a flood at full speed: 2 s of tiny puts
            for _ in range(1000):
                pub.put(b"\x02")
            offered += 1000
        _honest_puts(honest, k.est(2))
        _all_honest_arrive(got, lock)
        sub.undeclare()
    return got, lock, offered


@pytest.mark.integration
def test_a_flood_of_tiny_puts_is_held_by_its_message_count(gated_router):
    """Tiny puts stay far under any byte rate an honest role needs, but each costs every
    receiver: the gate counts Zenoh messages too. A batch of more messages than the
    identity's whole burst (what a flood at full speed sends: the client packs thousands of
    tiny puts into one) is not relayed and its connection is cut; in all, no more messages
    come in than the burst, the rate for as long as the test lasts, and that one batch."""
    ports, keys, counts, stop, _, msg_limits = gated_router
    rate, burst = msg_limits["agent-1"]
    t0 = time.monotonic()
    got, lock, offered = _tiny_flood((ports["recorder"], keys / "recorder.json"), (ports["agent-1"], keys / "agent-1.json"),
                                     (ports["agent-2"], keys / "agent-2.json"))
    elapsed = time.monotonic() - t0
    stop()
    c = json.loads(counts.read_text())["agent-1"]
    assert c["unparsed"] == 0, c
    assert c["cut"] > 0 or c["held_for_messages"] > 0, c  # the flood met the message limit
    # Relayed: each connection's burst (a connection after a cut only once a burst has
    # refilled: burst / rate later), and the rate.
    assert c["messages_in"] <= burst * (1 + elapsed * rate / burst) + rate * elapsed, (c, offered)
    with lock:
        assert got["flood"] <= c["messages_in"] < offered / 10, (got["flood"], c, offered)
    others = json.loads(counts.read_text())
    assert others["agent-2"]["held"] == 0 and others["agent-2"]["cut"] == 0 and others["recorder"]["held"] == 0


@pytest.fixture
def handshake_router(tmp_path):
    """A real router as compose runs it: ``--gate-listen`` on one TCP and one TLS port, every
    identity at both, each known by its handshake; sized from a 4-satellite scenario."""
    from swarm.supervise.launch import free_port
    from swarmrt.scenario_files import load_scenario

    keys = make_keys(tmp_path / "keys", 4, tls_hosts=["localhost", "127.0.0.1"])
    scenario = tmp_path / "sc.yaml"
    scenario.write_text("name: gate-compose\nn_sats: 4\nduration_s: 10\n")
    eps = {"tcp": f"tcp/127.0.0.1:{free_port()}", "tls": f"tls/127.0.0.1:{free_port()}"}
    counts = tmp_path / "gate-router.json"
    log = tmp_path / "router.log"
    with log.open("wb") as err:
        p = subprocess.Popen([sys.executable, "-m", "swarm.supervise.router", "--gate-listen", eps["tcp"], "--gate-listen", eps["tls"],
                              "--gate-counts", str(counts), "--keys", str(keys), "--run", RUN, "--scenario", str(scenario)],
                             stdout=subprocess.PIPE, stderr=err)
    try:
        assert b"READY" in p.stdout.readline(), log.read_text()
        from swarm.supervise.gate import handshake_plan

        plan = handshake_plan(load_scenario(scenario), list(eps.values()), "c", "k")
        assert plan is not None
        yield eps, keys, counts, p, {e.identity: e for e in plan}
    finally:
        end_router(p, log)
    assert not list(tmp_path.glob("swarm-router-gate-*"))


@pytest.mark.integration
def test_one_port_knows_each_identity_by_its_handshake_over_tcp_and_tls(handshake_router):
    """Compose's router: one TCP and one TLS port for everyone. The gate reads each
    connection's identity from its Zenoh handshake and holds it to that identity's buckets:
    agent 1's flood of tiny puts (over TCP) is cut while agent 2 (over TLS, the gate speaking
    TLS with the router's certificate) gets every put through; each identity counted apart,
    a stranger without a credential as ``unidentified``."""
    eps, keys, counts, router, _limits = handshake_router
    with pytest.raises(zenoh.ZError):
        _open(eps["tcp"], timeout_ms=2000)  # a stranger: refused by the router, counted by the gate
    _got, _lock, offered = _tiny_flood((eps["tcp"], keys / "recorder.json"), (eps["tcp"], keys / "agent-1.json"),
                                       (eps["tls"], keys / "agent-2.json"))
    # The world (its messages not limited): once known, its stream is relayed as bytes, not
    # parsed; every one of its 300 clocks arrives.
    k = M.Keys(RUN)
    clocks = threading.Semaphore(0)
    with _open(eps["tcp"], str(keys / "recorder.json")) as rec, _open(eps["tcp"], str(keys / "world.json")) as world:
        sub = rec.declare_subscriber(k.clock(), lambda _s: clocks.release())
        pub = world.declare_publisher(k.clock(), congestion_control=zenoh.CongestionControl.BLOCK)
        clock = M.encode(M.Clock(run=RUN, sender="world", k=1, t_s=1.0, live_agents=[1], mode="lockstep"))
        deadline = time.monotonic() + 30
        while not clocks.acquire(timeout=0.05) and time.monotonic() < deadline:  # until the subscription is in place
            pub.put(clock)
        for _ in range(300):
            pub.put(clock)
        assert all(clocks.acquire(timeout=30) for _ in range(300)), "a clock of the world's was lost"
        sub.undeclare()
    router.terminate()
    router.wait(30)
    # A file of the router process's own beside the path given (compose's folder outlives runs).
    (own,) = counts.parent.glob("gate-router.*.json")
    c = json.loads(own.read_text())
    assert merged_counts([own])["agent-2"]["connections"] >= 1
    print({name: (x["connections"], x["messages_in"], x["cut"], x["held"]) for name, x in c.items()})
    assert c["agent-1"]["cut"] > 0 and c["agent-1"]["unparsed"] == 0, c["agent-1"]
    assert c["agent-1"]["messages_in"] < offered / 10, (c["agent-1"], offered)
    for name in ("agent-2", "recorder"):  # each its own bucket: the thief's cut held nobody else
        assert c[name]["connections"] >= 1 and c[name]["held"] == 0 and c[name]["cut"] == 0, (name, c[name])
    assert c["unidentified"]["connections"] >= 1, c
    assert c["world"]["connections"] >= 1 and c["world"]["messages_in"] < 300 and c["world"]["bytes_in"] > 300 * len(clock), c["world"]
    assert "*" not in c and c["other"]["connections"] == 0, c  # nobody honest left unidentified


@pytest.mark.integration
def test_a_local_run_goes_through_the_gate_with_the_numbers_of_swarm_sim(tmp_path):
    from swarm.api import run, simulate
    from swarmrt.scenario_files import load_scenario

    sc = load_scenario("scenarios/demo.yaml", ["duration_s=8", "emulator.security=true"])
    got = run(sc, out=tmp_path / "run")
    ref = simulate(sc)
    assert got.summary["rms"] == ref.summary["rms"]
    gate = got.summary["router_gate"]
    assert {f"agent-{i}" for i in range(4)} | {"world", "recorder", "supervisor"} <= set(gate)
    assert all(c["held"] == 0 for c in gate.values()), gate  # an honest run is never held back
    # Every message of every limited identity read (none charged at the worst case), none cut.
    assert all(c["unparsed"] == 0 and c["cut"] == 0 for c in gate.values()), gate
    assert all(c["messages_in"] > 0 for name, c in gate.items() if name.startswith("agent-")), gate
    assert all(c["bytes_in"] > 0 for name, c in gate.items() if name.startswith("agent-"))


@pytest.mark.integration
def test_a_claimant_waiting_for_the_world_asks_a_few_times_a_second_not_in_a_spin(handshake_router, tmp_path):
    """``--id auto`` before any world serves claims: its query comes back at once, and it
    asked again at once (seen in compose: 574 queries of four replicas, held back by the
    gate). It now pauses between claims: over 2 s, a dozen queries at most."""
    from sat_agent.node import claim_id
    from swarmrt.bus.session import BusConfig
    from swarmrt.scenario_files import load_scenario

    eps, keys, counts, router, _limits = handshake_router
    sc = load_scenario(tmp_path / "sc.yaml")
    bus = BusConfig(mode="client", connect=[eps["tcp"]], credential_file=str(keys / "claimant.json"))
    with pytest.raises(SystemExit, match="no satellite id from the world"):
        claim_id(sc, RUN, bus, timeout=2.0)
    router.terminate()
    router.wait(30)
    (own,) = counts.parent.glob("gate-router.*.json")
    c = json.loads(own.read_text())["claimant"]
    print(c)
    assert 1 <= c["messages_by_kind"].get("request", 0) <= 2.0 / 0.2 + 2, c
    assert c["held"] == 0, c


def test_reserved_ports_are_below_the_ephemeral_range_and_never_given_twice():
    """A run's gate ports are reserved by the process that writes the plan, for the whole run
    (a router restarted by a fault binds them again): never one another swarm process holds,
    never one of the range the kernel gives outgoing connections; released, free again.
    (Seen without it: 3 router restarts of the 20-seed repeat benchmark beside a test suite
    failed with "address already in use".)"""
    import socket

    from swarm.supervise.gate import PortReservation

    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    a, b = PortReservation(), PortReservation()
    try:
        mine = [a.take() for _ in range(200)]
        theirs = [b.take() for _ in range(200)]
        assert 0 not in mine and len(set(mine)) == 200 and not set(mine) & set(theirs)
        assert max(mine + theirs) < low
        with socket.socket(socket.AF_UNIX) as lock:  # what a reservation holds
            with pytest.raises(OSError):
                lock.bind(f"\0swarm-coloc-port-{mine[0]}")
    finally:
        a.release()
        b.release()
    with socket.socket(socket.AF_UNIX) as lock:  # released: free for the next run
        lock.bind(f"\0swarm-coloc-port-{mine[0]}")
