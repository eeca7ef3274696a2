"""The estimator interface and the built-in estimators: full (bit for bit the MEKF it
wraps), ci and pairwise (consistent over Monte Carlo), their messages, their selection by
name, the relative covariances every view claims."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swarmcore import quat
from swarmcore.agent import AgentFilter, filter_params
from swarmcore.estimators import BUILTIN, IncompatibleScenario, StepInputs, builtin_estimator, configure, estimator_class
from swarmcore.estimators.base import cold_prior
from swarmcore.estimators.ci import CIEstimator, ci_weight
from swarmcore.estimators.views import relative_pose_cov
from swarmcore.graphs import encounter_schedule, incidence
from swarmcore.mekf import AbsoluteMeasurement, RelativeMeasurements
from swarmcore.metrics import relative_errors_of
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params
from swarmrt.bus import messages as M
from swarmrt.bus.convert import batch_wire_size
from swarmrt.estimators import EstimatorCodec, check_estimator, codec_for


def _sc(**kw) -> Scenario:
    base = dict(name="t", seed=3, n_sats=4, duration_s=20, initial={"attitude": "identity"})
    base.update(kw)
    return Scenario(**base)


def test_full_estimator_equals_the_agent_filter_it_wraps_bit_for_bit():
    sc = _sc()
    wp = world_params(sc)
    truth = initial_truth(sc)
    est = builtin_estimator(sc, 1)
    est.start(initial_estimate(sc, truth, 1))
    ref = AgentFilter(filter_params(sc, 1), initial_estimate(sc, truth, 1), sc.filter.mode)
    obs, tgt = np.nonzero(~np.eye(4, dtype=bool))
    for k in range(8):
        gyro = None
        if k > 0:
            truth, g = step_truth(wp, truth)
            gyro = g[1]
        absm = absolute_measurements(wp, truth)[1]
        rel = synthetic_batch(wp, truth, obs, tgt)
        est.predict(k, gyro)
        own = rel.subset(rel.observer == 1)
        others = rel.subset(rel.observer != 1)
        from swarmcore.estimators import Received

        rep = est.step(StepInputs(k, truth.t, gyro, absm, own, [Received(2, k, others)]))
        rref, _ = ref.step(k, gyro, absm, rel)
        for f in ("q_BI", "omega_BI_B", "r_H", "v_H", "bias_B", "P"):
            np.testing.assert_array_equal(getattr(est.view().full, f), getattr(ref.est, f))
        assert (rep.gate_accepted, rep.gate_rejected) == (rref.n_accepted, rref.n_rejected)


def test_relative_error_is_a_j_minus_T_rel_a_i_to_first_order():
    """The relative attitude error every view's P_rel_pose describes, a_rel = a_j − T(q̂_BjBi) a_i,
    against the exact error of q_j ⊗ q_i⁻¹ (a numerical derivative through the retraction)."""
    rng = np.random.default_rng(1)
    q_hat = quat.random_quaternion(rng, 3)
    r_hat = rng.normal(size=(3, 3))
    for _ in range(20):
        a = rng.normal(scale=1e-6, size=(3, 3))
        dr = rng.normal(scale=1e-3, size=(3, 3))
        q_true = quat.retract(q_hat, a)
        a_rel, dr_rel = relative_errors_of(q_hat, r_hat, 0, q_true, r_hat + dr)
        T_ji = quat.attitude_matrix(quat.qmul(q_hat, quat.qconj(np.broadcast_to(q_hat[0], (3, 4)))))
        lin = a - (T_ji @ a[0][:, None])[..., 0]
        np.testing.assert_allclose(a_rel[1:], lin[1:], rtol=0, atol=1e-11)
        np.testing.assert_allclose(dr_rel[1:], (dr - dr[0])[1:], atol=1e-15)
        assert np.isnan(a_rel[0]).all()


def test_relative_pose_covariance_matches_the_linear_map_by_monte_carlo():
    rng = np.random.default_rng(2)
    q = quat.random_quaternion(rng, 2)
    A = rng.normal(size=(12, 12)) * 1e-2
    P = A @ A.T + 1e-6 * np.eye(12)  # joint [pose_own, pose_peer]
    P_own, P_peer, P_cross = P[:6, :6], P[6:, 6:], P[6:, :6]
    C = relative_pose_cov(q[0], q[1:], P_own, P_peer[None], P_cross[None])[0]
    e = rng.multivariate_normal(np.zeros(12), P, size=200_000)
    T_ji = quat.attitude_matrix(quat.qmul(q[1], quat.qconj(q[0])))
    rel = np.c_[e[:, 6:9] - e[:, 0:3] @ T_ji.T, e[:, 9:12] - e[:, 3:6]]
    np.testing.assert_allclose(np.cov(rel.T), C, atol=0.02 * np.abs(C).max())  # 200,000 samples: ~1 % sampling error


@pytest.mark.parametrize("rho", [-0.95, 0.0, 0.95])
def test_covariance_intersection_never_understates_the_error_whatever_the_correlation(rho):
    """Two estimates of the same 2-vector with a correlation CI is not told: the fused
    covariance bounds the fused error's true covariance (P_CI − Cov ⪰ 0)."""
    Pa = np.array([[1.0, 0.3], [0.3, 0.5]])
    Pb = np.array([[0.4, -0.1], [-0.1, 2.0]])
    La, Lb = np.linalg.cholesky(Pa), np.linalg.cholesky(Pb)
    cross = rho * La @ Lb.T
    Ia, Ib = np.linalg.inv(Pa), np.linalg.inv(Pb)

    def logdet(w):
        return -np.linalg.slogdet(w * Ia + (1 - w) * Ib)[1]

    w = ci_weight(logdet)
    P = np.linalg.inv(w * Ia + (1 - w) * Ib)
    Ka, Kb = P @ (w * Ia), P @ ((1 - w) * Ib)
    true = Ka @ Pa @ Ka.T + Kb @ Pb @ Kb.T + Ka @ cross @ Kb.T + Kb @ cross.T @ Ka.T
    assert np.linalg.eigvalsh(P - true).min() > -1e-12
    assert 0 < w < 1


