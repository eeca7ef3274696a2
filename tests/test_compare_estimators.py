"""``swarm compare-estimators``: the paired ratio of relative errors to the reference is
taken over the (filter, peer) pairs both estimators estimate, so an estimator that tracks
only its graph neighbours is not flattered by the reference's errors of far pairs."""

import json

import numpy as np
import pytest

from swarm.studies.compare_estimators import relative_pairs, run_compare_estimators, same_pairs_ratio
from swarmcore.graphs import scenario_graph
from swarmrt.scenario_files import load_scenario


def _errors(K: int, near: float, far: float | None, n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(K, n, n) relative errors: ``near`` on the pairs (f, f ± 1), ``far`` on the others
    (NaN: not estimated), NaN on the diagonal."""
    p = np.full((K, n, n), np.nan)
    for f in range(n):
        for j in range(n):
            if abs(f - j) == 1:
                p[:, f, j] = near
            elif f != j and far is not None:
                p[:, f, j] = far
    return p, 1e-3 * p


def test_the_ratio_is_taken_over_the_pairs_both_estimate():
    """The reference: 1 mm on near pairs, 3 mm on far ones; an estimator that tracks only
    the near pairs, at 1.5 mm: 1.5× on the same pairs (its RMS over its pairs against the
    reference's RMS over all of its own would say 0.8×)."""
    K = 10
    ref = {"rel_pairs": relative_pairs(*_errors(K, 1e-3, 3e-3))}
    run = {"rel_pairs": relative_pairs(*_errors(K, 1.5e-3, None))}
    assert same_pairs_ratio(run, ref, "pos_m2") == pytest.approx(1.5, rel=1e-12)
    assert same_pairs_ratio(run, ref, "att_rad2") == pytest.approx(1.5, rel=1e-12)
    # Counted over the second half only: a first half at 100 mm changes nothing.
    p, a = _errors(K, 1.5e-3, None)
    p[: K // 2], a[: K // 2] = 0.1, 1e-4
    assert same_pairs_ratio({"rel_pairs": relative_pairs(p, a)}, ref, "pos_m2") == pytest.approx(1.5, rel=1e-12)
    # Nothing in common, or a run without the pairs (a results.jsonl of an older version): NaN.
    none = {"rel_pairs": relative_pairs(np.full((K, 4, 4), np.nan), np.full((K, 4, 4), np.nan))}
    assert np.isnan(same_pairs_ratio(none, ref, "pos_m2"))
    assert np.isnan(same_pairs_ratio({}, ref, "pos_m2"))


def test_compare_estimators_holds_gbp_to_centrals_errors_of_its_neighbours(tmp_path):
    """A short study (central and gbp, one seed, the ideal radio): gbp estimates only its
    graph neighbours, central every pair; the table's relative ratio is the same-pairs one,
    not the ratio of the two summaries."""
    sc = load_scenario("scenarios/estimators.yaml", ["duration_s=12"])
    doc = run_compare_estimators(sc, 1, tmp_path, estimators=("central", "gbp"), conditions=("ideal",), workers=1)
    runs = {r["estimator"]: r for r in doc["per_run"].values()}
    c, g = (np.asarray(runs[e]["rel_pairs"]["count"]) for e in ("central", "gbp"))
    G = scenario_graph(sc)
    neighbours = (G | G.T) & ~np.eye(sc.n_sats, dtype=bool)
    assert ((g > 0) <= neighbours).all() and (g > 0).any()
    assert ((c > 0) == ~np.eye(sc.n_sats, dtype=bool)).all()
    ratio = doc["summary"]["ideal"]["gbp"]["vs_ref"]["rel_pos"]
    assert ratio == pytest.approx(same_pairs_ratio(runs["gbp"], runs["central"], "pos_m2"), rel=1e-12)
    assert ratio != pytest.approx(runs["gbp"]["rel_pos"] / runs["central"]["rel_pos"], rel=1e-3)
    assert "pairs both estimate" in (tmp_path / "compare_estimators.md").read_text()
    assert json.loads((tmp_path / "compare_estimators.json").read_text())["summary"]["ideal"]["gbp"]["vs_ref"]["rel_pos"] == ratio
