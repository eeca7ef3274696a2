"""Forgeries against a running swarm, with real credentials on a real bus (the local swarm
of tests/test_security.py and the compose one of tests/test_compose.py share them)."""

from __future__ import annotations

import subprocess
import threading

import numpy as np
import zenoh

from swarmcore.mekf import RelativeMeasurements
from swarmrt.bus import messages as M
from swarmrt.bus.convert import batch_msg
from swarmrt.bus.session import BusConfig

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

    def seen_keys(self) -> list[str]:
        with self.cv:
            return [k for k, _ in self.got]


def _batch(run: str, sender: str, observer: int, k: int = MARK_K) -> bytes:
    """A well-formed measurement batch, half a step off in time (no real run's batch is)."""
    rel = RelativeMeasurements(np.array([observer]), np.array([(observer + 1) % 4]), np.array([[0, 0, 0, 1.0]]),
                               np.array([[1.0, 2, 3]]), np.eye(6)[None] * 1e-4)
    # t_s half a step off: no batch of a real run has it.
    return M.encode(batch_msg(rel, np.array([0]), run=run, sender=sender, k=k, t_s=k + 0.5, observer=observer))


def end_router(p, log) -> None:
    """SIGTERM a router a test started and wait for it; one that does not end within 30 s is
    killed and fails the test with the end of its log (``log``: its log file's path)."""
    p.terminate()
    try:
        p.wait(30)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()
        raise AssertionError(f"the router did not end within 30 s of SIGTERM; its log:\n{log.read_text()[-3000:]}") from None


def _open(endpoint: str, cred=None, timeout_ms: int = 10_000):
    return zenoh.open(BusConfig(mode="client", connect=[endpoint], credential_file=cred, connect_timeout_ms=timeout_ms).zenoh_config())


def forge(endpoint: str, run: str, keys_dir, done: dict, from_step: int = 3) -> None:
    """Once the run is at ``from_step``: a stranger tries to connect; agent 3's credential
    puts a fault command (kill agent 1, drop all of agent 1's messages, a camera off), a
    done clock, a batch on meas/2, and a batch on its own meas/3 naming agent 2 (the world,
    the radio, hears it, refuses it and carries it to no agent); the
    recorder's credential puts the same commands and clock. ``done`` collects what a
    separate recorder-identity session saw (a session hears its own puts locally)."""
    k = M.Keys(run)
    cred = {name: str(keys_dir / f"{name}.json") for name in ("recorder", "agent-3", "observer")}
    # First wait for the router itself (an observer's session, up to 60 s): a router in a
    # container just started may take longer than 10 s to listen on a busy machine (CI saw
    # "Unable to connect ... Timeout!" at 10 s), and a stranger refused by a router that is
    # not listening yet would prove nothing.
    _open(endpoint, cred["observer"], timeout_ms=60_000).close()
    try:
        _open(endpoint, timeout_ms=2000)
        done["stranger"] = "connected"
    except zenoh.ZError:
        done["stranger"] = "refused"
    with _open(endpoint, cred["observer"]) as obs, _open(endpoint, cred["recorder"]) as rec, \
            _open(endpoint, cred["agent-3"]) as a3, _open(endpoint, cred["recorder"]) as watcher:
        at = threading.Event()
        step: dict = {}

        def on_clock(s):
            m = M.Clock.FromString(s.payload.to_bytes())
            step["k"] = m.k
            if m.k >= from_step:
                at.set()

        sub = obs.declare_subscriber(k.clock(), on_clock)
        assert at.wait(300), "the run never reached the step of the forgeries"
        witness = Witness(watcher, k.everything())
        # The witness's subscription has reached the router once the run's own traffic
        # comes to it: only then do the forgeries (and the control) prove anything.
        assert witness.wait_for(lambda key, p: key == k.clock(), 60), "the witness heard none of the run"
        kk = step["k"]
        hdr = {"run": run, "sender": "cli", "k": kk, "t_s": float(kk), "phase": "command"}
        commands = [M.Fault(**hdr, action="kill-agent", target=1), M.Fault(**hdr, action="drop", target=1, rate=1.0),
                    M.Fault(**hdr, action="camera", target=0, camera=0, state="off")]
        clock = M.encode(M.Clock(run=run, sender="world", k=kk + 1, t_s=0.0, live_agents=[0], mode="lockstep", done=True))
        for who in (a3, rec):
            for cmd in commands:
                who.put(k.fault(), M.encode(cmd))
            who.put(k.clock(), clock)
        a3.put(k.meas(2), _batch(run, "agent-2", 2, kk + 1))
        a3.put(k.meas(3), _batch(run, "agent-2", 2, MARK_K))  # passes the router; receivers drop it
        a3.put(k.meas(3), _batch(run, "agent-3", 3, MARK_K))  # the control
        done["control"] = witness.wait_for(lambda key, p: key == k.meas(3) and M.decode("meas", p).sender == "agent-3")
        done["at_k"] = kk
        done["seen"] = list(witness.got)
        sub.undeclare()


def check_forgeries(done: dict, summary: dict, sc, run: str) -> None:
    """Nothing refused got through, the radio dropped the batch naming another, and
    the numbers are those of the run without the attempts (`swarm sim`), bit for bit."""
    from swarmcore.sim import simulate

    assert done.get("stranger") == "refused" and done.get("control"), {k: v for k, v in done.items() if k != "seen"}
    assert done["at_k"] < sc.steps - 2, "the forgeries came after the run"
    k = M.Keys(run)
    for key, p in done["seen"]:
        assert key != k.fault(), "a fault command got through"
        if key == k.meas(2):
            assert M.decode("meas", p).t_s % 1.0 == 0.0, "agent 3's batch on meas/2 got through"
        if key == k.clock():
            assert not M.Clock.FromString(p).done, "a forged clock got through"
    assert summary["faults"] == []
    sec = summary["security"]
    assert sec["state"] == "on"
    # The batch naming agent 2 on agent 3's key passed the router: its receiver, the world
    # (the radio), dropped and counted it, and carried nothing of it to any agent.
    assert sec["key_mismatch_dropped"]["world"] >= 1, sec
    ref = simulate(sc).summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis"):
        assert summary[key] == ref[key], key
