"""A scheduled kill-node never ends in a silent exit 0 (swarm.cluster.swarm.RaySwarm, no
cluster needed): the world holds the node's step until its moved agents are back, so a clock
after that step without one of them means the world gave up on it (``startup_timeout_s``),
and the supervisor declares the run broken; a moved agent listed by the next clock is back.
The events are the supervisor's own (the clocks it hears), fed by hand."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from swarm.api import load_scenario
from swarm.cluster.swarm import RaySwarm
from swarmrt.bus.messages import Clock


def _clock(k: int, live: list[int]):
    return SimpleNamespace(kind="clock", msg=Clock(run="r", sender="world", k=k, t_s=float(k), live_agents=live, mode="lockstep"),
                           role=None, sat=None, alive=None)


@pytest.fixture
def sw(tmp_path):
    sc = load_scenario({"name": "moves", "seed": 1, "n_sats": 6, "duration_s": 10, "graph": {"kind": "complete"}})
    s = RaySwarm(sc, tmp_path / "run", "local-ray:3", log=lambda _s: None)
    s._moved = {2: (4, 2, 0), 5: (4, 2, 1)}  # node 2 killed at step 4: agents 2 and 5 moved to nodes 0 and 1
    return s


def test_moved_agents_flying_after_the_step_clear(sw):
    sw._handle(_clock(4, [0, 1, 2, 3, 4, 5]))  # the step itself: the world put it once they were back
    sw._handle(_clock(5, [0, 1, 2, 3, 4, 5]))
    assert sw._moved == {} and sw.agent_gone() is None


def test_a_moved_agent_missing_after_the_step_breaks_the_run(sw):
    sw._handle(_clock(4, [0, 1, 3, 4]))  # (at the step itself nothing is concluded yet)
    assert sw.agent_gone() is None
    sw._handle(_clock(5, [0, 1, 3, 4, 5]))
    why = sw.agent_gone()
    assert why is not None and why.startswith("agent 2, moved from node 2 (lost at step 4) to node 0, is not flying at step 5"), why
    # Seen only with the world's last clock: run_to_end turns its exit 0 into a broken run.
    assert 5 not in sw._moved


def test_a_world_that_exits_0_without_a_moved_agent_is_a_broken_run(sw):
    """The world's last clock lacked agent 2 and the world exited 0: not a finished run."""
    sw._handle(_clock(9, [0, 1, 3, 4, 5]))
    sw.procs["world"] = SimpleNamespace(pid=1, poll=lambda: 0, wait=lambda timeout=None: 0)
    sw.node = SimpleNamespace(next_event=lambda timeout: None)
    assert sw.run_to_end() is None
    assert sw.broken is not None and "agent 2" in sw.broken and sw.broken_code == 5
