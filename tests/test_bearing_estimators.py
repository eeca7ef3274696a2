"""Angles-only bearings in the decentralized estimators (``ci``, ``pairwise``, ``gbp``).

A bearing travels in the inertial frame I: the observer turns its camera's unit line of
sight ``ũ_B`` with its own predicted attitude, ``ũ_I = T(q̂_i)ᵀ ũ_B``, and attaches
``R = (σ² + σ_a²) I₂`` on the tangent-plane residual (``swarmcore.agent.inertial_bearings``;
σ_a² the mean variance of that attitude). The filter's model is ``y = Eᵀ ũ_I``, a function
of the two positions alone (``swarmcore.mekf.bearing_residuals_padded``, 6-row layout).

Held here:

* the Jacobians each decentralized estimator stacks (``ci`` and ``gbp``: own 12 error
  states and the peers' ``[a, Δr]``, :func:`swarmcore.estimators.ci.stack_factors`;
  ``pairwise``: its two-satellite joint) against central differences on the manifold;
* the attitude the observer turned with is covered by R: the shared ``ũ_I`` moves with the
  observer's attitude error as ``M a`` with ``M Mᵀ = I₂`` in the residual's basis, so an
  isotropic attitude error of variance σ_a² adds exactly σ_a² I₂;
* the scenario check: the three accept bearings, an estimator that declares nothing is
  refused naming the field, image pipelines stay refused;
* NEES and NIS over Monte Carlo on a J2 along-track train with GPS on one satellite (the
  StarFOX setting, short): ``ci`` and ``gbp`` within the upper χ² bound; ``pairwise``'s own
  state is not (its stated limit, docs/estimators.md), and that is held too.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numdiff import numerical_jacobian, swarm_state  # type: ignore[attr-defined]
from scipy.stats import chi2
from test_longrange_wiring import j2_scenario

from swarmcore import quat
from swarmcore.agent import Detections, filter_params, inertial_bearings
from swarmcore.bearing import line_of_sight, tangent_basis
from swarmcore.estimators import IncompatibleScenario, builtin_estimator, configure, estimator_class
from swarmcore.estimators.ci import stack_factors
from swarmcore.estimators.pairwise import PairwiseEstimator
from swarmcore.mekf import BLOCK, RelativeMeasurements, gate, relative_residuals
from swarmcore.sim import simulate
from swarmcore.world import initial_estimate, initial_truth
from swarmrt.bus.convert import batch_wire_size
from swarmrt.estimators import codec_for

SIGMA_RAD = 5e-4  # 1 px at f = 2000 px


def _bearing_sc(**over):
    """A 4-satellite J2 along-track train (2 km apart), bearings of 5e-4 rad, GPS (5 m) on
    satellite 0 only, star trackers on all, 10 s steps."""
    base = dict(n_sats=4, dt_s=10.0, duration_s=300.0,
                sensors={"relative": {"model": "bearing", "bearing": {"sigma_px": 1.0, "f_px": 2000.0, "half_fov_deg": 60}},
                         "gps": {"sigma_m": 5.0, "satellites": [0]}},
                filter={"dynamics": "j2", "initial_sigma": {"pos_m": 20.0, "vel_m_s": 0.01}},
                initial={"position_max_m": 20.0, "velocity_max_m_s": 0.01, "attitude": "random"}, bound={"enabled": False})
    base.update(over)
    return j2_scenario(**base)


def _at_prediction(est, fp, observer, target) -> RelativeMeasurements:
    """Bearings ``observer → target`` (rows of ``est``) equal to the estimate's own
    prediction (residual zero there), R = σ² I₂ in the 6-row layout."""
    i, j = np.asarray(observer), np.asarray(target)
    m = i.size
    u, _ = line_of_sight(np.tile(quat.IDENTITY, (m, 1)), fp.T_IH(est.t), est.r_H[i], est.r_H[j])
    R = np.broadcast_to(np.eye(6), (m, 6, 6)).copy()
    R[:, 0:2, 0:2] = SIGMA_RAD**2 * np.eye(2)
    return RelativeMeasurements(i, j, np.tile(quat.IDENTITY, (m, 1)), u, R)


def test_ci_and_gbp_bearing_jacobians_match_central_differences():
    """The own satellite (row 0) and two peers; bearings own → peer and peer → own, as ci and
    gbp linearise them (gate on the joint, then :func:`stack_factors`): ``Ho`` over the own
    12 error states and ``Hp`` over each peer's ``[a, Δr]`` are minus the derivatives of the
    residual; every other column (attitudes, rates, bias, velocities) is zero."""
    sc = _bearing_sc(n_sats=3)
    tr = initial_truth(sc)
    joint = initial_estimate(sc, tr, 0)  # rows 0 (own, gyro mode), 1, 2
    jp = dataclasses.replace(filter_params(sc, 0), n=3, own=0, max_iterations=1)
    assert jp.relative_kind == "bearing"
    meas = _at_prediction(joint, jp, [0, 0, 1, 2], [1, 2, 0, 0]).canonical()
    y, Hi, Hj, _d2, accepted = gate(joint, jp, meas)
    assert accepted.all() and np.abs(y).max() < 1e-15
    Ho, Hp, R = stack_factors(meas, Hi, Hj, 2)
    assert Ho.shape == (6 * len(meas), BLOCK) and Hp.shape == (6 * len(meas), 12) and R.shape == (6 * len(meas),) * 2
    J = numerical_jacobian(lambda e: relative_residuals(e, jp, meas)[0].ravel(), joint, swarm_state(0), eps=1e-6)
    scale = max(1.0, np.abs(Ho).max(), np.abs(Hp).max())
    np.testing.assert_allclose(-J[:, 0:BLOCK], Ho, atol=1e-7 * scale)
    for p in (1, 2):
        pose_cols = np.r_[BLOCK * p : BLOCK * p + 3, BLOCK * p + 6 : BLOCK * p + 9]
        np.testing.assert_allclose(-J[:, pose_cols], Hp[:, 6 * (p - 1) : 6 * p], atol=1e-7 * scale)
        rest = np.r_[BLOCK * p + 3 : BLOCK * p + 6, BLOCK * p + 9 : BLOCK * p + 12]
        assert np.abs(J[:, rest]).max() < 1e-7 * scale
    # A bearing in I sees positions only, and is not blind to them.
    assert np.all(Ho[:, 0:6] == 0) and np.all(Ho[:, 9:12] == 0) and np.abs(Ho[:, 6:9]).max() > 1e-6
    # Padded rows 2–5: no Jacobian, unit noise uncorrelated with rows 0–1.
    pad = np.tile(np.r_[False, False, True, True, True, True], len(meas))
    assert np.all(Ho[pad] == 0) and np.all(Hp[pad] == 0)
    np.testing.assert_array_equal(R[np.ix_(pad, pad)], np.eye(pad.sum()))
    assert np.all(R[np.ix_(pad, ~pad)] == 0)


def test_pairwise_bearing_jacobians_match_central_differences():
    """pairwise's joint of an encounter (own row 0 in gyro mode, the peer in row 1) and
    both directions' bearings: the Jacobian blocks of its update against central
    differences over both satellites' 12 error states."""
    sc = _bearing_sc(n_sats=2)
    tr = initial_truth(sc)
    est = PairwiseEstimator(sc, 0)
    joint = initial_estimate(sc, tr, 0)
    meas = _at_prediction(joint, est.jp, [0, 1], [1, 0]).canonical()
    y, Hi, Hj = relative_residuals(joint, est.jp, meas)
    assert np.abs(y).max() < 1e-15
    J = numerical_jacobian(lambda e: relative_residuals(e, est.jp, meas)[0].ravel(), joint, swarm_state(0), eps=1e-6)
    H = np.zeros((6 * len(meas), 2 * BLOCK))
    for m in range(len(meas)):
        rows = slice(6 * m, 6 * m + 6)
        for b, Hb in ((meas.observer[m], Hi[m]), (meas.target[m], Hj[m])):
            H[rows, np.r_[BLOCK * b : BLOCK * b + 3, BLOCK * b + 6 : BLOCK * b + 9]] = Hb
    np.testing.assert_allclose(-J, H, atol=1e-7 * max(1.0, np.abs(H).max()))
    assert np.abs(H[:, [6, 7, 8, 18, 19, 20]]).max() > 1e-6


