"""Sharing relative measurements helps: cooperative beats isolated on other satellites."""

import numpy as np
import pytest

from swarmcore.scenario import Scenario
from swarmcore.sim import simulate


@pytest.mark.slow
def test_cooperative_beats_isolated_on_others():
    coop, iso = [], []
    for seed in range(3):
        base = dict(n_sats=5, seed=seed, duration_s=120, graph={"kind": "complete"})
        coop.append(simulate(Scenario(**base, filter={"mode": "cooperative"})).summary())
        iso.append(simulate(Scenario(**base, filter={"mode": "isolated"})).summary())
    # Paired by seed: every run, both halves. Others' attitude gains most (an isolated
    # filter sees another satellite's attitude only through σ_q = 0.03 rad of its own
    # camera); position gains less (each observer's own position is uncertain to others).
    assert len(coop) == len(iso) == 3
    for c, i in zip(coop, iso, strict=True):
        for block in ("rms", "rms_second_half"):
            assert c[block]["others"]["att_rad"] < 0.5 * i[block]["others"]["att_rad"]
            assert c[block]["others"]["pos_m"] < 0.95 * i[block]["others"]["pos_m"]
    c = np.mean([s["rms"]["others"]["pos_m"] for s in coop])
    i = np.mean([s["rms"]["others"]["pos_m"] for s in iso])
    assert c < 0.9 * i, f"others' position: cooperative {c:.3g} vs isolated {i:.3g}"


def test_isolated_filter_uses_only_its_own_relative_measurements():
    base = dict(n_sats=4, seed=2, duration_s=3, graph={"kind": "complete"})
    coop = simulate(Scenario(**base))
    iso = simulate(Scenario(**base, filter={"mode": "isolated"}))
    # Complete graph, n = 4: 12 relative measurements per step, 3 of them a filter's own.
    assert (coop.gate_accepted + coop.gate_rejected)[0].tolist() == [12] * 4
    assert (iso.gate_accepted + iso.gate_rejected)[0].tolist() == [3] * 4
