"""`swarm run` owns what it starts: SIGINT, SIGTERM or SIGKILL to it ends every process.

Real processes on a real loopback router: `swarm run` is started as a subprocess, the test
follows the run's clock on the bus until it is mid-run, sends the signal, and waits (with
a bound, polling the process table) until every process the run recorded in run.json is
gone. SIGINT and SIGTERM must also leave a closed, indexed run.mcap and a summary.json
marked as interrupted at the last recorded step; SIGKILL gives the supervisor no chance,
so its children must notice on their own (swarm/supervise/lifeline.py).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
import yaml
import zenoh
from mcap.reader import make_reader

from swarmrt.bus.messages import Clock, Keys
from swarmrt.bus.session import BusConfig

pytestmark = pytest.mark.integration

K_SIGNAL = 10  # the step the run must have reached before the signal
CLEAR_BOUND_S = 30.0  # every process gone within this (it takes a few seconds; see the printout)

# Long (600 steps) and paced (at most 10 simulated seconds per wall second), so the
# signal lands mid-run; with a selector, so every kind of role is there to be stopped.
SCENARIO = {
    "name": "signals",
    "seed": 4,
    "n_sats": 3,
    "duration_s": 600,
    "graph": {"kind": "complete"},
    "selection": {"strategy": "random", "budget": 3},
    "emulator": {"lockstep_max_realtime_factor": 10.0},
}


def wait_until(cond, timeout: float, what: str, every: float = 0.05):
    """Poll ``cond()`` until it returns something truthy (returned) or fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:.0f} s: {what}")
        time.sleep(every)


def _read_json(path):
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None  # not written yet, or half written


def _gone(p: psutil.Process) -> bool:
    """Ended: no such process (or the pid reused by another; psutil compares start times),
    or a zombie waiting for its reaper."""
    try:
        return not p.is_running() or p.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_for_step(endpoint: str, run: str, k: int, timeout: float, keys: str | None = None) -> None:
    """Block until the world's clock reaches step ``k`` (an event on the bus)."""
    reached = threading.Event()

    def on_clock(sample):
        if Clock.FromString(bytes(sample.payload.to_bytes())).k >= k:
            reached.set()

    cred = f"{keys}/observer.json" if keys else None  # the run's read-only identity
    with zenoh.open(BusConfig(mode="client", connect=[endpoint], credential_file=cred).zenoh_config()) as s:
        sub = s.declare_subscriber(Keys(run).clock(), on_clock)
        try:
            assert reached.wait(timeout), f"the run did not reach step {k} within {timeout:.0f} s"
        finally:
            sub.undeclare()


def _run_and_signal(tmp_path, sig: int):
    """Start `swarm run`, signal it at step K_SIGNAL, wait for every process to end.
    Returns (exit code of `swarm run`, seconds until every process was gone, run dir)."""
    scn = tmp_path / "signals.yaml"
    scn.write_text(yaml.safe_dump(SCENARIO))
    out = tmp_path / "run"
    log = open(tmp_path / "swarm-run.log", "wb")  # noqa: SIM115 - the child writes to it; closed in the finally below
    sup = subprocess.Popen([sys.executable, "-m", "swarm.cli", "run", str(scn), "--out", str(out)], stdout=log, stderr=subprocess.STDOUT)
    procs: list[psutil.Process] = []
    try:
        info = wait_until(lambda: _read_json(out / "run.json"), 180, "run.json written (every process started)")
        keys = info.get("keys")
        assert keys and Path(keys).is_dir(), "the run's credentials (security on by default)"
        procs = [psutil.Process(pid) for pid in info["pids"].values()]
        assert info.get("supervisor_pid") == sup.pid
        assert set(info["pids"]) == {"router", "recorder", "world", "selector", "agent-0", "agent-1", "agent-2"}
        _wait_for_step(info["endpoint"], info["run"], K_SIGNAL, 180, info.get("keys"))
        assert not any(_gone(p) for p in procs), "a process had ended before the signal: the test would prove nothing"
        t0 = time.monotonic()
        sup.send_signal(sig)
        wait_until(lambda: all(_gone(p) for p in procs), CLEAR_BOUND_S,
                   f"every process gone after {signal.Signals(sig).name}: left " + repr([p.pid for p in procs if not _gone(p)]))
        cleared_s = time.monotonic() - t0
        code = sup.wait(timeout=60)
        # Nothing else of this run is left either (a process it started but did not record).
        left = [p.info for p in psutil.process_iter(["pid", "cmdline"]) if info["run"] in " ".join(p.info["cmdline"] or ())
                and not _gone(p)]
        assert not left, left
        # The run's credentials are gone too, whichever signal (after SIGKILL, its orphaned
        # children delete them).
        wait_until(lambda: not Path(keys).exists(), 10, f"the run's keys {keys} deleted")
        print(f"\n{signal.Signals(sig).name}: every process of the run gone {cleared_s:.2f} s after the signal; "
              f"`swarm run` exited {code}")
        return code, cleared_s, out
    finally:
        for p in [*procs, psutil.Process(sup.pid) if sup.poll() is None else None]:
            if p is not None and not _gone(p):
                p.kill()
        sup.wait(timeout=30)
        log.close()


