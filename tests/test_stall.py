"""A stalled role (SIGSTOP, `docker pause`) longer than the bus lease (issue 24, P1).

The world of a running swarm is stopped with SIGSTOP mid-run and continued with SIGCONT
once the router has dropped its session (its liveliness token is seen to vanish: the
lease ran out). The rule: the run is either survived — lockstep, the same numbers as the
unstalled run — or declared broken (non-zero, ``interrupted`` in summary.json); never
finished with its agents gone. Real processes on a real loopback router; every wait is on
an event (the clock, a liveliness token) with a bound.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

import numpy as np
import pytest
import zenoh
from swarm_harness import scenario

from swarm.record.recording import load_recording
from swarm.supervise.launch import LocalSwarm
from swarm.supervise.outcome import run_outcome
from swarmcore.sim import simulate
from swarmrt.bus.messages import Clock, Keys
from swarmrt.bus.session import BusConfig

pytestmark = pytest.mark.integration

EQUAL_KEYS = ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean")
K_STALL = 8  # the step the run has reached when the world is stopped


def _observer(sw: LocalSwarm) -> zenoh.Session:
    cred = f"{sw.keys_dir}/observer.json" if sw.keys_dir else None  # the run's read-only identity
    return zenoh.open(BusConfig(mode="client", connect=sw.endpoints, credential_file=cred).zenoh_config())


STALL_AFTER_LEASE_S = 6.0  # the stall lasts this long after the lease ran out (the fault's length, not a synchronisation)


def _stall(sw: LocalSwarm, role: str, k: int, evidence: dict, timeout_s: float = 180.0) -> None:
    """At step ``k``, SIGSTOP ``role``'s process; SIGCONT it ``STALL_AFTER_LEASE_S`` after its
    liveliness token has vanished from the bus (the router's lease on its session ran out:
    every peer has seen it go, and held it longer than ``liveliness_hold_s``)."""
    reached, gone = threading.Event(), threading.Event()
    keys = Keys(sw.run)
    with _observer(sw) as s:
        sub = s.declare_subscriber(keys.clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= k and reached.set())
        # The token whose going shows the lease ran out: the role's own; for the router, the
        # world's (every client's session to it goes, and with it every token it carried).
        token = (keys.alive("world") if role == "router" else keys.alive(role) if role in ("world", "selector", "recorder")
                 else keys.alive("agent", int(role.split("-")[1])))
        lsub = s.liveliness().declare_subscriber(token, lambda smp: smp.kind == zenoh.SampleKind.DELETE and gone.set())
        try:
            assert reached.wait(timeout_s), f"the run did not reach step {k}"
            pid = sw.procs[role].pid
            os.kill(pid, signal.SIGSTOP)
            evidence["stopped_pid"] = pid
            try:
                evidence["lease_expired"] = gone.wait(60.0)
                threading.Event().wait(STALL_AFTER_LEASE_S)  # the stall goes on: its length is the fault
            finally:
                with contextlib.suppress(ProcessLookupError):  # (a broken run may have been stopped meanwhile)
                    os.kill(pid, signal.SIGCONT)
        finally:
            sub.undeclare()
            lsub.undeclare()


def _run_beside(sw, sc, th: threading.Thread, join_s: float):
    """Run ``sw`` to its end with ``th`` (the fault) started beside it; (world exit code, outcome)."""
    code = None
    try:
        sw.start()
        th.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
        th.join(join_s)
    return code, run_outcome(sc, sw.out / "run.mcap", run=sw.run, world_exit_code=code, interrupted=sw.interrupted,
                             broken=sw.broken, broken_code=sw.broken_code, router_faults=sw.router_faults)


def _stalled_run(tmp_path, role: str):
    """A 4-satellite run with a greedy selector, paced, whose ``role`` is stalled past the
    lease at step K_STALL. Returns (outcome, swarm, evidence, scenario)."""
    sc = scenario(duration_s=24, selection={"strategy": "greedy", "budget": 4},
                  emulator={"lockstep_max_realtime_factor": 4.0})
    out = tmp_path / "run"
    sw = LocalSwarm(sc, out, log=print)
    evidence: dict = {}
    code, outcome = _run_beside(sw, sc, threading.Thread(target=_stall, args=(sw, role, K_STALL, evidence), daemon=True), join_s=90)
    print(role, evidence, code, sw.broken, outcome.summary.get("interrupted"), outcome.summary.get("bus_gaps"))
    assert evidence.get("lease_expired"), f"the {role}'s token never vanished: the stall proved nothing ({evidence})"
    return outcome, sw, evidence, sc


def _survived_with_the_same_numbers(outcome, sw, sc) -> None:
    assert outcome.exit_code == 0
    rec = load_recording(sw.out / "run.mcap", sc.n_sats, sc.steps)
    assert rec.alive.all(), "an agent was counted dead: the stall changed the run"
    ref = simulate(sc)
    np.testing.assert_array_equal(rec.schedule, ref.schedule)
    ref_summary = ref.summary()
    for key in EQUAL_KEYS:
        assert outcome.summary[key] == ref_summary[key], key
    agents = {n: p.returncode for n, p in sw.procs.items() if n.startswith("agent-")}
    assert all(c == 0 for c in agents.values()), agents


@pytest.mark.slow
def test_world_stalled_longer_than_the_lease_is_survived_with_the_same_numbers(tmp_path):
    """The world is SIGSTOPped at step 8 until the router drops its session (~10 s, the
    Zenoh lease) and some seconds more, then continued: agents, selector and recorder wait
    for it (a world whose token went may be stalled), it resends its step, and the run
    ends with every agent alive and the numbers of the unstalled run."""
    outcome, sw, _evidence, sc = _stalled_run(tmp_path, "world")
    assert outcome.finished, f"the run was declared broken ({sw.broken}); it should have survived a stall"
    _survived_with_the_same_numbers(outcome, sw, sc)


@pytest.mark.slow
@pytest.mark.parametrize("role", ["agent-1", "selector", "recorder", "router"])
def test_another_role_stalled_past_the_lease_is_survived_or_declared_broken(tmp_path, role):
    """An agent, the selector or the recorder stalled past the lease: the world cannot wait
    for it (it cannot tell a stall from a death until the process is back), so the run goes
    on without it and differs from the unstalled run; the supervisor sees the role's
    session dropped while its process ran and declares the run broken (exit 5,
    ``interrupted`` naming it). The router stalled: every role loses the bus, waits, and
    resends its step when it is back (as after a router restart). Either way never
    "finished" with different numbers."""
    outcome, sw, _evidence, sc = _stalled_run(tmp_path, role)
    if outcome.finished:
        _survived_with_the_same_numbers(outcome, sw, sc)
    else:
        assert outcome.exit_code == 5 and role in outcome.summary["interrupted"]["reason"], outcome.summary["interrupted"]


def test_scheduled_short_stalls_of_every_role_change_no_number(tmp_path):
    """The stall faults (``stall-<role>``, carried out by the supervisor: SIGSTOP, SIGCONT
    ``down_s`` wall seconds later), each role in turn, every one shorter than the lease:
    the lockstep run finishes with the numbers of the unstalled in-process run, bit for bit.
    The router's and the selector's stalls outlast the world's old 2 s wait for a selection
    (a chaos campaign found a router stall changing the greedy schedule that way). The
    recorder is stalled again at the next step, while the world runs on within its lag and
    the first stall still holds: the first ends there, the second starts, both are done (it
    was "already stopped", or done, as the wall clock fell: the repeat benchmark's seed 16)."""
    faults = [{"at_step": 4, "action": "stall-agent", "target": 1, "down_s": 2.0},
              {"at_step": 8, "action": "stall-world", "down_s": 3.0},
              {"at_step": 12, "action": "stall-recorder", "down_s": 2.0},
              {"at_step": 13, "action": "stall-recorder", "down_s": 2.0},
              {"at_step": 16, "action": "stall-router", "down_s": 2.5},
              {"at_step": 20, "action": "stall-selector", "down_s": 2.5}]
    sc = scenario(duration_s=26, selection={"strategy": "greedy", "budget": 4}, faults=faults)
    sw = LocalSwarm(sc, tmp_path / "run", log=print)
    code = None
    try:
        sw.start()
        code = sw.run_to_end(timeout=300)
    finally:
        sw.stop()
    outcome = run_outcome(sc, sw.out / "run.mcap", run=sw.run, world_exit_code=code, interrupted=sw.interrupted,
                          broken=sw.broken, broken_code=sw.broken_code, router_faults=sw.router_faults)
    done = [f for f in outcome.summary["faults"] if f["phase"] == "done" and f["action"].startswith("stall-")]
    assert sorted(f["action"] for f in done) == sorted(f["action"] for f in faults), outcome.summary["faults"]
    assert all("SIGSTOP pid" in f["detail"] and "SIGCONT after" in f["detail"] for f in done), done
    assert outcome.finished and not outcome.summary.get("selector_fallback_steps"), outcome.summary.get("interrupted")
    _survived_with_the_same_numbers(outcome, sw, sc)


def test_an_agent_that_exits_while_the_world_runs_breaks_the_run(tmp_path):
    """An agent that leaves by itself mid-run (here SIGKILLed behind the supervisor's back,
    not by a fault it carried out) is noticed: the run is declared broken (non-zero,
    ``interrupted`` naming the agent), never reported finished with an agent gone."""
    sc = scenario(duration_s=30, emulator={"lockstep_max_realtime_factor": 4.0})
    out = tmp_path / "run"
    sw = LocalSwarm(sc, out, log=print)
    killed = {}

    def kill_agent_at(k: int) -> None:
        reached = threading.Event()
        with _observer(sw) as s:
            sub = s.declare_subscriber(Keys(sw.run).clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= k and reached.set())
            try:
                if reached.wait(180):
                    killed["pid"] = sw.procs["agent-2"].pid
                    os.kill(killed["pid"], signal.SIGKILL)
            finally:
                sub.undeclare()

    code, outcome = _run_beside(sw, sc, threading.Thread(target=kill_agent_at, args=(6,), daemon=True), join_s=30)
    print(killed, code, sw.broken, outcome.summary.get("interrupted"))
    assert killed, "the agent was never killed"
    assert outcome.exit_code != 0 and not outcome.finished
    assert "agent-2" in outcome.summary["interrupted"]["reason"], outcome.summary["interrupted"]


def test_the_stall_safety_net_continues_a_stopped_group_by_itself():
    """Should the supervisor die during a stall, the net (a shell in a session of its own)
    continues the stopped group: with Debian's sh (dash) its `kill -CONT -- -PGID` was
    refused ("Illegal number"), and a campaign killed during a world stall left the world
    stopped for good."""
    import subprocess
    import sys

    from swarm.supervise.launch import stall_safety_net

    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
    try:
        os.killpg(p.pid, signal.SIGSTOP)
        _pid, status = os.waitpid(p.pid, os.WUNTRACED)  # (the child's stop, as an event)
        assert os.WIFSTOPPED(status)
        net = stall_safety_net(p.pid, 0.2)
        assert net.wait(timeout=30) == 0, "the net's shell failed"
        _pid, status = os.waitpid(p.pid, os.WCONTINUED | os.WNOHANG)  # continued by now, or never
        assert os.WIFCONTINUED(status), "the net did not continue the group"
    finally:
        p.kill()
        p.wait(timeout=30)