def test_the_shared_bearing_carries_the_observers_attitude_error_as_R_says():
    """``ũ_I = T(q̂)ᵀ ũ_B``: with the observer's true attitude ``q = δq(a) ⊗ q̂`` the shared
    vector moves as ``M a`` (central differences through ``inertial_bearings``); in the
    residual's tangent basis ``Eᵀ M (Eᵀ M)ᵀ = I₂``, so an attitude error ``N(0, σ_a² I₃)``
    adds σ_a² I₂ to the residual: the inflation ``R = (σ² + σ_a²) I₂`` the observer attaches
    (its attitude columns are then zero, as the Jacobian tests hold)."""
    sc = _bearing_sc(n_sats=3)
    tr = initial_truth(sc)
    pred = initial_estimate(sc, tr, 0, [0])  # an own-state estimator's prediction: one row
    u_I = np.array([[0.3, -0.5, 0.8], [-0.6, 0.1, 0.2]])
    u_I /= np.linalg.norm(u_I, axis=1, keepdims=True)
    T_true = quat.attitude_matrix(pred.q_BI[0])

    def shared(a: np.ndarray) -> np.ndarray:
        q = quat.retract(pred.q_BI[0], a)  # the true attitude the camera looked with
        u_B = u_I @ quat.attitude_matrix(q).T
        dets = Detections(0, np.array([1, 2]), np.zeros(2, dtype=int), np.tile(quat.IDENTITY, (2, 1)), u_B)
        rel, _ = inertial_bearings(0, dets, pred, SIGMA_RAD)
        return rel.r_ij_Bi

    assert np.allclose(shared(np.zeros(3)), u_I @ T_true.T @ T_true, atol=1e-15)
    eps = 1e-6
    D = np.stack([(shared(eps * e) - shared(-eps * e)) / (2 * eps) for e in np.eye(3)], axis=-1)  # (2, 3, 3)
    for m in range(2):
        M = tangent_basis(u_I[m]).T @ D[m]
        np.testing.assert_allclose(M @ M.T, np.eye(2), atol=1e-8)
    rel, _ = inertial_bearings(0, Detections(0, np.array([1]), np.zeros(1, dtype=int), np.tile(quat.IDENTITY, (1, 1)), u_I[:1]),
                               pred, SIGMA_RAD)
    var_att = float(np.mean(np.diag(pred.P[0:3, 0:3])))
    np.testing.assert_allclose(rel.R_Bi[0, 0:2, 0:2], (SIGMA_RAD**2 + var_att) * np.eye(2), rtol=1e-12)


