"""``gbp``, Gaussian belief propagation (swarmcore/estimators/gbp.py): its factor
messages against numerical derivatives and against the information form, its cavity
bookkeeping, its message on the wire, its consistency over Monte Carlo, and the estimator
study's scenario flown in-process."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
from numdiff import EUCLIDEAN, numerical_jacobian, swarm_state
from scipy.stats import chi2
from test_estimators import _own_and_relative_nees

from swarmcore import quat
from swarmcore.estimators import BUILTIN, Received, StepInputs, builtin_estimator
from swarmcore.estimators.gbp import GbpEstimator, GbpMessage, GbpParams, factor_message, joint_factors, stack_factors
from swarmcore.estimators.own import absolute_update
from swarmcore.mekf import FilterParams, RelativeMeasurements, SwarmEstimate, apply_correction, predict, relative_residuals
from swarmcore.scenario import Scenario
from swarmcore.sensors import relative_pose
from swarmcore.sim import simulate
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params
from swarmrt.bus import messages as M
from swarmrt.bus.convert import batch_wire_size
from swarmrt.estimators import codec_for

N_E = 1.08e-3
J = np.diag([1.67, 8.33, 3.67])


def _sc(**kw) -> Scenario:
    base = dict(name="t", seed=3, n_sats=4, duration_s=20, initial={"attitude": "identity"}, estimator={"kind": "gbp"})
    base.update(kw)
    return Scenario(**base)


def _joint(rng, n=3, t=321.0) -> SwarmEstimate:
    q = quat.random_quaternion(rng, n)
    return SwarmEstimate(0, t, q, rng.uniform(-0.01, 0.01, (n, 3)), rng.uniform(-10, 10, (n, 3)),
                         rng.uniform(-0.01, 0.01, (n, 3)), rng.uniform(-1e-4, 1e-4, 3), np.eye(12 * n))


def _factor_case(seed: int):
    """Own satellite row 0 of a 3-satellite joint, both directions and two measurements of
    one pair (observer → target 0→2, 2→0, 1→0, 0→1), exact (zero residuals): the
    measurements, the residual Jacobians, and ``∂y/∂δ`` by numerical differences over all
    36 error states."""
    rng = np.random.default_rng(seed)
    est = _joint(rng)
    p = FilterParams(n=3, own=0, dt=1.0, mean_motion=N_E, J=J, arw=3e-7, rrw=3e-10, torque=5e-6, accel=1e-8)
    obs, tgt = np.array([0, 2, 1, 0]), np.array([2, 0, 0, 1])

    def meas(x: SwarmEstimate) -> RelativeMeasurements:
        q, r = relative_pose(N_E, x.t, x.q_BI, x.r_H, obs, tgt)
        return RelativeMeasurements(obs, tgt, q, r, np.tile(np.diag(rng.uniform(1e-6, 1e-2, 6)), (4, 1, 1)))

    m0 = meas(est)
    y0, Hi, Hj = relative_residuals(est, p, m0)
    np.testing.assert_allclose(y0, 0.0, atol=1e-12)
    num = numerical_jacobian(lambda x: relative_residuals(est, p, dataclasses.replace(meas(x), R_Bi=m0.R_Bi))[0].ravel(),
                             est, swarm_state(0), EUCLIDEAN, eps=1e-5)
    return m0, Hi, Hj, num


@pytest.mark.parametrize("seed", [0, 1])
def test_factor_jacobians_match_numerical_derivatives(seed):
    """The stacked relative factors of one belief (own satellite row 0 of the joint, two
    neighbours, both directions and two measurements of one pair): ``∂y/∂δ`` is ``Ho`` on
    the own 12 error states and ``Hp`` on the neighbours' [a, Δr], zero elsewhere."""
    m0, Hi, Hj, num = _factor_case(seed)
    Ho, Hp, R = stack_factors(m0, Hi, Hj, 2)
    assert Ho.shape == (24, 12) and Hp.shape == (24, 12) and R.shape == (24, 24)
    H = np.zeros((24, 36))
    H[:, 0:12] = Ho
    pose = np.r_[0:3, 6:9]
    for r in range(2):
        H[:, 12 * (r + 1) + pose] = Hp[:, 6 * r : 6 * r + 6]
    np.testing.assert_allclose(num, H, rtol=0, atol=5e-9)
    np.testing.assert_array_equal(R[6:12, 6:12], m0.R_Bi[1])


