"""The Cramér–Rao bound of a distributed run (``swarm run``): its summary.json, written from
the recording (swarm.supervise.outcome), has the bound ``swarm sim`` gives the same scenario,
to the bit, centralized and of one filter through lossy, late links. Real processes on a
loopback Zenoh bus (as tests/test_integration_swarm.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from swarm_harness import scenario

from swarm.api import run
from swarm.simulation import simulate_scenario

pytestmark = pytest.mark.integration

# Every batch late (1.2 s on a 1 s step) and a fifth of them lost in bursts.
LINKS = {"enabled": True, "latency": {"fixed_s": 1.2, "speed_of_light": False},
         "loss": {"model": "gilbert_elliott", "rate": 0.2, "mean_burst": 2.0}}


@pytest.mark.parametrize("over", [{}, {"bound": {"filter": 1}, "links": LINKS}], ids=["central", "filter-1-links"])
def test_run_summary_has_the_simulators_bound(tmp_path, over):
    sc = scenario(duration_s=20, **over)
    res = run(sc, out=tmp_path / "run")
    assert res.outcome is not None and res.outcome.finished, res.summary.get("interrupted")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    sim = simulate_scenario(sc)
    ref = sim.summary()
    assert summary["bound"]["kind"] == ("central" if sc.bound.filter is None else f"filter {sc.bound.filter}")
    for key in ("bound", "rms_over_bound"):
        assert json.dumps(summary[key]) == json.dumps(ref[key]), key
    # The arrays behind them, step by step (the API reads the recording the summary came from).
    got, want = res.recording.bound, sim.bound
    assert got is not None and want is not None
    for name in ("att_rad2", "pos_m2", "rel_pos_m2", "att_axes_rad2", "pos_axes_m2"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    if sc.links.enabled:
        # The test means something: batches came late and were lost, and the filter's bound
        # (what reached it) is not the centralized one (everything taken).
        assert summary["late"]["used"] > 0 and summary["links"]["totals"]["lost"] > 0, (summary["late"], summary["links"]["totals"])
        central = simulate_scenario(sc.model_copy(update={"bound": sc.bound.model_copy(update={"filter": None})})).bound
        assert central is not None and np.all(central.pos_m2[1:] <= got.pos_m2[1:]) and np.any(central.pos_m2 < got.pos_m2)
