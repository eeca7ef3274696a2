"""How the supervisor judges an agent process that ended by itself (``LocalSwarm.agent_gone``),
driven with real child processes and no bus: an agent exits 0 only after the world's last
clock, which the supervisor's own subscription may receive later than the agent did."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

import swarm
from swarm.supervise import launch

ROOT = Path(__file__).resolve().parents[1]


def _swarm(tmp_path, code: int) -> tuple[launch.LocalSwarm, subprocess.Popen]:
    """A supervisor whose agent-2 has ended with status ``code`` (negative: killed by signal −code)."""
    sc = swarm.load_scenario(ROOT / "scenarios" / "demo.yaml", duration_s=5)
    s = launch.LocalSwarm(sc, tmp_path / "run", log=lambda *_: None)
    script = f"import sys; sys.exit({code})" if code >= 0 else f"import os; os.kill(os.getpid(), {-code})"
    p = subprocess.Popen([sys.executable, "-c", script])
    p.wait(timeout=30)
    s.procs["agent-2"] = p
    return s, p


def test_an_agent_that_exited_0_before_the_supervisor_saw_the_end_is_given_time(tmp_path):
    s, _p = _swarm(tmp_path, 0)
    assert s.agent_gone() is None  # its "done" clock may still be on its way to us
    s.world_done = True  # ... and here it comes
    assert s.agent_gone() is None


def test_an_agent_that_exited_0_and_no_end_came_is_a_broken_run_after_the_grace(tmp_path):
    s, p = _swarm(tmp_path, 0)
    assert s.agent_gone() is None
    s._clean_exit_at[p.pid] = time.monotonic() - launch._CLEAN_EXIT_GRACE_S - 1.0  # the grace has passed
    why = s.agent_gone()
    assert why is not None and "agent-2" in why and "exited with status 0" in why


@pytest.mark.parametrize("code", [1, 2, -9])
def test_an_agent_that_failed_is_a_broken_run_at_once(tmp_path, code):
    s, _p = _swarm(tmp_path, code)
    expect = "killed by SIGKILL" if code == -9 else f"exited with status {code}"
    why = s.agent_gone()
    assert why is not None and expect in why


def test_a_faulted_agent_is_no_surprise(tmp_path):
    s, p = _swarm(tmp_path, 1)
    s._faulted.add(p.pid)
    assert s.agent_gone() is None