@pytest.mark.parametrize("seed", [0, 1])
def test_joint_factor_jacobians_match_numerical_derivatives(seed):
    """``fusion: joint``: the relative factors on the pair potentials' joint (own row 0, two
    neighbours, both directions and two measurements of one pair): ``∂y/∂δ`` over all 36
    error states is ``H`` of :func:`joint_factors` (the observer's and target's [a, Δr]
    blocks, zero elsewhere), its noise the measurements' R."""
    m0, Hi, Hj, num = _factor_case(seed)
    H, R = joint_factors(m0, Hi, Hj, 3)
    assert H.shape == (24, 36) and R.shape == (24, 24)
    np.testing.assert_allclose(num, H, rtol=0, atol=5e-9)
    np.testing.assert_array_equal(R[18:24, 18:24], m0.R_Bi[3])


def _flown(sc: Scenario, steps: int):
    """Every satellite's estimator flown ``steps`` steps by hand on the ideal radio (every
    message of the step delivered); returns them, the world's state and its parameters."""
    wp = world_params(sc)
    truth = initial_truth(sc)
    n = sc.n_sats
    ests = [builtin_estimator(sc, i) for i in range(n)]
    for i, e in enumerate(ests):
        e.start(initial_estimate(sc, truth, i, e.prior_ids()))
    for k in range(steps):
        gyro = [None] * n
        if k > 0:
            truth, g = step_truth(wp, truth)
            gyro = list(g)
        absm = absolute_measurements(wp, truth)
        rel = synthetic_batch(wp, truth, *np.nonzero(~np.eye(n, dtype=bool)))
        for i, e in enumerate(ests):
            e.predict(k, gyro[i])
        sent = [e.transmit(k) for e in ests]
        for i, e in enumerate(ests):
            heard = [Received(j, k, rel.subset(rel.observer == j), sent[j]) for j in range(n) if j != i]
            e.step(StepInputs(k, truth.t, gyro[i], absm[i], rel.subset(rel.observer == i), heard))
    return ests, truth, wp


def test_joint_messages_never_enter_the_pair_potentials_nor_their_cavity():
    """``fusion: joint`` (the default): a neighbour's message of the step, moved by 5 mm,
    moves the belief and the cavity towards the other neighbour, but neither the cavity
    towards that neighbour (it never takes its message) nor the pair potentials (messages
    are fused into a copy of them each step, never accumulated)."""
    sc = _sc(n_sats=3, duration_s=10, graph={"kind": "complete", "absolute": [1]})
    ests, truth, wp = _flown(sc, 5)
    k = 5
    truth, g = step_truth(wp, truth)
    absm = absolute_measurements(wp, truth)
    rel = synthetic_batch(wp, truth, *np.nonzero(~np.eye(3, dtype=bool)))
    for i, e in enumerate(ests):
        e.predict(k, g[i])
    sent = [e.transmit(k) for e in ests]
    moved = dataclasses.replace(sent[1], r_H=(sent[1].r_H + np.float32(0.005)).astype(np.float32))
    out = []
    for m1 in (sent[1], moved):
        e = copy.deepcopy(ests[0])
        heard = [Received(1, k, rel.subset(rel.observer == 1), m1), Received(2, k, rel.subset(rel.observer == 2), sent[2])]
        e.step(StepInputs(k, truth.t, g[0], absm[0], rel.subset(rel.observer == 0), heard))
        out.append(e)
    a, b = out
    pa, pb = a.pairs, b.pairs  # type: ignore[attr-defined]
    np.testing.assert_array_equal(a.cav[1].P, b.cav[1].P)  # type: ignore[attr-defined]
    np.testing.assert_allclose(a.cav[1].r_H, b.cav[1].r_H, rtol=0, atol=1e-12)  # type: ignore[attr-defined]
    assert np.abs(a.cav[2].r_H - b.cav[2].r_H).max() > 1e-4  # type: ignore[attr-defined]
    assert np.abs(a.e.r_H - b.e.r_H).max() > 1e-4
    np.testing.assert_array_equal(pa.P, pb.P)
    ja, jb = (apply_correction(p.ref, e._jfp, p.d, p.P) for p, e in ((pa, a), (pb, b)))  # type: ignore[attr-defined]
    np.testing.assert_allclose(ja.r_H, jb.r_H, rtol=0, atol=1e-9)
    np.testing.assert_allclose(quat.local(ja.q_BI, jb.q_BI), 0.0, atol=1e-8)  # the re-centring is first order in d


