"""The runtime's bus loads nothing of the application and changes no process setting.

The generated message classes live in the runtime (``swarmrt/bus/v1/``); before, they were
``swarm/v1/`` and importing any message ran ``swarm/__init__.py``, which tunes the process
(environment variables of the BLAS, malloc). Checked in a fresh interpreter, since this
test session has long since imported ``swarm``."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

_PROBE = r"""
import gc, json, os, signal, sys, threading
def settings():
    return {
        "environ": dict(os.environ),
        "switch_interval": sys.getswitchinterval(),
        "recursion_limit": sys.getrecursionlimit(),
        "gc_threshold": list(gc.get_threshold()),
        "gc_enabled": gc.isenabled(),
        "signals": {s.name: repr(signal.getsignal(s)) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1)},
        "stack_size": threading.stack_size(),
    }
before = settings()
import swarmrt.bus
import swarmrt.bus.messages as M
import swarmrt.bus.convert
from swarmrt.bus.v1.estimate_pb2 import Estimate
payload = M.encode(M.Clock(schema_version=1, run="r", sender="world", k=3, t_s=1.5, mode="lockstep"))
msg = M.decode("clock", payload)
after = settings()
print(json.dumps({
    "app_modules": sorted(m for m in sys.modules if m == "swarm" or m.startswith("swarm.")),
    "changed": {k: [before[k], after[k]] for k in before if before[k] != after[k]},
    "estimate": Estimate.DESCRIPTOR.full_name,
    "k": msg.k,
    "tuned": sys.modules["swarmrt.tuning"]._tuned if "swarmrt.tuning" in sys.modules else None,
}))
"""


def test_importing_the_bus_loads_no_application_module_and_changes_no_process_setting():
    p = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out["app_modules"] == [], f"importing swarmrt.bus loaded the application: {out['app_modules']}"
    assert out["changed"] == {}, f"importing swarmrt.bus changed process settings: {out['changed']}"
    assert out["tuned"] in (None, False), "importing swarmrt.bus tuned the process (swarmrt.tuning.tune_process)"
    # The wire names did not move with the code: recordings and other languages see swarm.v1.
    assert out["estimate"] == "swarm.v1.Estimate"
    assert out["k"] == 3


def test_the_probe_sees_what_the_application_does():
    # The same probe, importing the application first, reports it: the test above can fail.
    probe = _PROBE.replace("import swarmrt.bus\n", "import swarm\nimport swarmrt.bus\n", 1)
    p = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out["app_modules"] == ["swarm"]
    assert "environ" in out["changed"]
