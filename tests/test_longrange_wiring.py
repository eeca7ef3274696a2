"""The long-range core wired in: orbit.model j2 truth, filter.dynamics j2, angles-only bearings.

What is held here:

* scenario validation names the field at fault;
* the j2 truth is orbit.propagate of each satellite's ECI state, and its relative truth is
  orbit.eci_to_hill about the chief (the chief itself: sequential orbit.propagate of its
  elements); relmotion's prediction of it agrees to ~1e-6 m;
* the j2 filter's prediction is relmotion.propagate_relative's state and STM;
* bearings in the 6-row layout: the padding changes nothing (gate distance, information),
  and the padded Jacobians match central differences;
* the distributed world (world_sim's protocol machine) publishes the same truth and the same
  bearing detections as the in-process simulator computes, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from numdiff import numerical_jacobian, swarm_state  # type: ignore[attr-defined]
from protocol_driver import Driver, FakeClock
from pydantic import ValidationError

from swarmcore import orbit, relmotion
from swarmcore.agent import SyntheticPoseEstimator, filter_params
from swarmcore.mekf import BLOCK, observed_indices, predict, relative_residuals, update
from swarmcore.reference import chief_of, force_model_of
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate
from swarmcore.synthetic import synthetic_model
from swarmcore.world import SyntheticCameras, initial_estimate, initial_truth, step_truth, world_params


def j2_scenario(**over) -> Scenario:
    base = {
        "name": "lr", "seed": 4, "n_sats": 3, "duration_s": 6, "dt_s": 2.0,
        "orbit": {"model": "j2", "altitude_m": 550e3, "eccentricity": 0.001, "inclination_deg": 97.6, "raan_deg": 20.0,
                  "argp_deg": 30.0, "true_anomaly_deg": 10.0},
        "initial": {"layout": "train", "spacing_m": 2000.0, "position_max_m": 50.0, "velocity_max_m_s": 0.01},
    }
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            base[k] = {**base[k], **v}  # type: ignore[dict-item]
        else:
            base[k] = v
    return Scenario.model_validate(base)


@pytest.mark.parametrize(
    ("over", "field"),
    [
        ({"orbit": {"model": "j2", "altitude_m": 500e3, "semi_major_axis_m": 7e6}}, "orbit.altitude_m"),
        ({"orbit": {"model": "hcw", "drag": {"enabled": True}}}, "orbit.model"),
        ({"orbit": {"model": "j2", "altitude_m": 500e3, "eccentricity": 0.1}}, "orbit.eccentricity"),
        ({"filter": {"dynamics": "j2"}}, "filter.dynamics"),
        ({"orbit": {"model": "j2", "drag": {"enabled": True, "ballistic_m2_kg": [0.01, 0.02]}}}, "orbit.drag.ballistic_m2_kg"),
        ({"sensors": {"relative": {"model": "bearing"}}, "selection": {"strategy": "greedy"}}, "selection.strategy"),
    ],
)
def test_validation_names_the_field(over, field):
    with pytest.raises(ValidationError) as e:
        Scenario.model_validate({"n_sats": 3, **over})
    assert field in str(e.value)


def test_hcw_default_is_untouched():
    sc = Scenario.model_validate({"n_sats": 3})
    fp = filter_params(sc, 0)
    assert sc.orbit.model == "hcw" and sc.filter_dynamics() == "hcw"
    assert fp.chief is None and fp.dynamics == "hcw" and fp.relative_kind == "pose" and fp.mean_motion == 1.08e-3


def test_j2_truth_is_orbit_propagation_and_its_hill_frame():
    sc = j2_scenario(disturbances={"force": False}, orbit={"drag": {"enabled": True, "ballistic_m2_kg": [0.01, 0.02, 0.03]}})
    wp = world_params(sc)
    tr = initial_truth(sc)
    force = force_model_of(sc.orbit)
    assert force.atmosphere is not None
    # The chief: its elements, propagated step by step on its own.
    o = sc.orbit
    coe = np.array([o.semi_major_axis(), o.eccentricity, *np.radians([o.inclination_deg, o.raan_deg, o.argp_deg, o.true_anomaly_deg])])
    rc, vc = orbit.coe_to_rv(coe)
    r_I, v_I = tr.r_I.copy(), tr.v_I.copy()
    r_H0, v_H0 = tr.r_H.copy(), tr.v_H.copy()
    rc0, vc0 = rc, vc
    for _k in range(3):
        tr, _gyro = step_truth(wp, tr)
        r_I, v_I = orbit.propagate(r_I, v_I, sc.dt_s, force, step_s=o.step_s, ballistic_m2_kg=np.array([0.01, 0.02, 0.03]))
        rc, vc = orbit.propagate(rc, vc, sc.dt_s, force, step_s=o.step_s, ballistic_m2_kg=0.01)
        assert np.array_equal(tr.r_I, r_I) and np.array_equal(tr.v_I, v_I)
        a_c = orbit.acceleration(rc, vc, force, 0.01)
        r_H, v_H = orbit.eci_to_hill(rc, vc, r_I, v_I, a_c)
        assert np.array_equal(tr.r_H, r_H) and np.array_equal(tr.v_H, v_H)
    # 2 km along-track train: the relative model predicts the truth to well under a mm.
    st = relmotion.propagate_relative(rc0, vc0, r_H0, v_H0, 3 * sc.dt_s, force, step_s=o.step_s,
                                      ballistic_m2_kg=np.array([0.01, 0.02, 0.03]), chief_ballistic_m2_kg=0.01, with_stm=False)
    gap = np.abs(st.r_H_m - tr.r_H).max()
    print(f"relmotion vs j2 truth after 6 s at 2 km: {gap:.2e} m")
    assert gap < 1e-6
    assert np.abs(tr.r_H[:, 1] + np.array([0, 2000, 4000])).max() < 100.0  # the train


def test_j2_filter_prediction_is_relmotion():
    sc = j2_scenario(filter={"dynamics": "j2"})
    tr = initial_truth(sc)
    fp = filter_params(sc, 1)
    est = initial_estimate(sc, tr, 1)
    nxt = predict(est, fp, np.zeros(3))
    rc, vc = chief_of(sc).state(0)
    st = relmotion.propagate_relative(rc, vc, est.r_H, est.v_H, sc.dt_s, force_model_of(sc.orbit), step_s=sc.orbit.step_s)
    assert np.array_equal(nxt.r_H, st.r_H_m) and np.array_equal(nxt.v_H, st.v_H_m_s)
    assert st.phi is not None
    for b in range(3):
        s = slice(BLOCK * b + 6, BLOCK * b + 12)
        # P⁺ = Φ P Φᵀ + Q on each translation block (P starts block-diagonal).
        expect = st.phi[b] @ est.P[s, s] @ st.phi[b].T + fp.q_trans
        np.testing.assert_allclose(nxt.P[s, s], expect, rtol=1e-9, atol=1e-18)
    # ...and the HCW filter about the same chief differs (model error).
    hcw = predict(est, filter_params(j2_scenario(filter={"dynamics": "hcw"}), 1), np.zeros(3))
    assert np.abs(hcw.r_H - nxt.r_H).max() > 1e-6


def bearing_setup():
    sc = j2_scenario(sensors={"relative": {"model": "bearing", "bearing": {"sigma_px": 1.0, "f_px": 2000.0}}},
                     initial={"attitude": "random"})
    tr = initial_truth(sc)
    wp = world_params(sc)
    obs, tgt = np.array([0, 0, 1, 2]), np.array([1, 2, 2, 0])
    seen = SyntheticCameras(wp).observe(tr, obs, tgt)
    pe = SyntheticPoseEstimator(sc)
    from swarmcore.mekf import RelativeMeasurements

    rel = RelativeMeasurements.concat([pe.measure(i, seen[i], initial_estimate(sc, tr, i))[0] for i in sorted(seen)]).canonical()
    return sc, tr, rel


def test_bearing_detections_are_unit_lines_of_sight_with_the_set_noise():
    sc, tr, rel = bearing_setup()
    assert len(rel) == 4
    np.testing.assert_allclose(np.linalg.norm(rel.r_ij_Bi, axis=1), 1.0, atol=1e-15)
    # σ² of the camera plus the observer's prior attitude variance (initial_sigma.att_rad 0.01).
    s2 = (1.0 / 2000.0) ** 2 + 0.01**2
    np.testing.assert_allclose(rel.R_Bi[:, 0:2, 0:2], np.broadcast_to(s2 * np.eye(2), (4, 2, 2)), rtol=1e-12)
    np.testing.assert_array_equal(rel.R_Bi[:, 2:, 2:], np.broadcast_to(np.eye(4), (4, 4, 4)))
    # Shared in I: the true line of sight turned by the observer's estimated attitude.
    T_IH = chief_of(sc).T_IH(0.0)
    d_I = (tr.r_H[rel.target] - tr.r_H[rel.observer]) @ T_IH.T
    u_true = d_I / np.linalg.norm(d_I, axis=1, keepdims=True)
    ang = np.arccos(np.clip(np.sum(u_true * rel.r_ij_Bi, axis=1), -1, 1))
    assert np.all(ang < 0.06), ang  # camera noise 5e-4 rad + prior attitude error 0.01 rad/axis
    fp = filter_params(sc, 0)
    assert fp.relative_kind == "bearing" and fp.rel_dof == 2
    # χ²(2) gate at 0.999: −2 ln(0.001)
    assert fp.gate_threshold == pytest.approx(-2 * np.log(1e-3), rel=1e-12)


def test_bearing_padding_adds_nothing_and_jacobians_match_central_differences():
    sc, tr, rel = bearing_setup()
    fp = filter_params(sc, 0)
    est = initial_estimate(sc, tr, 0)
    y, Hi, Hj = relative_residuals(est, fp, rel)
    assert np.all(y[:, 2:] == 0) and np.all(Hi[:, 2:] == 0) and np.all(Hj[:, 2:] == 0)
    assert np.all(Hj[:, :, 0:3] == 0) and np.all(Hi[:, :, 0:3] == 0), "an inertial bearing sees no attitude"
    # The 2-row Mahalanobis distance equals the padded one the gate computes.
    _est1, rep = update(est, fp, None, rel)
    O = observed_indices(est.n)
    P_OO = est.P[np.ix_(O, O)]
    for m in range(len(rel)):
        i, j = rel.observer[m], rel.target[m]
        H = np.zeros((2, P_OO.shape[0]))
        H[:, 6 * i : 6 * i + 6] = Hi[m, 0:2]
        H[:, 6 * j : 6 * j + 6] = Hj[m, 0:2]
        S = H @ P_OO @ H.T + rel.R_Bi[m, 0:2, 0:2]
        assert rep.d2[m] == pytest.approx(float(y[m, 0:2] @ np.linalg.solve(S, y[m, 0:2])), rel=1e-9)
    assert rep.nis_dof == 2 * int(rep.accepted.sum())
    # Jacobians: measured at the estimate's own prediction (y = 0 there), the residual
    # y(x̂ ⊞ δ) = E(x̂ ⊞ δ)ᵀ ũ moves as −H δ.
    from dataclasses import replace

    from swarmcore.bearing import line_of_sight

    i, j = rel.observer, rel.target
    u_hat, _ = line_of_sight(np.tile([0.0, 0.0, 0.0, 1.0], (i.size, 1)), fp.T_IH(est.t), est.r_H[i], est.r_H[j])
    at_pred = replace(rel, r_ij_Bi=u_hat)
    assert np.abs(relative_residuals(est, fp, at_pred)[0]).max() < 1e-15
    J = numerical_jacobian(lambda e: relative_residuals(e, fp, at_pred)[0][:, 0:2].ravel(), est, swarm_state(0), eps=1e-6)
    y, Hi, Hj = relative_residuals(est, fp, at_pred)
    for m in range(len(rel)):
        rows = slice(2 * m, 2 * m + 2)
        for b, Hb in ((i[m], Hi[m]), (j[m], Hj[m])):
            cols = np.r_[BLOCK * b : BLOCK * b + 3, BLOCK * b + 6 : BLOCK * b + 9]
            np.testing.assert_allclose(-J[rows][:, cols], Hb[0:2], atol=1e-7 * max(1.0, np.abs(Hb).max()))


def test_world_protocol_matches_the_simulator_bit_for_bit():
    """The distributed world (its protocol machine, driven without a bus) publishes the
    truth and bearing detections the in-process simulator flies on."""
    from swarmrt.bus.messages import Keys
    from world_sim.protocol import WorldProtocol

    sc = j2_scenario(sensors={"relative": {"model": "bearing"}}, initial={"attitude": "random"},
                     orbit={"drag": {"enabled": True}}, duration_s=4)
    res = simulate(sc)
    keys = Keys("t")
    clock = FakeClock()
    w = WorldProtocol(sc, "t", synthetic_model(sc).cameras(), clock=clock)
    d = Driver(w, clock)
    from test_protocol_world import alive, est, finish

    d.feed(alive("recorder"))
    for i in range(sc.n_sats):
        d.feed(alive("agent", i), est(i, 0, "prior"))
    wp = world_params(sc)
    cams = SyntheticCameras(wp)
    tr = initial_truth(sc)
    for k in range(sc.steps):
        (truth,) = d.sent_on(keys.truth())
        assert truth.k == k
        np.testing.assert_array_equal(np.asarray(truth.r_H_m).reshape(-1, 3), res.truth.r_H_m[k])
        np.testing.assert_array_equal(np.asarray(truth.v_H_m_s).reshape(-1, 3), res.truth.v_H_m_s[k])
        if k:
            tr, _ = step_truth(wp, tr)
        obs, tgt = np.nonzero(~np.eye(sc.n_sats, dtype=bool))
        mine = cams.observe(tr, obs, tgt)
        for i in range(sc.n_sats):
            (cam,) = d.sent_on(keys.cam(i))
            got = np.array([x.r_ij_Bi_m for x in cam.detections])
            np.testing.assert_array_equal(got, mine[i].r_ij_Bi)
        d.take()
        d.feed(*finish(k))


def test_agent_protocol_shares_inertial_bearings_turned_by_its_prediction():
    """sat_agent (its protocol machine, no bus) measures bearings from the world's camera
    output with its own prediction, as the simulator does: the batch it sends equals
    SyntheticPoseEstimator.measure with that prediction, bit for bit."""
    from test_protocol_agent import K, WorldScript, prior_answer

    from sat_agent.protocol import AgentProtocol
    from swarmcore.estimators import builtin_estimator
    from swarmcore.graphs import scenario_graph
    from swarmrt.protocol import Event

    sc = j2_scenario(sensors={"relative": {"model": "bearing"}}, initial={"attitude": "random"})
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, "t", SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    (own,) = d.sent_on(K.meas(0))
    G = scenario_graph(sc)
    obs, tgt = np.nonzero(G & ~np.eye(sc.n_sats, dtype=bool))
    seen = SyntheticCameras(world_params(sc)).observe(world.truth, obs, tgt)
    rel, _ = SyntheticPoseEstimator(sc).measure(0, seen[0], initial_estimate(sc, world.truth, 0))
    assert len(rel) == 2
    np.testing.assert_array_equal(np.asarray(own.r_ij_Bi_m).reshape(-1, 3), rel.r_ij_Bi)


def test_starfox_scenario_flies_on_bearings_alone_with_one_gps():
    """scenarios/starfox.yaml, 60 s: only satellite 0 reads GPS, bearings are taken and
    used (through the lossy, delayed crosslink), and satellite 0's filter keeps its
    estimates of the others within a few of its own σ (prior 100 m per axis)."""
    from pathlib import Path

    from swarm.simulation import simulate_scenario
    from swarmcore.world import absolute_measurements
    from swarmrt.scenario_files import load_scenario

    sc = load_scenario(Path(__file__).resolve().parents[1] / "scenarios" / "starfox.yaml", ["duration_s=60"])
    absm = absolute_measurements(world_params(sc), initial_truth(sc))
    assert absm[0].r_H is not None and all(a.r_H is None for a in absm[1:])
    assert all(a.q_BI is not None for a in absm)
    res = simulate_scenario(sc)
    assert res.gate_accepted.sum() > 50 and res.late_used.sum() > 0
    P = res.est.P_diag[-1, 0].reshape(sc.n_sats, 12)[:, 6:9]
    err = res.est.r_H_m[-1, 0] - res.truth.r_H_m[-1]
    assert np.all(np.abs(err) < 5 * np.sqrt(P) + 1.0)
