"""Who may say what on the bus, for real: a real router (``python -m swarm.router``) with a
run's keys and access rules, real sessions with real credentials, a real swarm.

Negative checks (something must NOT arrive) wait on an event with a timeout, and each is
paired with a positive control sent afterwards over the same session (a Zenoh session's
puts reach a subscriber in order): when the control has arrived, the refused message
would have arrived before it.
"""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh

from swarm.bus import messages as M
from swarm.bus.convert import batch_msg
from swarm.bus.session import BusConfig
from swarm.launch import free_port
from swarm.security import acl_config, make_keys
from swarmcore.mekf import RelativeMeasurements
from swarmcore.sim import simulate

from swarm_harness import run_swarm, scenario

pytestmark = pytest.mark.integration

RUN = "sec-1"
MARK_K = 1_000_000  # a step no run reaches: marks the test's own messages


class Witness:
    """A session subscribed to keys, collecting (key, payload); ``wait_for(pred)``."""

    def __init__(self, session, key: str):
        self.got: list[tuple[str, bytes]] = []
        self.cv = threading.Condition()
        self.sub = session.declare_subscriber(key, self._cb)

    def _cb(self, s) -> None:
        with self.cv:
            self.got.append((str(s.key_expr), bytes(s.payload.to_bytes())))
            self.cv.notify_all()

    def wait_for(self, pred, timeout: float = 10.0) -> bool:
        with self.cv:
            return self.cv.wait_for(lambda: any(pred(k, p) for k, p in self.got), timeout)

    def keys(self) -> list[str]:
        with self.cv:
            return [k for k, _ in self.got]


def _batch(run: str, sender: str, observer: int, k: int = MARK_K) -> bytes:
    rel = RelativeMeasurements(np.array([observer]), np.array([(observer + 1) % 4]), np.array([[0, 0, 0, 1.0]]),
                               np.array([[1.0, 2, 3]]), np.eye(6)[None] * 1e-4)
    # t_s half a step off: no batch of a real run has it.
    return M.encode(batch_msg(rel, np.array([0]), run=run, sender=sender, k=k, t_s=k + 0.5, observer=observer))


def _open(endpoint: str, cred=None, timeout_ms: int = 10_000):
    return zenoh.open(BusConfig(mode="client", connect=[endpoint], credential_file=cred, connect_timeout_ms=timeout_ms).zenoh_config())