def test_estimator_kind_and_parameters_are_validated_naming_the_field():
    with pytest.raises(IncompatibleScenario, match=r"estimator.kind: unknown estimator 'kalmanish'"):
        check_estimator(_sc(estimator={"kind": "kalmanish"}))
    with pytest.raises(IncompatibleScenario, match=r"estimator.split"):
        check_estimator(_sc(estimator={"kind": "ci", "split": "maybe"}))
    with pytest.raises(IncompatibleScenario, match=r"estimator.colour: Extra inputs"):
        check_estimator(_sc(estimator={"kind": "pairwise", "colour": 3}))
    with pytest.raises(IncompatibleScenario, match=r"selection.strategy: 'greedy' plans from every satellite's full-swarm covariance"):
        check_estimator(_sc(estimator={"kind": "ci"}, selection={"strategy": "greedy"}))
    check_estimator(_sc(estimator={"kind": "ci"}, selection={"strategy": "random_tree"}))
    assert check_estimator(_sc()) is BUILTIN["full"] and estimator_class("pairwise").kind == "pairwise"
    assert configure(CIEstimator, _sc(estimator={"kind": "ci", "split": False})).split is False  # type: ignore[attr-defined]


@pytest.mark.parametrize("kind", ["ci", "pairwise", "gbp"])
def test_estimator_messages_cross_the_bus_bit_for_bit(kind):
    sc = _sc(estimator={"kind": kind})
    truth = initial_truth(sc)
    codec = codec_for(sc)
    ests = [builtin_estimator(sc, i) for i in range(sc.n_sats)]
    for i, e in enumerate(ests):
        e.start(initial_estimate(sc, truth, i, e.prior_ids()))
    if kind == "pairwise":  # give it factors to send
        ests[0].sigma[1] = np.arange(144.0).reshape(12, 12)  # type: ignore[attr-defined]
        ests[0].sigma[2] = -np.eye(12)  # type: ignore[attr-defined]
    payload = ests[0].transmit(0)
    msg = codec.to_msg(payload)
    wire = M.encode(M.MeasBatch(run="r", sender="agent-0", k=0, t_s=0.0, observer=0, estimator=msg,
                                R_Bi=M.Matrix(shape=[0, 6, 6])))
    back = M.decode("meas", wire)
    got = codec.from_msg(back.estimator, 0, 0)
    for f in dataclasses.fields(payload):
        np.testing.assert_array_equal(getattr(got, f.name), getattr(payload, f.name))
    assert EstimatorCodec(BUILTIN["ci" if kind == "pairwise" else "pairwise"]).from_msg(back.estimator, 0, 0) is None
    size = batch_wire_size("x", codec.to_msg)(0, 0, 0.0, RelativeMeasurements.empty(), np.zeros(0, dtype=int), payload)
    assert size > batch_wire_size("x", codec.to_msg)(0, 0, 0.0, RelativeMeasurements.empty(), np.zeros(0, dtype=int), None)