def test_joint_sends_each_cavity_predicted_to_the_step_it_is_used_at():
    """With a fixed 3 s link latency (late replay), each cavity goes out predicted by three
    steps (the held rate, the gyro bias prior's σ): the message of step k is the neighbours'
    fresh message at step k + 3."""
    sc = _sc(n_sats=3, duration_s=10, graph={"kind": "complete", "absolute": [1]}, filter={"late": "replay", "history_s": 30},
             links={"enabled": True, "latency": {"fixed_s": 3.0, "speed_of_light": False}})
    e = builtin_estimator(sc, 0)
    assert e._lead == 3  # type: ignore[attr-defined]
    e.start(initial_estimate(sc, initial_truth(sc), 0, e.prior_ids()))
    msg = e.transmit(0)
    c = e.cav[1]  # type: ignore[attr-defined]
    for _ in range(3):
        c = predict(c, e._pfp, None)  # type: ignore[attr-defined]
    q, r, P = msg.pose(msg.row(1))  # type: ignore[arg-type]
    np.testing.assert_allclose(r, c.r_H[0], rtol=0, atol=1e-5)
    np.testing.assert_allclose(quat.local(q, c.q_BI[0]), 0.0, atol=1e-6)
    _at_or_above(P, c.P[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])])
    sc0 = _sc(n_sats=3, graph={"kind": "complete", "absolute": [1]})
    assert builtin_estimator(sc0, 0)._lead == 0  # type: ignore[attr-defined]


def test_plain_gbp_update_is_prior_information_plus_factor_message():
    """``fusion: kalman``: the belief's information is the prior's plus the factor →
    variable message ``Λ = Hoᵀ (R + Hp P_cav Hpᵀ)⁻¹ Ho`` (module docstring)."""
    rng = np.random.default_rng(4)
    sc = _sc(n_sats=2, estimator={"kind": "gbp", "fusion": "kalman"}, graph={"kind": "complete", "absolute": "none"})
    truth = initial_truth(sc)
    wp = world_params(sc)
    e = builtin_estimator(sc, 0)
    assert isinstance(e, GbpEstimator)
    e.start(initial_estimate(sc, truth, 0, e.prior_ids()))
    peer = builtin_estimator(sc, 1)
    peer.start(initial_estimate(sc, truth, 1, peer.prior_ids()))
    msg = peer.transmit(0)
    rel = synthetic_batch(wp, truth, np.array([0, 1]), np.array([1, 0]))
    A = rng.normal(size=(12, 12))
    e.est = dataclasses.replace(e.e, P=e.e.P + 1e-6 * A @ A.T)
    prior = e.e
    post = e._fuse_all({-1: prior}, rel.canonical(), {1: msg})[0][-1]  # type: ignore[attr-defined]
    joint, jp, local = e._linearise(prior, rel, {1: msg}, [1])
    _, Hi, Hj = relative_residuals(joint, jp, local)
    Ho, Hp, R = stack_factors(local, Hi, Hj, 1)
    Lam, _ = factor_message(Ho, Hp, R, msg.pose(msg.row(0))[2])  # type: ignore[arg-type]
    np.testing.assert_allclose(np.linalg.inv(post.P), np.linalg.inv(prior.P) + Lam, rtol=1e-6)


