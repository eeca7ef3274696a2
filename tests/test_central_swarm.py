"""The centralized reference (``estimator.kind: central``) flown distributed: every agent
sends its own absolute reading (star tracker, GPS) in its estimator message, so ``swarm
run`` feeds each full filter what ``swarm sim`` feeds it and the numbers are the
simulator's, bit for bit, on the ideal radio and through late, lossy links; the
Cramér–Rao bound of one filter counts the peers' readings that reached it (not every one
taken), in-process and from the recording alike. Real processes on a loopback Zenoh bus
(as tests/test_bound_swarm.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from swarm_harness import scenario
from test_integration_swarm import assert_same_arrays

from swarm.simulation import simulate_scenario
from swarmcore.result import RunBuilder

# Every batch (and reading) late (1.2 s on a 1 s step) and a fifth of them lost in bursts.
LINKS = {"enabled": True, "latency": {"fixed_s": 1.2, "speed_of_light": False},
         "loss": {"model": "gilbert_elliott", "rate": 0.2, "mean_burst": 2.0}}
ANCHORS = [0, 2]  # filter 1 is not anchored: the peers' readings are what it knows the anchors by
SUMMARY_KEYS = ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean", "relative",
                "late", "bound", "rms_over_bound")


def _scenario(links: bool):
    over = {"links": LINKS} if links else {}
    return scenario(duration_s=20, estimator={"kind": "central"}, graph={"kind": "complete", "absolute": ANCHORS},
                    bound={"filter": 1}, **over)


def test_the_bound_of_one_filter_counts_the_peer_readings_that_reached_it(monkeypatch):
    """In-process, through lossy links: filter 1's bound counts each anchor's reading at the
    step it was taken when the radio delivered it to filter 1 (late ones too), and only
    then; the peers' readings the radio lost are not counted."""
    counted: set[tuple[int, int]] = set()
    real = RunBuilder.absolute_at

    def spy(self, k, sats):
        counted.update((int(k), int(j)) for j in np.atleast_1d(np.asarray(sats, dtype=int)))
        return real(self, k, sats)

    monkeypatch.setattr(RunBuilder, "absolute_at", spy)
    sc = _scenario(links=True)
    res = simulate_scenario(sc)
    K = sc.steps
    peers = {(k, j) for (k, j) in counted if j != 1}
    assert {j for _, j in peers} == set(ANCHORS)
    # The last two steps' readings (1.2 s late: each delivered two steps on) reach nobody
    # before the end; of the others about a fifth are lost.
    missing = 2 * K - len(peers)
    assert 2 * 2 < missing < K, (missing, K)
    assert res.summary()["links"]["totals"]["lost"] > 0
    ideal = simulate_scenario(_scenario(links=False))
    assert ideal.bound is not None and res.bound is not None
    # What was lost is information the filter lacks: the bound of an anchor's position is above the ideal radio's.
    assert np.all(res.bound.pos_m2[2:, ANCHORS] >= ideal.bound.pos_m2[2:, ANCHORS] * (1 - 1e-12))
    assert np.any(res.bound.pos_m2[2:, ANCHORS] > ideal.bound.pos_m2[2:, ANCHORS] * 1.01)


@pytest.mark.integration
@pytest.mark.parametrize("links", [False, True], ids=["ideal", "links"])
def test_swarm_run_of_central_equals_swarm_sim(tmp_path, links):
    """``swarm run`` with ``estimator.kind=central`` (4 satellites, 20 s, anchors 0 and 2,
    the bound of non-anchored filter 1): summary numbers, every array and the bound equal
    ``swarm sim``'s to the bit, on the ideal radio and with 1.2 s of latency and 20 %
    bursty loss (late readings replayed)."""
    from swarm.api import run

    sc = _scenario(links)
    res = run(sc, out=tmp_path / "run")
    assert res.outcome is not None and res.outcome.finished, res.summary.get("interrupted")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    sim = simulate_scenario(sc)
    ref = sim.summary()
    assert summary["estimator"] == ref["estimator"] == "central"
    for key in SUMMARY_KEYS:
        if key in ref or key in summary:
            assert json.dumps(summary.get(key)) == json.dumps(ref.get(key)), key
    got, want = res.recording.bound, sim.bound
    assert got is not None and want is not None and got.kind == "filter 1"
    for name in ("att_rad2", "pos_m2", "rel_pos_m2", "att_axes_rad2", "pos_axes_m2"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert_same_arrays(res.recording, sim)
    # The anchors' messages carry their readings: their bytes are above the others'.
    sent = sim.bytes_sent.sum(axis=0)
    assert min(sent[j] for j in ANCHORS) > max(sent[j] for j in range(sc.n_sats) if j not in ANCHORS)
    if links:
        assert summary["late"]["used"] > 0 and summary["links"]["totals"]["lost"] > 0, (summary["late"], summary["links"]["totals"])