def _raw_ci(**changes):
    c = M.CiState(q_BI=[0, 0, 0, 1.0], omega_BI_B_rad_s=[0, 0, 0.0], r_H_m=[1, 2, 3.0], v_H_m_s=[0, 0, 0.0],
                  P_pose=M.Matrix(shape=[6, 6], data=np.eye(6).ravel().tolist()))
    for k, v in changes.items():
        if k == "P_pose":
            c.P_pose.CopyFrom(v)
        else:
            del getattr(c, k)[:]
            getattr(c, k).extend(v)
    return M.EstimatorMessage(kind="ci", version=1, ci=c)


@pytest.mark.parametrize("est, why", [
    (_raw_ci(q_BI=[0, 0, 0, 2.0]), "estimator.ci.q_BI: not a unit quaternion"),
    (_raw_ci(r_H_m=[1, 2]), "estimator.ci.r_H_m: 2 numbers"),
    (_raw_ci(P_pose=M.Matrix(shape=[6, 6], data=(np.eye(6) + np.triu(np.ones((6, 6)), 1)).ravel().tolist())), "P_pose: not symmetric"),
    (_raw_ci(P_pose=M.Matrix(shape=[6, 6], data=(-np.eye(6)).ravel().tolist())), "P_pose: not positive-definite"),
    (_raw_ci(v_H_m_s=[0, 0, float("nan")]), "v_H_m_s: not finite"),
    (M.EstimatorMessage(kind="Bad Kind!", version=1), "estimator.kind"),
    (M.EstimatorMessage(kind="ci", version=1), "without a body"),
    (M.EstimatorMessage(kind="", version=1, opaque=b"x"), "a body without a kind"),
    (M.EstimatorMessage(kind="plug", version=1, opaque=b"x" * (M.MAX_OPAQUE_BYTES + 1)), "bytes (at most"),
    (M.EstimatorMessage(kind="pairwise", version=1, pairwise=M.PairwiseState(
        q_BI=[0, 0, 0, 1.0], omega_BI_B_rad_s=[0, 0, 0.0], r_H_m=[0, 0, 0.0], v_H_m_s=[0, 0, 0.0], bias_B_rad_s=[0, 0, 0.0],
        P=M.Matrix(shape=[12, 12], data=np.eye(12).ravel().tolist()), partners=[2, 1],
        sigma=M.Matrix(shape=[2, 12, 12], data=[0.0] * 288))), "partners: not ascending"),
    (M.EstimatorMessage(kind="pairwise", version=1, pairwise=M.PairwiseState(
        q_BI=[0, 0, 0, 1.0], omega_BI_B_rad_s=[0, 0, 0.0], r_H_m=[0, 0, 0.0], v_H_m_s=[0, 0, 0.0], bias_B_rad_s=[0, 0, 0.0],
        P=M.Matrix(shape=[12, 12], data=np.eye(12).ravel().tolist()), partners=[0],
        sigma=M.Matrix(shape=[1, 12, 12], data=[0.0] * 144))), "cannot be its own partner"),
])
def test_hostile_estimator_messages_are_refused_naming_the_problem(est, why):
    wire = M.encode(M.MeasBatch(run="r", sender="agent-0", k=0, t_s=0.0, observer=0, estimator=est, R_Bi=M.Matrix(shape=[0, 6, 6])))
    with pytest.raises(M.MessageError, match=why.replace("(", r"\(").replace(")", r"\)")):
        M.decode("meas", wire, n_sats=4)


def test_a_plugin_message_over_the_opaque_limit_is_an_error_at_its_sender():
    """Every receiver refuses an opaque body over MAX_OPAQUE_BYTES; the sender's codec (used by
    `swarm sim` and the agent alike) says so with the sizes instead of sending it."""

    class Big:
        kind, message_version = "big", 1
        size = M.MAX_OPAQUE_BYTES + 1

        @classmethod
        def encode(cls, payload) -> bytes:
            return b"x" * cls.size

    codec = EstimatorCodec(Big)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=f"'big'.*encodes to {M.MAX_OPAQUE_BYTES + 1} bytes, over the {M.MAX_OPAQUE_BYTES}"):
        codec.to_msg(object())
    Big.size = M.MAX_OPAQUE_BYTES  # at the limit: sent, and every receiver takes it
    msg = codec.to_msg(object())
    wire = M.encode(M.MeasBatch(run="r", sender="agent-0", k=0, t_s=0.0, observer=0, estimator=msg, R_Bi=M.Matrix(shape=[0, 6, 6])))
    assert len(M.decode("meas", wire, n_sats=4).estimator.opaque) == M.MAX_OPAQUE_BYTES


