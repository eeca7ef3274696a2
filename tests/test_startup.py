"""Start-up: the roles of a scenario that renders nothing load no vision library."""

import contextlib
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from swarm_harness import run_swarm, scenario

from swarmrt.bus.messages import Clock, Keys

VISION = ("cv2", "open3d", "pyrender", "trimesh", "OpenGL", "pyglet")


def test_role_modules_import_no_vision_library():
    code = (
        "import sys, sat_agent.node, world_sim.node, selector.node, swarm.record.recorder, swarm.supervise.router, swarm.supervise.launch;"
        f"print(sorted(m for m in {VISION!r} if m in sys.modules))"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]", p.stdout


@pytest.mark.integration
def test_running_roles_of_a_scenario_without_rendering_map_no_vision_library(tmp_path):
    """Read each live process's memory map mid-run: no shared object of a vision library."""
    import zenoh

    sc = scenario(n_sats=3, duration_s=8, emulator={"lockstep_max_realtime_factor": 4.0})
    maps = {}

    def look(sw):
        seen = threading.Event()
        with zenoh.open(sw.bus_as("observer").zenoh_config()) as s:
            sub = s.declare_subscriber(Keys(sw.run).clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= 2 and seen.set())
            assert seen.wait(120)
            sub.undeclare()
        for name, p in sw.procs.items():
            with contextlib.suppress(OSError):
                maps[name] = Path(f"/proc/{p.pid}/maps").read_text()

    _rec, _summary, codes, _sw = run_swarm(sc, tmp_path / "run", during=look)
    assert codes["world"] == 0
    assert {"world", "recorder", "agent-0", "agent-1", "agent-2"} <= set(maps)
    for name, text in maps.items():
        libs = {line.split()[-1] for line in text.splitlines() if line.count(" ") >= 5 and "/" in line}
        hits = [lib for lib in libs if any(f"/{v}/" in lib or f"/{v.lower()}" in lib.lower() for v in ("cv2", "open3d", "pyrender", "OpenGL"))]
        assert not hits, f"{name} mapped {hits}"
