"""swarm.supervise.exec_agent: an agent of another language started outside `swarm run`
(compose.rust.yaml) is given the agent contract's environment, then becomes the command."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHOW_ENV = ("import json, os; print(json.dumps({k: v for k, v in os.environ.items() if k.startswith('SWARM_')}));"
            " print(os.getpid()); print(open(os.environ['SWARM_SCENARIO_JSON']).read().replace(chr(10), ' '))")


def _exec_agent(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "swarm.supervise.exec_agent", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "SWARM_SET": "", **(env or {})})


def test_the_contracts_environment_then_exec(tmp_path):
    cred = tmp_path / "agent-2.json"
    cred.write_text('{"user": "agent-2", "password": "x"}')
    p = subprocess.Popen([sys.executable, "-m", "swarm.supervise.exec_agent", "--id", "2", "--run", "r1", "--scenario",
                          "scenarios/demo.yaml", "--credential", str(cred), "--connect", "tcp/127.0.0.1:7447", "--",
                          sys.executable, "-c", SHOW_ENV], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "SWARM_SET": "n_sats=4 estimator.kind=ci emulator.agent_commands.2=swarm-rust-agent"})
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    shown, pid, scenario_json = out.splitlines()
    assert int(pid) == p.pid, "the agent runs in exec_agent's place (its signals and exit status are its own)"
    env = json.loads(shown)
    assert (env["SWARM_SAT_ID"], env["SWARM_RUN"], env["SWARM_CONNECT"], env["SWARM_RESTART"]) == ("2", "r1", "tcp/127.0.0.1:7447", "0")
    assert env["SWARM_CREDENTIAL"] == str(cred)
    # An in-memory file the agent inherited: nothing on disk to outlive it.
    assert env["SWARM_SCENARIO_JSON"].startswith("/proc/self/fd/"), env["SWARM_SCENARIO_JSON"]
    sc = json.loads(scenario_json)  # resolved: SWARM_SET applied, derived numbers added
    assert sc["n_sats"] == 4 and sc["estimator"]["kind"] == "ci" and sc["emulator"]["agent_commands"] == {"2": "swarm-rust-agent"}
    assert sc["derived"]["steps"] == 61 and sc["derived"]["gate_threshold"] > 0


def test_a_satellite_the_world_may_hand_out_is_refused():
    p = _exec_agent("--id", "2", "--run", "r1", "--scenario", "scenarios/demo.yaml", "--", "true")
    assert p.returncode == 2 and "emulator.agent_commands.2=" in p.stderr, p.stderr
    p = _exec_agent("--id", "9", "--run", "r1", "--scenario", "scenarios/demo.yaml", "--", "true")
    assert p.returncode == 2 and "--id 9: not a satellite" in p.stderr, p.stderr


def test_without_a_command_or_with_a_missing_one():
    p = _exec_agent("--id", "1", "--run", "r1", "--scenario", "scenarios/demo.yaml")
    assert p.returncode == 2 and "after `--`" in p.stderr
    p = _exec_agent("--id", "1", "--run", "r1", "--scenario", "scenarios/demo.yaml", "--", "/no/such/agent",
                    env={"SWARM_SET": "emulator.agent_commands.1=x"})
    assert p.returncode == 127 and "cannot run '/no/such/agent'" in p.stderr, p.stderr