def test_encounter_schedule_is_a_matching_every_step():
    G = incidence(9, "complete")
    colour, C = encounter_schedule(G)
    assert C >= 8 and (colour == colour.T).all() and (np.diag(colour) == -1).all()
    for c in range(C):
        deg = (colour == c).sum(axis=1)
        assert deg.max() <= 1, "a satellite meets two peers in one step"
    assert (colour[~np.eye(9, dtype=bool)] >= 0).all()
    again, C2 = encounter_schedule(G)
    assert C2 == C and (again == colour).all()


def test_a_cold_start_takes_its_own_readings_as_the_posterior():
    sc = _sc(estimator={"kind": "ci"})
    wp = world_params(sc)
    truth = initial_truth(sc)
    absm = absolute_measurements(wp, truth)[2]
    inputs = StepInputs(0, 0.0, None, absm, RelativeMeasurements.empty())
    prior = cold_prior(sc, 2, inputs)
    assert prior is not None and prior.n == 1
    np.testing.assert_array_equal(prior.r_H[0], absm.r_H)
    assert cold_prior(sc, 2, dataclasses.replace(inputs, absolute=AbsoluteMeasurement(None, None, 1.0, 1.0))) is None
    e = builtin_estimator(sc, 2)
    assert e.cold_start(inputs) and not e.prior_pending and e.view().ids.tolist() == [2]