@pytest.mark.parametrize("kind", ["ci", "pairwise", "gbp"])
def test_decentralized_estimators_accept_bearings_and_predict_their_own_satellite(kind):
    sc = _bearing_sc(estimator={"kind": kind})
    configure(estimator_class(kind), sc)  # no refusal
    est = builtin_estimator(sc, 2)
    est.start(initial_estimate(sc, initial_truth(sc), 2, [2]))
    p = est.prediction()
    assert p is not None and p.n == 1
    # ...and what they refuse still names the field.
    with pytest.raises(IncompatibleScenario, match=r"vision\.pipeline"):
        estimator_class(kind).check_scenario(sc.model_copy(update={"vision": sc.vision.model_copy(update={"pipeline": "stereo"})}),
                                             estimator_class(kind).Params())


def test_an_estimator_that_declares_nothing_refuses_bearings_naming_the_field():
    from swarmcore.estimators.own import OwnStateEstimator

    class Solo(OwnStateEstimator):  # a plug-in that says nothing about bearings
        kind = "solo-test"

        def transmit(self, k):
            return None

        def step(self, inputs):
            raise NotImplementedError

        def view(self):
            raise NotImplementedError

    sc = _bearing_sc()
    with pytest.raises(IncompatibleScenario, match=r"sensors\.relative\.model: bearing"):
        Solo.check_scenario(sc, Solo.Params())