def test_cavity_towards_a_neighbour_never_fuses_its_factors():
    """Two satellites, plain GBP: the cavity belief towards the only neighbour is the own
    filter fed its own gyro and readings and nothing of the peer; the belief is tighter. The message carries the cavity, not the belief."""
    sc = _sc(n_sats=2, duration_s=10, estimator={"kind": "gbp", "fusion": "kalman"}, graph={"kind": "complete", "absolute": [0]})
    wp = world_params(sc)
    truth = initial_truth(sc)
    ests = [builtin_estimator(sc, i) for i in range(2)]
    for i, e in enumerate(ests):
        e.start(initial_estimate(sc, truth, i, e.prior_ids()))
    fp = ests[0].fp  # type: ignore[attr-defined]
    ref = initial_estimate(sc, truth, 0, [0])  # the own filter alone
    obs, tgt = np.array([0, 1]), np.array([1, 0])
    for k in range(6):
        gyro = [None, None]
        if k > 0:
            truth, g = step_truth(wp, truth)
            gyro = [g[0], g[1]]
        absm = absolute_measurements(wp, truth)
        rel = synthetic_batch(wp, truth, obs, tgt)
        for i, e in enumerate(ests):
            e.predict(k, gyro[i])
        if k > 0:
            ref = predict(ref, fp, gyro[0])
        sent = [e.transmit(k) for e in ests]
        P_sent = ests[0].cav[1].P  # type: ignore[attr-defined]
        for i, e in enumerate(ests):
            j = 1 - i
            e.step(StepInputs(k, truth.t, gyro[i], absm[i], rel.subset(rel.observer == i), [Received(j, k, rel.subset(rel.observer == j), sent[j])]))
        ref = absolute_update(ref, fp, absm[0])[0]
        cav = ests[0].cav[1]  # type: ignore[attr-defined]
        # the same to the linearisation of the dynamics at the belief's mean (module docstring)
        np.testing.assert_allclose(cav.P, ref.P, rtol=1e-3, atol=1e-15)
        np.testing.assert_allclose(cav.r_H, ref.r_H, rtol=0, atol=1e-9)
        np.testing.assert_allclose(quat.local(cav.q_BI, ref.q_BI), 0.0, atol=1e-10)
        assert np.trace(ests[0].e.P) < np.trace(cav.P)  # type: ignore[attr-defined]
        P = sent[0].pose(0)[2]  # the message of step k: the cavity's prior pose covariance, on the wire
        _at_or_above(P, P_sent[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])])


def test_message_round_trips_bit_for_bit_and_refuses_garbage():
    sc = _sc(graph={"kind": "complete"})
    truth = initial_truth(sc)
    codec = codec_for(sc)
    e = builtin_estimator(sc, 0)
    e.start(initial_estimate(sc, truth, 0, e.prior_ids()))
    payload = e.transmit(0)
    assert isinstance(payload, GbpMessage) and payload.targets.tolist() == [1, 2, 3]
    assert len(GbpEstimator.encode(payload)) == 10 + 3 * 82 + 24 == GbpMessage.size_of(3)
    msg = codec.to_msg(payload)
    wire = M.encode(M.MeasBatch(run="r", sender="agent-0", k=0, t_s=0.0, observer=0, estimator=msg, R_Bi=M.Matrix(shape=[0, 6, 6])))
    got = codec.from_msg(M.decode("meas", wire).estimator, 0, 0)
    assert isinstance(got, GbpMessage)
    for f in dataclasses.fields(payload):
        a, b = getattr(got, f.name), getattr(payload, f.name)
        assert np.asarray(a).dtype == np.asarray(b).dtype
        np.testing.assert_array_equal(a, b)
    for r in range(3):
        for a, b in zip(got.pose(r), payload.pose(r), strict=True):
            np.testing.assert_array_equal(a, b)
    # The covariance the receiver rebuilds is the sender's cavity's, a hair above it.
    _at_or_above(payload.pose(0)[2], e.cav[1].P[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])])  # type: ignore[attr-defined]
    rng = np.random.default_rng(0)
    for _ in range(200):  # and of any pose covariance, however correlated and scaled (1e-6 rad … 1 m)
        A = rng.normal(size=(6, 6)) * np.r_[np.full(3, 10.0 ** rng.uniform(-6, -3)), np.full(3, 10.0 ** rng.uniform(-4, 0))][:, None]
        P0 = A @ A.T + 1e-3 * np.diag(np.diag(A @ A.T))
        e.cav[1] = dataclasses.replace(e.cav[1], P=np.eye(12))  # type: ignore[attr-defined]
        e.cav[1].P[np.ix_(np.r_[0:3, 6:9], np.r_[0:3, 6:9])] = P0  # type: ignore[attr-defined]
        _at_or_above(e.transmit(0).pose(0)[2], P0, within=1.1)
    raw = GbpEstimator.encode(payload)
    for bad in (raw[:5], raw[:-1], raw + b"\0"):
        with pytest.raises(ValueError):
            GbpEstimator.decode(bad)
    nan = bytearray(raw)
    nan[16:20] = np.array([np.nan], "<f4").tobytes()
    with pytest.raises(ValueError):
        GbpEstimator.decode(bytes(nan))
    size = batch_wire_size("x", codec.to_msg)(0, 0, 0.0, RelativeMeasurements.empty(), np.zeros(0, dtype=int), payload)
    assert size > len(raw)


def _at_or_above(P: np.ndarray, P0: np.ndarray, within: float = 1.01) -> None:
    """P ⪰ P0 and within ``within`` of it (whitened by P0)."""
    L = np.linalg.cholesky(P0)
    W = np.linalg.solve(L, np.linalg.solve(L, P).T)
    ev = np.linalg.eigvalsh(0.5 * (W + W.T))
    assert ev.min() >= 1.0 - 1e-9 and ev.max() <= within, ev