def _check_closed_and_marked(out, sig: signal.Signals) -> None:
    summary = json.loads((out / "summary.json").read_text())
    intr = summary["interrupted"]
    assert intr["reason"] == sig.name and intr["signal"] == int(sig)
    planned = round(SCENARIO["duration_s"]) + 1
    assert K_SIGNAL <= intr["last_step"] < planned - 1 and intr["steps_planned"] == planned
    assert summary["steps"] == intr["last_step"] + 1
    # The recording was closed cleanly: a finalised, indexed MCAP whose last step is the
    # summary's.
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None, "run.mcap has no summary section: it was not closed"
        clock_k = [Clock.FromString(m.data).k for _s, ch, m in reader.iter_messages() if ch.topic.endswith("/clock")]
    assert clock_k and max(clock_k) >= intr["last_step"] >= K_SIGNAL


def test_sigint_stops_every_process_and_closes_the_run(tmp_path):
    code, _s, out = _run_and_signal(tmp_path, signal.SIGINT)
    assert code == 130
    _check_closed_and_marked(out, signal.SIGINT)


def test_sigterm_stops_every_process_and_closes_the_run(tmp_path):
    code, _s, out = _run_and_signal(tmp_path, signal.SIGTERM)
    assert code == 143
    _check_closed_and_marked(out, signal.SIGTERM)


def test_sigkill_of_swarm_run_leaves_no_process_behind(tmp_path):
    code, _s, out = _run_and_signal(tmp_path, signal.SIGKILL)
    assert code == -signal.SIGKILL
    assert not (out / "summary.json").exists()  # the supervisor had no chance to write it
    # The children stopped themselves cleanly: the recorder, told by its lifeline, closed
    # run.mcap as an indexed file.
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        assert sum(1 for _ in reader.iter_messages()) > 0


def test_sigterm_ends_a_twice_chaos_campaign_without_its_second_run(tmp_path):
    """`swarm chaos --twice` stopped by SIGTERM during its first run (the user, or a parent
    that ended: scripts/twice_soak.py runs campaigns under a lifeline) ends there with the
    run's status: no second run is started (it was, and ran on orphaned, issue 35)."""
    scn = tmp_path / "signals.yaml"
    scn.write_text(yaml.safe_dump(SCENARIO))
    out = tmp_path / "chaos"
    log = open(tmp_path / "chaos.log", "wb")  # noqa: SIM115 - the child writes to it; closed in the finally below
    cmd = [sys.executable, "-m", "swarm.cli", "chaos", str(scn), "--faults", "2", "--seed", "3", "--twice", "--out", str(out)]
    sup = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    try:
        info = wait_until(lambda: _read_json(out / "run" / "run.json"), 180, "the first run's run.json written")
        _wait_for_step(info["endpoint"], info["run"], K_SIGNAL, 180, info.get("keys"))
        sup.send_signal(signal.SIGTERM)
        code = sup.wait(timeout=120)
    finally:
        if sup.poll() is None:
            sup.kill()
            sup.wait(timeout=30)
        log.close()
    assert code == 143, (tmp_path / "chaos.log").read_text()[-3000:]
    assert not (out / "run-2").exists(), "a second run was started after the signal"
    assert "SIGTERM: the campaign stops" in (tmp_path / "chaos.log").read_text()