def _bearing_nees(estimator: str | dict, seeds) -> tuple[float, float, float, int]:
    """Mean NEES/dof of every filter's own pose and of its relative estimates over the
    second half, and the NIS/dof of its updates, over ``seeds``; and the number of filters.
    ``estimator``: its kind, or the whole ``estimator`` section."""
    own, rel, nis, dof = [], [], 0.0, 0
    for s in seeds:
        sc = _bearing_sc(seed=300 + s, estimator={"kind": estimator} if isinstance(estimator, str) else estimator)
        res = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg))
        K, n = res.nees.shape[0], sc.n_sats
        assert int(res.gate_accepted.sum()) > 4 * K, "bearings were fused"  # pairwise: one encounter per agent and step
        own.append(np.nanmean(res.nees[K // 2 :, np.arange(n), np.arange(n)]))
        assert res.rel_nees is not None
        rel.append(np.nanmean(res.rel_nees[K // 2 :]))
        ok = res.nis_dof[K // 2 :] > 0
        nis += float(np.nansum(res.nis[K // 2 :][ok]))
        dof += int(res.nis_dof[K // 2 :][ok].sum())
    return float(np.mean(own)) / 6, float(np.mean(rel)) / 6, nis / dof, len(seeds) * 4


@pytest.mark.parametrize("kind", ["ci", "gbp"])
def test_bearing_fusion_is_consistent_over_monte_carlo(kind):
    """3 seeds × 4 filters, 300 s: own and relative NEES/dof within the upper χ² bound
    (97.5 %) of the mean of 12 independent χ²(6)/6 (a filter's steps counted as one sample,
    the stricter bound), and above a floor that a collapsed or exploded covariance would
    miss; the NIS per dof of the updates as well (CI's is below 1 by construction)."""
    own, rel, nis, N = _bearing_nees(kind, range(3))
    hi = chi2.ppf(0.975, 6 * N) / (6 * N)
    print(f"{kind} bearings: NEES/dof own {own:.3f}, relative {rel:.3f}, NIS/dof {nis:.3f}; upper bound {hi:.3f}")
    assert 0.2 < own <= hi and 0.1 < rel <= hi
    assert 0.1 < nis <= hi


def test_pairwise_with_bearings_is_overconfident_in_its_own_state_its_stated_limit():
    """pairwise's limit (docs/estimators.md): on the same Monte Carlo its own NEES/dof is far
    above the upper χ² bound with Luft et al.'s rule for absent peers (``absent: scale``,
    the default; measured 7.9), and ``absent: keep`` more than halves it (measured 1.8, still
    above; its relative NEES/dof 2.2 is above too, not held); the default's relative
    estimates, and the NIS of either, are within the bound."""
    own_s, rel_s, nis_s, N = _bearing_nees("pairwise", range(3))
    own_k, rel_k, nis_k, _ = _bearing_nees({"kind": "pairwise", "absent": "keep"}, range(3))
    hi = chi2.ppf(0.975, 6 * N) / (6 * N)
    print(f"pairwise bearings NEES/dof own, relative, NIS/dof: scale {own_s:.3f} {rel_s:.3f} {nis_s:.3f}; "
          f"keep {own_k:.3f} {rel_k:.3f} {nis_k:.3f}; upper bound {hi:.3f}")
    assert own_s > hi, "the limit docs/estimators.md states is gone: update the docs"
    assert own_k < own_s / 2
    assert 0.1 < rel_s <= hi
    assert 0.1 < nis_s <= hi and 0.1 < nis_k <= hi
