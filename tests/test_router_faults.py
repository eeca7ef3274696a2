"""The bus can fail too (issue 16): a Zenoh router killed and restarted mid-run, killed for
good, two meshed routers with one killed, and a world that dies.

Real processes on real loopback routers (``swarm run``'s supervisor, or `swarm run` itself
as a subprocess); waits are on bus events (the world's clock) or on processes ending, each
with a bound.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import psutil
import pytest
import yaml
import zenoh
from swarm_harness import scenario
from test_run_signals import _gone, _read_json, wait_until

from swarm.record.recording import load_recording
from swarm.supervise.faults import send_fault
from swarm.supervise.launch import LocalSwarm
from swarmcore.sim import simulate
from swarmrt.bus.messages import Clock, Keys
from swarmrt.bus.session import BusConfig

pytestmark = pytest.mark.integration

EQUAL_KEYS = ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean")


def _wait_step(endpoints: list[str], run: str, k: int, keys: str | None, timeout: float = 180.0) -> None:
    reached = threading.Event()
    cred = f"{keys}/observer.json" if keys else None  # the run's read-only identity (security on)
    with zenoh.open(BusConfig(mode="client", connect=endpoints, credential_file=cred).zenoh_config()) as s:
        sub = s.declare_subscriber(Keys(run).clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= k and reached.set())
        try:
            assert reached.wait(timeout), f"the run did not reach step {k} within {timeout:.0f} s"
        finally:
            sub.undeclare()


def _run_with_router_fault(tmp_path, routers: int, action: str, target: int, scheduled: bool = False, **fields):
    """A 4-satellite swarm with a greedy selector; at step 8 ``swarm fault`` (the same
    function) sends ``action`` — or the scenario schedules it there. Returns (recording,
    summary, world exit code, the fault command's answer, the scenario)."""
    faults = [{"at_step": 8, "action": action, "target": target, **fields}] if scheduled else []
    sc = scenario(duration_s=20, selection={"strategy": "greedy", "budget": 4}, faults=faults)
    out = tmp_path / "run"
    sw = LocalSwarm(sc, out, log=lambda s: None, routers=routers)
    answer = {}

    def during():
        _wait_step(sw.endpoints, sw.run, 8, str(sw.keys_dir) if sw.keys_dir else None)
        answer["fault"] = send_fault(run_dir=out, action=action, target=target, **fields)

    th = threading.Thread(target=during, daemon=True)
    try:
        sw.start()
        if not scheduled:
            th.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
        if th.is_alive():
            th.join(60)
    rec = load_recording(out / "run.mcap", sc.n_sats, sc.steps)
    return rec, rec.summary(sc), code, answer.get("fault", ""), sc


def _assert_same_numbers_as_without_the_fault(rec, summary, sc):
    res = simulate(sc)  # the distributed run without faults equals this bit for bit (test_integration_swarm)
    np.testing.assert_array_equal(rec.schedule, res.schedule)
    ref = res.summary()
    for key in EQUAL_KEYS:
        assert summary[key] == ref[key], key
    assert summary["steps"] == sc.steps and rec.alive.all() and summary["selector_fallback_steps"] == []


def test_router_restarted_mid_run_same_numbers_gap_recorded(tmp_path):
    """The router is SIGKILLed at step 8 and a new one starts on the same endpoint 1.5 s
    later: every role reconnects, the world waits, what was in flight is sent again — the
    run's numbers equal the fault-free run's, and the recording holds the fault and the gap."""
    rec, summary, code, answer, sc = _run_with_router_fault(tmp_path, 1, "restart-router", 0, down_s=1.5)
    print(answer, summary.get("bus_gaps"), summary["messages"].get("resent_after_gap"))
    assert code == 0 and "done by supervisor" in answer, answer
    _assert_same_numbers_as_without_the_fault(rec, summary, sc)
    [gap] = summary["bus_gaps"]
    assert gap["observer"] == "recorder" and 1.5 <= gap["duration_s"] < 15.0, gap
    assert 8 <= gap["last_step_before"] <= gap["first_step_after"] < sc.steps, gap
    done = [f for f in summary["faults"] if f["action"] == "restart-router" and f["phase"] == "done"]
    assert len(done) == 1 and done[0]["sender"] == "supervisor" and "new router pid" in done[0]["detail"], summary["faults"]


def test_two_meshed_routers_one_killed_the_run_goes_on(tmp_path):
    """`swarm run --routers 2`: router 0 (the one every role connected to first) is killed
    for good at step 8, as the scenario schedules; every role fails over to router 1 and the
    run completes, its numbers equal to the fault-free run's."""
    rec, summary, code, _answer, sc = _run_with_router_fault(tmp_path, 2, "kill-router", 0, scheduled=True)
    print(summary.get("bus_gaps"), summary["faults"])
    assert code == 0
    _assert_same_numbers_as_without_the_fault(rec, summary, sc)
    assert any(f["action"] == "kill-router" and f["phase"] == "done" for f in summary["faults"]), summary["faults"]
    # The failover happened: the recorder's link to router 0 went with it, and the bus came
    # back (through router 1) within seconds, after the kill and before the run's end.
    gaps = summary.get("bus_gaps") or []
    assert gaps, "no bus gap recorded: the recorder never lost router 0, so nothing failed over"
    for g in gaps:
        assert g["duration_s"] is not None and g["duration_s"] < 15.0, g
        assert 7 <= g["last_step_before"] < sc.steps, g


BOUND_S = 5.0  # emulator.bus_lost_after_s of the broken runs
BROKEN = {
    "name": "broken",
    "seed": 4,
    "n_sats": 3,
    "duration_s": 600,
    "selection": {"strategy": "greedy", "budget": 3},
    "emulator": {"lockstep_max_realtime_factor": 10.0, "bus_lost_after_s": BOUND_S},
}


def _break_run(tmp_path, victim: str):
    """`swarm run` as a subprocess; at step 8 SIGKILL ``victim`` (router or world); wait
    until every process of the run is gone. Returns (exit status, seconds until every
    process was gone, summary, output)."""
    scn = tmp_path / "broken.yaml"
    scn.write_text(yaml.safe_dump(BROKEN))
    out = tmp_path / "run"
    log_path = tmp_path / "swarm-run.log"
    with open(log_path, "wb") as log:
        sup = subprocess.Popen([sys.executable, "-m", "swarm.cli", "run", str(scn), "--out", str(out)], stdout=log,
                               stderr=subprocess.STDOUT, env=dict(os.environ, COLUMNS="200"))
        procs = []
        try:
            info = wait_until(lambda: _read_json(out / "run.json"), 180, "run.json written")
            procs = [psutil.Process(pid) for pid in info["pids"].values()]
            _wait_step(info["endpoints"], info["run"], 8, info.get("keys"))
            t0 = time.monotonic()
            os.kill(info["pids"][victim], signal.SIGKILL)
            wait_until(lambda: all(_gone(p) for p in procs), BOUND_S + 20.0, "every process of the run gone")
            gone_s = time.monotonic() - t0
            code = sup.wait(timeout=60)
        finally:
            for p in [*procs, psutil.Process(sup.pid) if sup.poll() is None else None]:
                if p is not None and not _gone(p):
                    p.kill()
            sup.wait(timeout=30)
    text = log_path.read_text()
    print(f"\n{victim} killed: every process gone after {gone_s:.2f} s, `swarm run` exited {code}")
    return code, gone_s, json.loads((out / "summary.json").read_text()), text


def test_router_killed_for_good_the_run_ends_broken(tmp_path):
    code, gone_s, summary, text = _break_run(tmp_path, "router")
    assert code == 3, text[-2000:]
    assert gone_s < BOUND_S + 10.0
    intr = summary["interrupted"]
    assert intr["reason"].startswith("bus lost") and 8 <= intr["last_step"] < 600 and intr["steps_planned"] == 601, intr
    assert summary["steps"] == intr["last_step"] + 1
    assert summary["bus_gaps"][-1]["up_unix_ns"] is None  # marked: it never came back
    assert "BROKEN RUN" in text and "bus lost" in text


def test_world_killed_the_run_ends_broken(tmp_path):
    code, gone_s, summary, text = _break_run(tmp_path, "world")
    assert code == 4, text[-2000:]
    # The reason below shows the direct path (the world's exit, not a bus lost); the time
    # only guards against a hang: generous, a loaded machine took 14.2 s (load 25 on 2 cores).
    assert gone_s < 30.0
    intr = summary["interrupted"]
    assert intr["reason"] == "the world died (SIGKILL)" and 8 <= intr["last_step"] < 600, intr
    assert "BROKEN RUN" in text and "the world died" in text


def test_a_wait_without_a_timeout_blocks_until_its_event():
    """`Wait(until, inf)` (the selector when there is nothing to select) waits for its event
    instead of failing: an infinite timeout is no deadline."""
    from swarmrt.node import Node
    from swarmrt.protocol import Event

    n = Node("selector", 0, "t", 3, BusConfig(mode="peer"), announce=False)
    got = []
    try:
        t = threading.Timer(0.3, lambda: n.inbox.put_event(Event("", "clock", None)))
        t.start()
        assert n.wait_for(lambda: bool(got), float("inf"), got.append)
        assert got[0].kind == "clock"
    finally:
        n.close()


def test_a_client_reaches_the_second_router_when_the_first_is_down():
    """A process started while the first of its two routers is down (a failover campaign:
    an agent restarted then) connects to the second. Zenoh 1.x alone does not: a client
    whose connect/timeout_ms is set retries its first endpoint until the timeout
    (swarmrt.bus.session.open_session says how it is worked around)."""
    import json as _json

    from swarm.supervise.launch import free_port
    from swarmrt.bus.session import open_session

    down, up = free_port(), free_port()
    rc = zenoh.Config()
    rc.insert_json5("mode", '"router"')
    rc.insert_json5("listen/endpoints", _json.dumps([f"tcp/127.0.0.1:{up}"]))
    rc.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(rc) as router:
        endpoints = [f"tcp/127.0.0.1:{down}", f"tcp/127.0.0.1:{up}"]
        t0 = time.monotonic()
        with open_session(BusConfig(mode="client", connect=endpoints)) as s:
            routers = [str(p) for p in s.info.routers_zid()]
            assert routers == [str(router.info.zid())], routers
        assert time.monotonic() - t0 < 10.0
    # No router up at all: it gives up after its timeout, saying so.
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_session(BusConfig(mode="client", connect=endpoints, connect_timeout_ms=2000))
    assert time.monotonic() - t0 < 5.0


def test_the_recorders_router_killed_while_it_lags_behind_the_recording_loses_nothing(tmp_path):
    """Issue 37: the recorder is stalled (SIGSTOP) at step 5, several steps behind the world
    when router 0 (the one it is on) is killed for good at step 7; it fails over to router 1
    when it resumes. The world runs at most ``recorder_max_lag_steps`` ahead of it (the
    bounded lag) and every role sends its last steps again when the recorder's token comes
    back: the recording holds every step, with the fault-free run's numbers, and every
    fault's record."""
    faults = [{"at_step": 5, "action": "stall-recorder", "down_s": 2.0}, {"at_step": 7, "action": "kill-router", "target": 0}]
    sc = scenario(duration_s=20, selection={"strategy": "greedy", "budget": 4}, faults=faults,
                  emulator={"recorder_max_lag_steps": 2})
    out = tmp_path / "run"
    sw = LocalSwarm(sc, out, log=lambda s: None, routers=2)
    try:
        sw.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
    rec = load_recording(out / "run.mcap", sc.n_sats, sc.steps)
    summary = rec.summary(sc)
    print(summary.get("bus_gaps"), summary.get("recorder_lag"), summary["messages"].get("resent_not_written"))
    assert code == 0
    _assert_same_numbers_as_without_the_fault(rec, summary, sc)
    lag = summary["recorder_lag"]
    assert lag["max_lag_steps"] == 2 and lag["steps_waited"] >= 0 and lag["wait_s"] >= 0.0, lag
    phases = {(f["action"], f["phase"]) for f in summary["faults"]}
    for action in ("stall-recorder", "kill-router"):
        assert (action, "command") in phases and (action, "done") in phases, summary["faults"]


def _run_faults(tmp_path, name: str, faults: list[dict]):
    # The radio's link model on, as in the repeat benchmark: a restarted agent then gets its
    # state through the radio in rounds, the same in every run (without it, which peer's
    # estimate it borrows is the first to answer).
    sc = scenario(duration_s=16, selection={"strategy": "greedy", "budget": 4}, faults=faults,
                  links={"enabled": True, "latency": {"speed_of_light": False}})
    sw = LocalSwarm(sc, tmp_path / name, log=lambda s: None, routers=2)
    try:
        sw.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
    assert code == 0, sw.broken
    rec = load_recording(tmp_path / name / "run.mcap", sc.n_sats, sc.steps)
    return rec, rec.summary(sc)


def test_a_router_killed_while_an_agent_on_it_is_stalled_waits_for_the_stall_and_changes_nothing(tmp_path):
    """Issue 35 (the repeat benchmark's seeds 1, 11, 13): agent 1 is stalled (SIGSTOP, 2 s)
    and router 0, the one it is on, is killed at the same step while the world is on router 1
    (router 0 killed and restarted first: every role fails over to router 1; agent 1 then
    restarted: it connects to router 0). A stopped agent cannot fail over: killed under it,
    the router would take its token, the world would count it gone after liveliness_hold_s
    or not as the wall clock fell, and the same campaign would give other numbers (or the
    supervisor would call the run broken). The kill waits for the stall to end: the run has
    the numbers of the same run without the stall and the second kill, and the router
    fault's record says it waited."""
    before = [{"at_step": 2, "action": "kill-router", "target": 0}, {"at_step": 3, "action": "restart-router", "target": 0},
              {"at_step": 4, "action": "restart-agent", "target": 1}]
    ref, ref_summary = _run_faults(tmp_path, "reference", before)
    rec, summary = _run_faults(tmp_path, "stalled", [*before, {"at_step": 8, "action": "stall-agent", "target": 1, "down_s": 2.0},
                                                     {"at_step": 8, "action": "kill-router", "target": 0}])
    np.testing.assert_array_equal(rec.schedule, ref.schedule)
    np.testing.assert_array_equal(rec.alive, ref.alive)
    for key in EQUAL_KEYS:
        assert summary[key] == ref_summary[key], key
    done = [f for f in summary["faults"] if f["phase"] == "done" and f["k"] >= 8]
    assert {f["action"] for f in done} == {"stall-agent", "kill-router"}, summary["faults"]
    [kill] = [f for f in done if f["action"] == "kill-router"]
    assert "once the stall of pid" in kill["detail"], kill


@contextlib.contextmanager
def _world_node_and_agent_token():
    """A real router on loopback, the world's node watching liveliness and a peer session
    holding agent 2's token, seen alive: (node, token, its key)."""
    from swarm.supervise.launch import free_port
    from swarmrt.node import Node

    port = free_port()
    rc = zenoh.Config()
    rc.insert_json5("mode", '"router"')
    rc.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    rc.insert_json5("scouting/multicast/enabled", "false")
    router = zenoh.open(rc)
    bus = BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"])
    n = Node("world", 0, "t", 4, bus, announce=False)
    peer = zenoh.open(bus.zenoh_config())
    key = Keys("t").alive("agent", 2)
    try:
        n.watch_liveliness()
        token = peer.liveliness().declare_token(key)
        seen: list = []
        assert n.wait_for(lambda: any(e.kind == "alive" and e.alive for e in seen), 10.0, seen.append)
        yield n, token, key
    finally:
        n.close()
        peer.close()
        router.close()


def test_a_return_is_said_again_twice_a_moment_later():
    """A resync (a peer's token back before it counted gone) is handed on, then ``again``
    events come _AGAIN_AFTER_S later, on which roles send every step they keep once more: a
    put made while a failover still rebuilt the routes is lost without a trace (issue 35's
    repeat benchmark). One series for a burst of returns; none if the bus goes meanwhile."""
    from swarmrt.node import _AGAIN_AFTER_S
    from swarmrt.protocol import Event

    with _world_node_and_agent_token() as (n, _token, key):
        seen: list = []
        n.inbox.put_event(Event(key, "alive", 2, alive=False, role="agent"))  # its going, heard late
        seen.clear()
        assert n.wait_for(lambda: any(e.kind == "resync" for e in seen), 10.0, seen.append), seen
        t0 = time.monotonic()
        got: list = []
        assert n.wait_for(lambda: len([e for e, _t in got if e.kind == "again"]) == len(_AGAIN_AFTER_S), 20.0,
                          lambda e: got.append((e, time.monotonic()))), got
        again = [(e, t) for e, t in got if e.kind == "again"]
        assert [e.msg for e, _t in again] == ["bus"] * len(_AGAIN_AFTER_S), "every step kept, as for the bus's return"
        assert all(t - t0 >= d - 0.05 for (_e, t), d in zip(again, _AGAIN_AFTER_S, strict=True)), "not before its time"
        # A burst of returns (a failover brings every token back at once): one series.
        got.clear()
        for _ in range(5):
            n.inbox.put_event(Event(key, "resync", 2, role="agent"))
        end = time.monotonic() + _AGAIN_AFTER_S[-1] + 1.0
        while (left := end - time.monotonic()) > 0:
            if (e := n.next_event(left)) is not None:
                got.append(e)
        assert [e.kind for e in got] == ["resync"] * 5 + ["again"] * len(_AGAIN_AFTER_S), got
        # The bus goes before they are due: none comes (its return will send again).
        n.inbox.put_event(Event(key, "resync", 2, role="agent"))
        n.inbox.put_event(Event("", "bus", None, alive=False))
        got.clear()
        end = time.monotonic() + _AGAIN_AFTER_S[-1] + 0.5
        while (left := end - time.monotonic()) > 0:  # (wait_for would wait for the bus to come back)
            if (e := n.next_event(left)) is not None:
                got.append(e)
        assert [e.kind for e in got] == ["resync", "bus"], got


def test_a_token_whose_going_arrives_after_its_return_is_not_counted_gone():
    """A client failing over between meshed routers re-declares its token on the second
    router; the removal of its old declaration (the first router's) can reach a watcher
    after the new one, or be read late. The node then holds the token and, its hold over,
    asks the routers: declared, so not gone (a resync). A token really gone still counts
    gone after its hold. (Issue 35: a run declared broken over an agent back in 7 ms.)"""
    from swarmrt.protocol import Event

    with _world_node_and_agent_token() as (n, token, key):
        seen: list = []
        # The crossed order: its going heard after its (still standing) declaration.
        n.inbox.put_event(Event(key, "alive", 2, alive=False, role="agent"))
        seen.clear()
        assert n.wait_for(lambda: any(e.kind in ("resync", "alive") for e in seen), 10.0, seen.append), seen
        assert [e.kind for e in seen] == ["held", "resync"], seen
        # Really gone: counted gone once held for liveliness_hold_s.
        token.undeclare()
        seen.clear()
        assert n.wait_for(lambda: any(e.kind == "alive" for e in seen), 10.0, seen.append), seen
        assert [e.kind for e in seen] == ["held", "alive"] and seen[-1].alive is False, seen