def test_gbp_is_a_builtin_on_the_graph_radio():
    assert BUILTIN["gbp"] is GbpEstimator and GbpEstimator.radio == "graph"


def _nees(fusion: str, seeds) -> tuple[float, float, int]:
    """Own and relative NEES/dof (test_estimators' measure) and the number of filters."""
    est = {"kind": "gbp", "fusion": fusion.split("/")[0]}
    if "/" in fusion:
        est["peers"] = fusion.split("/")[1]
    own, rel = _own_and_relative_nees(est, seeds, bound={"enabled": False})
    return own, rel, 5 * len(seeds)


@pytest.mark.parametrize("fusion", ["joint", "joint/bound", "ci"])
def test_gbp_is_consistent_over_monte_carlo(fusion):
    """NEES/dof of the own and relative estimates over 4 seeds × 5 filters (second half of
    40 s; n = 5, complete graph: every triangle a loop) within the upper χ² bound (97.5 %)
    of the mean of 20 independent χ²(6)/6 (the steps of one filter are correlated: counted
    as one sample each, the stricter bound). Only the upper bound is held: split CI is
    conservative by construction (ci's is below the lower one too: docs/estimators.md), and
    ``joint`` bounds the neighbours' mutual correlation (``peers: auto``, here ``common``:
    what they share counted once; ``joint/bound``: for any correlation)."""
    own, rel, N = _nees(fusion, range(4))
    hi = chi2.ppf(0.975, 6 * N) / (6 * N)
    print(f"gbp ({fusion}) NEES/dof own {own:.3f}, relative {rel:.3f}; upper bound {hi:.3f}")
    assert 0.2 < own <= hi and 0.1 < rel <= hi


@pytest.mark.slow
def test_plain_gbp_is_overconfident_on_loops():
    """Why the conservative fusion: the same Monte Carlo with plain GBP (``fusion:
    kalman``) claims far more than it knows."""
    own, _, N = _nees("kalman", range(3))
    assert own > chi2.ppf(0.975, 6 * N) / (6 * N)


def _study(**kw) -> Scenario:
    import yaml

    with open("scenarios/estimators.yaml") as f:
        d = yaml.safe_load(f)
    d.update(duration_s=25, estimator={"kind": "gbp"}, bound={"enabled": False})
    d.update(kw)
    return Scenario(**d)


def test_flies_the_estimator_study_in_process():
    """scenarios/estimators.yaml (shortened): every filter claims its own state and the
    neighbours it fused, its traffic is counted, nothing is unusable on the ideal radio."""
    sc = _study()
    res = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg))
    s = res.summary()
    print({k: s[k] for k in ("rms_second_half", "nees", "traffic")})
    assert s["estimator"]["kind"] == "gbp" if isinstance(s["estimator"], dict) else True
    assert s["rms_second_half"]["self"]["pos_m"] < 0.05
    assert s["nees"]["mean"] / 6 < 1.5
    assert 0 < s["traffic"]["bytes_per_sat_per_s_mean"] < 3000
    assert np.isfinite(s["relative"]["rms"]["pos_m"])


def test_late_messages_are_replayed_or_dropped_and_counted():
    """A 2.5 s latency: every message late. Replayed at their step (used, counted) the own
    errors stay small; dropped (filter.late: drop) they are counted and lost."""
    out = {}
    for late in ("replay", "drop"):
        sc = _study(duration_s=30, filter={"late": late, "history_s": 30},
                    links={"enabled": True, "latency": {"fixed_s": 2.5, "speed_of_light": False}})
        s = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg)).summary()
        out[late] = (s["late"], s["rms_second_half"]["self"]["pos_m"], s["nees"]["mean"] / 6)
    (rl, rpos, rnees), (dl, dpos, _) = out["replay"], out["drop"]
    print(out)
    assert rl["used"] > 0 and rl["replayed_steps"] > 0 and rl["dropped"] == 0
    assert dl["used"] == 0 and dl["dropped"] > 0
    assert rpos < 0.7 * dpos, (rpos, dpos)
    assert rnees < 1.4


