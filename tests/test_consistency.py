"""Statistical consistency: NEES and NIS inside their 95 % χ² bounds over Monte Carlo.

The truth follows the filter's model (matched noise, no filter-only tuning noise, gate off)
so a consistent filter gives NEES ~ χ²(6) per pose and NIS ~ χ²(dof) per update. With M
runs, the run-average at each step, times M, is χ²(6M) (NEES) and χ²(Σ dof) (NIS).
Seeds are fixed, so the test is deterministic; the bounds are the textbook two-sided 95 %.
With links (2 s latency, 30 % bursty loss, replay) the NIS is that of each step's own
update, whose prior already holds every replayed late batch. The centralized reference
(``central``: every anchor's absolute readings in every filter) is held to the same.
"""

import numpy as np
import pytest
from scipy.stats import chi2

from swarm.simulation import simulate_scenario
from swarmcore.scenario import Scenario

pytestmark = pytest.mark.slow

RUNS = 16
STEPS = 40


#: Links with 2 s latency (plus jitter) and 30 % bursty loss: every peer batch arrives
#: late or not at all, and the filters replay what arrives.
LINKS = {"enabled": True, "latency": {"fixed_s": 2.0, "jitter": {"distribution": "uniform", "scale_s": 0.5}},
         "loss": {"model": "gilbert_elliott", "rate": 0.3, "mean_burst": 3.0}}


def _mc(n, graph, links=None, estimator="full"):
    out = []
    for r in range(RUNS):
        sc = Scenario(
            n_sats=n,
            seed=1000 + r,
            duration_s=STEPS - 1,
            graph={"kind": graph},
            filter={"att_rw_other_rad_sqrt_s": 0.0, "pos_rw_m_sqrt_s": 0.0, "gate": {"enabled": False}, "late": "replay"},
            links=links or {},
            estimator={"kind": estimator},
        )
        out.append(simulate_scenario(sc))
    return out


@pytest.fixture(scope="module", params=[(3, "complete", None, "full"), (5, "chain", None, "full"),
                                        (4, "complete", LINKS, "full"), (4, "chain", None, "central")],
                ids=["n3-complete", "n5-chain", "n4-links-2s-30pc-bursty-replay", "n4-chain-central"])
def mc(request):
    n, graph, links, estimator = request.param
    runs = _mc(n, graph, links, estimator)
    if links is not None:
        late = sum(r.late_used.sum() for r in runs)
        assert late > 0, "the links made nothing late: the case tests nothing"
    return (n, graph), runs


def test_nees_within_chi2_bounds(mc):
    (_n, _graph), runs = mc
    nees = np.stack([r.nees for r in runs])  # (M, K, F, n)
    avg = nees.mean(axis=0)  # (K, F, n): run-average per step, filter and target
    lo, hi = chi2.ppf([0.025, 0.975], 6 * RUNS) / RUNS
    inside = np.mean((avg >= lo) & (avg <= hi))
    # Nominally 95 %; pairs share measurements and steps are correlated, so allow 85 %.
    assert inside >= 0.85, f"only {inside:.1%} of run-averaged NEES inside [{lo:.2f}, {hi:.2f}]"
    # The grand mean over everything, against the bounds of its (effective) sample.
    grand = avg.mean()
    lo_g, hi_g = chi2.ppf([0.025, 0.975], 6 * RUNS * STEPS) / (RUNS * STEPS)
    assert lo_g * 0.9 <= grand <= hi_g * 1.1, f"grand mean NEES {grand:.3f} (dof 6)"


def test_nis_within_chi2_bounds(mc):
    (_n, _graph), runs = mc
    nis = np.stack([r.nis for r in runs])  # (M, K, F)
    dof = np.stack([r.nis_dof for r in runs])
    tot, totdof = nis.sum(axis=0), dof.sum(axis=0)  # (K, F)
    lo = chi2.ppf(0.025, totdof) / totdof
    hi = chi2.ppf(0.975, totdof) / totdof
    ratio = tot / totdof
    inside = np.mean((ratio >= lo) & (ratio <= hi))
    assert inside >= 0.85, f"only {inside:.1%} of NIS/dof inside the 95 % bounds"
    assert abs(nis.sum() / dof.sum() - 1.0) < 0.05, f"overall NIS/dof {nis.sum() / dof.sum():.3f}"