@pytest.fixture
def router(tmp_path):
    keys = make_keys(tmp_path / "keys", 4)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    p = subprocess.Popen([sys.executable, "-m", "swarm.router", "--listen", endpoint, "--keys", str(keys), "--run", RUN,
                          "--n-sats", "4"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert b"READY" in p.stdout.readline(), p.stderr.read()
        yield endpoint, keys
    finally:
        p.terminate()
        p.wait(10)


def test_the_router_refuses_strangers_and_enforces_who_may_say_what(router):
    endpoint, keys = router
    k = M.Keys(RUN)
    # No credential, a wrong password, a credential of another swarm: refused at connection.
    with pytest.raises(zenoh.ZError):
        _open(endpoint, timeout_ms=2000)
    bad = keys / "bad.json"
    bad.write_text('{"user": "agent-1", "password": "not-its-password"}')
    with pytest.raises(zenoh.ZError):
        _open(endpoint, bad, timeout_ms=2000)

    cred = {name: str(keys / f"{name}.json") for name in ("recorder", "world", "agent-1", "agent-3", "observer")}
    with _open(endpoint, cred["recorder"]) as rec, _open(endpoint, cred["world"]) as world, \
            _open(endpoint, cred["agent-1"]) as a1, _open(endpoint, cred["agent-3"]) as a3:
        everything = Witness(rec, k.everything())
        truth_at_agent = Witness(a1, k.truth())  # an agent asking for the truth is refused
        meas_at_agent = Witness(a1, k.meas())
        # Subscriptions propagate through the router: probe until the recorder sees a put.
        for _ in range(100):
            world.put(k.clock(), b"probe")
            if everything.wait_for(lambda key, p: p == b"probe", 0.1):
                break
        assert everything.wait_for(lambda key, p: p == b"probe", 1)

        # Agent 3 may put a batch on meas/3, not on meas/2, nor a fault command, nor a clock.
        a3.put(k.meas(2), _batch(RUN, "agent-2", 2))
        a3.put(k.fault(), b"forged command")
        a3.put(k.clock(), b"forged clock")
        a3.put(k.fault_report("agent-2"), b"forged report")
        a3.put(k.meas(3), _batch(RUN, "agent-3", 3))  # the control
        assert everything.wait_for(lambda key, p: key == k.meas(3))
        assert meas_at_agent.wait_for(lambda key, p: key == k.meas(3))
        assert everything.keys().count(k.clock()) >= 1 and b"forged clock" not in [p for _, p in everything.got]
        assert {k.meas(2), k.fault(), k.fault_report("agent-2")}.isdisjoint(everything.keys())
        assert k.meas(2) not in meas_at_agent.keys()

        # The world puts the truth: the recorder gets it, agent 1 (subscribed) does not.
        world.put(k.truth(), b"truth")
        world.put(k.clock(), b"control")
        assert everything.wait_for(lambda key, p: p == b"control")
        assert k.truth() in everything.keys()
        assert not truth_at_agent.got

        # The recorder puts nothing (its own puts reach no other session; it has no control
        # to send, so wait the timeout for what must not come).
        with _open(endpoint, cred["observer"]) as obs:
            clocks = Witness(obs, k.clock())
            faults = Witness(world, k.faults())
            world.put(k.clock(), b"ready?")
            assert clocks.wait_for(lambda key, p: p == b"ready?")
            rec.put(k.clock(), b"recorder clock")
            rec.put(k.fault(), b"recorder fault")
            assert not clocks.wait_for(lambda key, p: p == b"recorder clock", 1.0)
            assert not faults.got


def test_access_rules_follow_the_key_space():
    acl = acl_config("r", 3, links=True)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["agent-2:ingress:put"]["key_exprs"] == sorted(["swarm/r/meas/2", "swarm/r/est/2", "swarm/r/health/2",
                                                              "swarm/r/fault/agent-2"])
    # With the radio on, an agent hears peers' batches only through the world.
    assert "swarm/r/rx/2" in rules["agent-2:ingress:sub"]["key_exprs"]
    assert "swarm/r/meas/*" not in rules["agent-2:ingress:sub"]["key_exprs"]
    assert "recorder:ingress:put" not in rules
    assert rules["cli:ingress:put"]["key_exprs"] == ["swarm/r/fault", "swarm/r/fault/cli"]
    assert not any("truth" in e for name in ("agent-0", "selector", "observer") for e in rules[f"{name}:egress:samples"]["key_exprs"])
    assert {p["subjects"][0] for p in acl["policies"]} == {s["id"] for s in acl["subjects"]}


def test_forgeries_against_a_running_swarm_change_nothing(tmp_path):
    """Agent 3's credential publishing a batch on meas/2, a fault command and a clock; the
    recorder's publishing; a stranger's fault command: all refused. A batch on agent 3's
    own key naming agent 2 as its sender passes the router and is dropped and counted by
    every receiver. The run equals `swarm sim` bit for bit."""
    sc = scenario(n_sats=4, duration_s=14, emulator={"lockstep_max_realtime_factor": 4.0})
    done: dict = {}

    def forge(sw):
        k = M.Keys(sw.run)
        cred = {name: str(sw.keys_dir / f"{name}.json") for name in ("recorder", "agent-3", "observer")}
        try:
            _open(sw.endpoint, timeout_ms=2000)  # a stranger with a forged kill-agent in hand
            done["stranger"] = "connected"
        except zenoh.ZError:
            done["stranger"] = "refused"
        with _open(sw.endpoint, cred["observer"]) as obs, _open(sw.endpoint, cred["recorder"]) as rec, \
                _open(sw.endpoint, cred["agent-3"]) as a3, _open(sw.endpoint, cred["recorder"]) as watcher:
            at = threading.Event()
            step = {}

            def on_clock(s):
                m = M.Clock.FromString(s.payload.to_bytes())
                step["k"] = m.k
                if m.k >= 3:
                    at.set()

            sub = obs.declare_subscriber(k.clock(), on_clock)
            assert at.wait(120)
            witness = Witness(watcher, k.everything())  # a session of its own (a session hears its own puts)
            kill = M.encode(M.Fault(run=sw.run, sender="cli", k=step["k"], t_s=0.0, phase="command", action="kill-agent", target=1))
            clock = M.encode(M.Clock(run=sw.run, sender="world", k=step["k"] + 1, t_s=0.0, live_agents=[0], mode="lockstep", done=True))
            for who in (a3, rec):
                who.put(k.fault(), kill)
                who.put(k.clock(), clock)
            a3.put(k.meas(2), _batch(sw.run, "agent-2", 2, step["k"] + 1))
            a3.put(k.meas(3), _batch(sw.run, "agent-2", 2, MARK_K))  # passes the router; receivers drop it
            a3.put(k.meas(3), _batch(sw.run, "agent-3", 3, MARK_K))  # the control
            done["control"] = witness.wait_for(lambda key, p: key == k.meas(3) and M.decode("meas", p).sender == "agent-3")
            done["at_k"] = step["k"]
            done["seen"] = list(witness.got)
            sub.undeclare()

    rec, summary, codes, sw = run_swarm(sc, tmp_path / "run", during=forge)
    assert done.get("stranger") == "refused" and done.get("control"), done
    assert done["at_k"] < sc.steps - 2, "the forgeries came after the run"
    k = M.Keys(sw.run)
    # Nothing refused reached the recorder: no fault command, no second clock of a step, no
    # batch on meas/2 but agent 2's own.
    for key, p in done["seen"]:
        assert key != k.fault(), "a fault command got through"
        if key == k.meas(2):
            assert M.decode("meas", p).t_s % 1.0 == 0.0, "agent 3's batch on meas/2 got through"
        if key == k.clock():
            assert not M.Clock.FromString(p).done, "a forged clock got through"
    assert summary["faults"] == []
    for name, code in codes.items():
        assert code in (0, None), f"{name} exited with {code}"
    assert codes["world"] == 0 and rec.alive.all(), "an agent died"
    # Defence in depth: every agent dropped the batch that named agent 2 on agent 3's key.
    sec = summary["security"]
    assert sec["state"] == "on"
    assert all(sec["key_mismatch_dropped"][f"agent-{i}"] >= 1 for i in range(4)), sec
    ref = simulate(sc).summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis"):
        assert summary[key] == ref[key], key
    assert not (tmp_path / "run" / "keys").exists(), "the run's keys outlived it"