def _own_and_relative_nees(estimator: str | dict, seeds=range(6), **over) -> tuple[float, float]:
    """Mean NEES/dof of every filter's own and relative estimates over the second half
    (n = 5, 40 s, complete graph), over ``seeds``. ``estimator``: its kind, or the whole
    ``estimator`` section; ``over``: other scenario fields."""
    own, rel = [], []
    for seed in seeds:
        est = {"kind": estimator} if isinstance(estimator, str) else estimator
        sc = _sc(n_sats=5, duration_s=40, seed=100 + seed, estimator=est, **over)
        res = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg))
        K = res.nees.shape[0]
        idx = np.arange(5)
        own.append(np.nanmean(res.nees[K // 2 :, idx, idx]))
        assert res.rel_nees is not None
        rel.append(np.nanmean(res.rel_nees[K // 2 :]))
    return float(np.mean(own)) / 6, float(np.mean(rel)) / 6


@pytest.mark.slow
def test_decentralized_estimators_are_not_overconfident():
    """Monte Carlo over the same seeds: ci adds no overconfidence to the full filter's own
    baseline (its own-state NEES/dof here is ~1.1: the MEKF's own model, shared by every
    estimator); pairwise stays within the issue's 1.4; both own and relative."""
    full_own, full_rel = _own_and_relative_nees("full")
    ci_own, ci_rel = _own_and_relative_nees("ci")
    pw_own, pw_rel = _own_and_relative_nees("pairwise")
    print(f"NEES/dof own, relative: full {full_own:.3f} {full_rel:.3f}; ci {ci_own:.3f} {ci_rel:.3f}; pairwise {pw_own:.3f} {pw_rel:.3f}")
    assert ci_own <= full_own + 0.1 and ci_rel <= max(full_own, full_rel) + 0.1
    assert pw_own <= 1.4 and pw_rel <= 1.4


@pytest.mark.parametrize("kind", ["ci", "pairwise", "gbp", "full"])
def test_an_agent_restarted_in_process_remembers_nothing_of_its_first_life(kind):
    """A restarted ``sat_agent`` is a new process: the in-process outage must start a new
    estimator too. The first life's peers (their step-k messages, pairwise factors) must
    not reach the second life's view; every claim after the restart stays finite and
    within reason."""
    sc = _sc(n_sats=5, duration_s=30, seed=5, estimator={"kind": kind})
    kill, back = 8, 20
    res = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg), outages={2: (kill, back)})
    assert np.isnan(res.nees[kill:back, 2]).all()  # dead: no claims
    if kind != "full":  # a cold start: its own readings, no peer yet
        others = np.delete(res.nees[back, 2], 2)
        assert np.isnan(others).all(), f"stale peers in the restarted view: {others}"
        assert np.isfinite(res.nees[back, 2, 2])
    after = res.nees[back:, 2]
    assert np.nanmax(after) < 200.0, f"restarted agent's NEES up to {np.nanmax(after):.3g}"


def test_ci_replays_late_deliveries_at_their_own_step():
    """Under a 2.5 s latency every peer message comes late: with ``filter.late: replay`` ci
    files each under its step and re-runs its own state from there (used, counted, and the
    own errors those measurements buy); with ``drop`` it uses none of them."""
    out = {}
    for late in ("replay", "drop"):
        sc = _sc(n_sats=5, duration_s=40, seed=11, estimator={"kind": "ci"}, filter={"late": late},
                 graph={"kind": "complete", "absolute": [0]},  # the others know where they are from their peers
                 links={"enabled": True, "latency": {"fixed_s": 2.5, "speed_of_light": False}})
        res = simulate(sc, wire_size=batch_wire_size("t", codec_for(sc).to_msg))
        s = res.summary()
        out[late] = (s["late"], s["rms_second_half"]["self"]["pos_m"], s["nees"]["mean"] / 6)
    (rl, rpos, rnees), (dl, dpos, _) = out["replay"], out["drop"]
    assert rl["used"] > 0 and rl["replayed_steps"] > 0 and rl["dropped"] == 0
    assert dl["used"] == 0 and dl["dropped"] > 0
    assert rpos < 0.5 * dpos, (rpos, dpos)
    assert rnees < 1.4


# ------------------------------------------------------------ the centralized reference's message


def _reading(star=True, gps=True, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal(4)
    return AbsoluteMeasurement(q_BI=q / np.linalg.norm(q) if star else None, r_H=rng.standard_normal(3) * 17.3 if gps else None,
                               sigma_att_rad=1.7e-5, sigma_pos_m=0.0031)


@pytest.mark.parametrize("parts", [(True, True), (True, False), (False, True)], ids=["star+gps", "star", "gps"])
@pytest.mark.parametrize("kind", [{"kind": "central"}, {"kind": "full", "central": True}], ids=["central", "full-central"])
def test_central_message_crosses_the_bus_bit_for_bit(kind, parts):
    """Its message is the sender's absolute reading, float64 in, float64 out: a peer applies
    the very numbers the sender's own filter applies (sized with the batch by the links)."""
    from swarmcore.estimators.full import CentralMessage

    sc = _sc(estimator=kind)
    codec = codec_for(sc)
    e = builtin_estimator(sc, 0)
    e.start(initial_estimate(sc, initial_truth(sc), 0, e.prior_ids()))
    reading = _reading(*parts)
    e.absolute_reading(0, reading)
    assert e.transmit(1) is None  # a reading of another step is not sent
    payload = e.transmit(0)
    assert isinstance(payload, CentralMessage) and payload.absolute is reading
    assert len(payload.encode()) == 1 + 8 * (2 + 4 * parts[0] + 3 * parts[1])
    msg = codec.to_msg(payload)
    assert msg.kind == kind["kind"] and msg.WhichOneof("body") == "opaque"
    wire = M.encode(M.MeasBatch(run="r", sender="agent-0", k=0, t_s=0.0, observer=0, estimator=msg, R_Bi=M.Matrix(shape=[0, 6, 6])))
    got = codec.from_msg(M.decode("meas", wire).estimator, 0, 0)
    assert got == payload and type(e).absolute_in(got) is not None
    a, b = got.absolute, reading
    for f in ("q_BI", "r_H"):
        x, y = getattr(a, f), getattr(b, f)
        assert (x is None) == (y is None) and (x is None or (x.dtype == np.float64 and x.tobytes() == np.asarray(y).tobytes())), f
    assert (a.sigma_att_rad, a.sigma_pos_m) == (b.sigma_att_rad, b.sigma_pos_m)
    size = batch_wire_size("x", codec.to_msg)
    none = (0, 0, 0.0, RelativeMeasurements.empty(), np.zeros(0, dtype=int))
    assert size(*none, payload) > size(*none, None)
    # No reading (not anchored, or neither sensor): nothing sent. Plain full sends nothing.
    e.absolute_reading(1, None)
    assert e.transmit(1) is None
    e.absolute_reading(2, AbsoluteMeasurement(None, None, 1e-5, 1e-3))
    assert e.transmit(2) is None
    f = builtin_estimator(_sc(), 0)
    f.absolute_reading(0, reading)
    assert f.transmit(0) is None and not f.hears_peer_absolute and type(f).absolute_in(payload) is not None


@pytest.mark.parametrize("data, why", [
    (b"", "empty"),
    (b"\x00" + bytes(16), "unknown flags"),
    (b"\x04" + bytes(16), "unknown flags"),
    (b"\x03" + bytes(16 + 32), "bytes where flags"),
    (b"\x02" + bytes(16 + 24) + b"\x00", "bytes where flags"),
    (b"\x02" + np.array([1e-5, np.nan, 0, 0, 0], dtype="<f8").tobytes(), "not finite"),
    (b"\x01" + np.array([1e-5, 1e-3, 0, 0, np.inf, 1], dtype="<f8").tobytes(), "not finite"),
    (b"\x01" + np.array([1e-5, 1e-3, 0, 0, 0, 2], dtype="<f8").tobytes(), "unit quaternion"),
    (b"\x02" + np.array([1e-5, 0.0, 1, 2, 3], dtype="<f8").tobytes(), "positive"),
    (b"\x02" + np.array([-1e-5, 1e-3, 1, 2, 3], dtype="<f8").tobytes(), "positive"),
])
def test_malformed_central_messages_are_refused(data, why):
    with pytest.raises(ValueError, match=why):
        BUILTIN["central"].decode(data)


def _central_steps(sc, late_at: int | None, deliver_at: int, steps: int = 6):
    """Satellite 1's centralized reference over ``steps`` steps of a 4-satellite swarm, every
    peer's batch and reading delivered on time but satellite 3's reading of step ``late_at``,
    which comes at ``deliver_at``. Returns its estimator and the reports."""
    from swarmcore.estimators import Received
    from swarmcore.estimators.full import CentralMessage

    wp = world_params(sc)
    truth = initial_truth(sc)
    e = builtin_estimator(sc, 1)
    e.start(initial_estimate(sc, truth, 1, e.prior_ids()))
    obs, tgt = np.nonzero(~np.eye(4, dtype=bool))
    held = None
    reports = []
    for k in range(steps):
        gyro = None
        if k > 0:
            truth, g = step_truth(wp, truth)
            gyro = g[1]
        absm = absolute_measurements(wp, truth)
        rel = synthetic_batch(wp, truth, obs, tgt)
        e.predict(k, gyro)
        got = []
        for j in (0, 2, 3):
            msg = CentralMessage(absm[j])
            if k == late_at and j == 3:
                held, msg = msg, None
            got.append(Received(j, k, rel.subset(rel.observer == j), msg))
        if k == deliver_at and held is not None:
            got.insert(0, Received(3, late_at, RelativeMeasurements.empty(), held))
        reports.append(e.step(StepInputs(k, truth.t, gyro, absm[1], rel.subset(rel.observer == 1), got)))
    return e, reports


def test_central_replays_a_late_peer_reading_at_its_own_step():
    """A peer's absolute reading that comes late is inserted at its step and the filter
    re-run from there (``filter.late: replay``): the posterior is the one of the reading on
    time; with ``drop`` (or older than the history) it is dropped and counted."""
    sc = _sc(estimator={"kind": "central"}, links={"enabled": True})
    on_time, _ = _central_steps(sc, None, 4)
    late, reps = _central_steps(sc, 2, 4)
    assert (reps[4].late_used, reps[4].late_dropped, reps[4].replayed_steps) == (1, 0, 2)  # steps 2 and 3 re-run
    never, _ = _central_steps(sc, 2, 99)
    a, b, c = on_time.view().full, late.view().full, never.view().full
    for f in ("q_BI", "r_H", "v_H", "P"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=1e-12, atol=1e-15, err_msg=f)
    assert not np.allclose(c.P, a.P, rtol=1e-12, atol=0)  # the test means something: the reading mattered
    dropped, reps = _central_steps(_sc(estimator={"kind": "central"}, links={"enabled": True}, filter={"late": "drop"}), 2, 4)
    assert (reps[4].late_used, reps[4].late_dropped, reps[4].replayed_steps) == (0, 1, 0)
    np.testing.assert_array_equal(dropped.view().full.P, c.P)