@pytest.mark.parametrize("peers", ["auto", "common", "bound", "sequential", "independent"])
def test_every_peers_option_flies(peers):
    """The ways of handling the neighbours' mutual correlation (module docstring) fly and
    claim finite estimates; an unknown one is refused when the scenario is loaded."""
    sc = _sc(n_sats=4, duration_s=12, estimator={"kind": "gbp", "peers": peers}, bound={"enabled": False})
    s = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg)).summary()
    assert np.isfinite(s["nees"]["mean"]) and s["rms"]["self"]["pos_m"] < 0.1


def test_unknown_options_are_refused_naming_the_field():
    from swarmcore.estimators import IncompatibleScenario, configure

    with pytest.raises(IncompatibleScenario, match=r"estimator\.peers"):
        configure(GbpEstimator, _sc(estimator={"kind": "gbp", "peers": "all"}))
    with pytest.raises(IncompatibleScenario, match=r"estimator\.fusion"):
        configure(GbpEstimator, _sc(estimator={"kind": "gbp", "fusion": "admm"}))
    with pytest.raises(IncompatibleScenario, match=r"estimator\.peers: common .* fusion: ci"):
        configure(GbpEstimator, _sc(estimator={"kind": "gbp", "fusion": "ci", "peers": "common"}))


def test_auto_takes_common_with_poses_and_bound_with_bearings_and_filter_forms():
    sc = _sc(n_sats=4, estimator={"kind": "gbp"})
    assert GbpEstimator(sc, 0)._peers == "common"
    assert GbpEstimator(sc, 0, GbpParams(fusion="ci"))._peers == "bound"
    bearing = sc.model_copy(update={"sensors": sc.sensors.model_copy(update={
        "relative": sc.sensors.relative.model_copy(update={"model": "bearing"})})})
    assert GbpEstimator(bearing, 0)._peers == "bound"


def _spd(rng, k: int = 6) -> np.ndarray:
    A = rng.normal(size=(k, k))
    return A @ A.T + 0.1 * np.eye(k)


@pytest.mark.parametrize("m", [2, 3, 5])
def test_common_noise_bounds_every_covariance_of_its_model(m):
    """``peers: common`` (:func:`_peer_noise`): for messages whose errors are their own parts
    plus a part common to all (the same attitude error in I, turned into each one's body
    frame, and the same position error), of any covariance Γ the messages allow (``B_k Γ
    B_kᵀ ⪯ C_k``), the stack's noise is at or above the true covariance; the differences of
    the messages keep their own covariances (what ``bound`` inflates m times); and treating
    them as independent would not be enough."""
    from swarmcore.estimators.gbp import _common_modes, _peer_noise

    rng = np.random.default_rng(70 + m)
    short = 0.0
    for _ in range(60):
        Cs = [_spd(rng) for _ in range(m)]
        q = [quat.random_quaternion(rng) for _ in range(m)]
        Bs = [_common_modes(x) for x in q]
        D = _peer_noise(Cs, Bs, "common", m)
        G0 = _spd(rng)
        # the largest multiple of G0 every message allows: B_k t G0 B_kᵀ ⪯ C_k
        t = min(1.0 / np.linalg.eigvalsh(np.linalg.solve(np.linalg.cholesky(C), np.linalg.solve(np.linalg.cholesky(C), B @ G0 @ B.T).T)).max()
                for C, B in zip(Cs, Bs))
        for frac in (1.0, 0.5, 0.1):
            Gam = frac * t * G0
            B = np.vstack(Bs)
            cov = np.zeros((6 * m, 6 * m))
            for k in range(m):
                cov[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = Cs[k] - Bs[k] @ Gam @ Bs[k].T
            cov += B @ Gam @ B.T
            assert np.linalg.eigvalsh(D - cov).min() > -1e-9 * np.abs(D).max()
            short = max(short, np.linalg.eigvalsh(cov - _peer_noise(Cs, Bs, "independent", m)).max())
        # a difference of two messages, in the frame where their common parts cancel: its own covariances
        x = rng.normal(size=6)
        v = np.zeros(6 * m)
        v[:6], v[6:12] = Bs[0] @ x, -Bs[1] @ x
        blk = _peer_noise(Cs, Bs, "independent", m)
        assert v @ D @ v == pytest.approx(v @ blk @ v, rel=1e-9)
        assert v @ _peer_noise(Cs, Bs, "bound", m) @ v == pytest.approx(m * (v @ blk @ v), rel=1e-12)
    assert short > 0, "the model's covariances exceed the block diagonal: independence would be overconfident"
    assert np.array_equal(_peer_noise(Cs[:1], Bs[:1], "common", 1), Cs[0])

