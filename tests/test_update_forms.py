"""The fast updates equal the dissertation's stacked form to round-off."""

import numpy as np
import pytest

from swarmcore import graphs, quat
from swarmcore.agent import filter_params
from swarmcore.mekf import SOLVERS, choose_method, predict, update
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import (
    absolute_measurements,
    initial_estimate,
    initial_truth,
    step_truth,
    world_params,
)


def _setup(n, graph="complete", steps=5, seed=3, **kw):
    sc = Scenario(n_sats=n, seed=seed, graph={"kind": graph}, **kw)
    wp = world_params(sc)
    obs, tgt = graphs.edges(graphs.incidence(n, graph))
    truth = initial_truth(sc)
    p = filter_params(sc, 1)
    est = initial_estimate(sc, truth, 1)
    # Run a few steps so P carries realistic correlations and its ~20 decades of scale.
    for _ in range(steps):
        truth, gyro = step_truth(wp, truth)
        est = predict(est, p, gyro[1])
        est, _ = update(est, p, absolute_measurements(wp, truth)[1], synthetic_batch(wp, truth, obs, tgt))
    if steps:
        truth, gyro = step_truth(wp, truth)
        est = predict(est, p, gyro[1])
    return est, p, absolute_measurements(wp, truth)[1], synthetic_batch(wp, truth, obs, tgt)


def _close(a, b, P_scale):
    """Compare covariances element-wise on the correlation scale sqrt(P_ii P_jj)."""
    d = np.sqrt(np.diag(P_scale))
    return np.max(np.abs(a - b) / np.outer(d, d))


@pytest.mark.parametrize("steps", [0, 5], ids=["first-update", "converged"])
@pytest.mark.parametrize("n,graph", [(3, "complete"), (5, "chain"), (6, "complete"), (5, "star")])
def test_information_and_sequential_equal_stacked(n, graph, steps):
    # steps=0: a diagonal prior that the star tracker shrinks a million-fold, the case where
    # a naive information form (P − P G P) loses every digit of the own attitude.
    est, p, ab, rel = _setup(n, graph, steps=steps)
    out = {m: update(est, p, ab, rel, method=m) for m in ("stacked", "sequential", "information")}
    ref, rep_ref = out["stacked"]
    sd = np.sqrt(np.diag(ref.P))
    for m in ("sequential", "information"):
        e, rep = out[m]
        assert _close(e.P, ref.P, ref.P) < 1e-9, m
        np.testing.assert_array_equal(rep.accepted, rep_ref.accepted)
        assert rep.nis == pytest.approx(rep_ref.nis, rel=1e-8) and rep.nis_dof == rep_ref.nis_dof
        for key in ("r_H", "v_H", "omega_BI_B"):
            diff = np.abs(getattr(e, key) - getattr(ref, key))
            assert np.max(diff) < 1e-9 * max(1.0, np.max(np.abs(getattr(ref, key)))), (m, key)
        np.testing.assert_allclose(e.q_BI, ref.q_BI, atol=1e-12)
        np.testing.assert_allclose(e.bias_B, ref.bias_B, atol=1e-15 + 1e-6 * sd[12 * p.own + 3])


def test_equal_with_rejections_and_without_absolute():
    est, p, _ab, rel = _setup(4, "complete", sensors={"relative": {"sigma_att_rad": 0.003, "sigma_pos_m": 0.001}})
    # Corrupt two measurements so the gate rejects them.
    r = rel.r_ij_Bi.copy()
    r[[1, 5]] += 5.0
    rel = type(rel)(rel.observer, rel.target, rel.q_BjBi, r, rel.R_Bi)
    a, rep_a = update(est, p, None, rel, method="stacked")
    assert rep_a.n_rejected >= 2 and not rep_a.accepted[1] and not rep_a.accepted[5]
    for m in ("sequential", "information"):
        b, rep_b = update(est, p, None, rel, method=m)
        np.testing.assert_array_equal(rep_b.accepted, rep_a.accepted)
        assert rep_b.nis == pytest.approx(rep_a.nis, rel=1e-8) and rep_b.nis_dof == rep_a.nis_dof
        assert _close(b.P, a.P, a.P) < 1e-9, m
        # Round-off is ~1e-16 of each quantity's scale (m, m/s, rad/s); these leave 100×.
        np.testing.assert_allclose(b.r_H, a.r_H, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.v_H, a.v_H, rtol=0, atol=1e-14)
        np.testing.assert_allclose(b.omega_BI_B, a.omega_BI_B, rtol=0, atol=1e-14)
        np.testing.assert_allclose(b.bias_B, a.bias_B, rtol=0, atol=1e-17)
        np.testing.assert_allclose(quat.angle_between(b.q_BI, a.q_BI), 0.0, atol=1e-12)


def test_no_measurements_leaves_state_and_covariance_alone():
    est, p, _ab, rel = _setup(3)
    for m in SOLVERS:
        e, rep = update(est, p, None, rel.subset(np.zeros(len(rel), bool)), method=m)
        np.testing.assert_array_equal(e.P, 0.5 * (est.P + est.P.T))
        for key in ("r_H", "v_H", "omega_BI_B", "bias_B"):
            np.testing.assert_array_equal(getattr(e, key), getattr(est, key), err_msg=f"{m}: {key}")
        np.testing.assert_allclose(e.q_BI, est.q_BI, rtol=0, atol=1e-15, err_msg=m)
        assert (e.step, e.t) == (est.step, est.t) and rep.d2.size == 0 and rep.nis_dof == 0


def test_auto_chooses_sequential_for_few_measurements():
    assert choose_method("auto", 10, 2) == "sequential"
    assert choose_method("auto", 10, 90) == "information"
    assert choose_method("stacked", 10, 2) == "stacked"


def test_unknown_satellite_id_is_refused():
    est, p, ab, rel = _setup(3)
    bad = type(rel)(rel.observer.copy(), rel.target.copy(), rel.q_BjBi, rel.r_ij_Bi, rel.R_Bi)
    bad.target[0] = 7
    with pytest.raises(ValueError, match="unknown"):
        update(est, p, ab, bad)


def test_simulation_is_identical_for_every_update_form():
    base = dict(n_sats=3, duration_s=15, seed=11)
    res = {m: simulate(Scenario(**base, filter={"update": m})) for m in ("information", "sequential", "stacked")}
    for m in ("information", "sequential"):
        np.testing.assert_allclose(res[m].pos_err_m, res["stacked"].pos_err_m, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(res[m].att_err_rad, res["stacked"].att_err_rad, rtol=1e-9, atol=1e-13)
