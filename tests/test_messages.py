"""Every bus message round-trips exactly; malformed and hostile payloads are refused with a reason."""

import numpy as np
import pytest

from swarmcore import quat
from swarmcore.mekf import RelativeMeasurements, SwarmEstimate
from swarmcore.metrics import pose_cov_blocks
from swarmcore.scenario import Scenario
from swarmcore.world import initial_truth
from swarmrt.bus import messages as M
from swarmrt.bus.convert import (
    array,
    batch_msg,
    estimate_from_full,
    estimate_msg,
    full_estimate_msg,
    images_msg,
    matrix,
    observation_from_images,
    pairs_from_select,
    relative_from_batches,
    relative_from_step,
    select_msg,
    step_batches_msg,
    truth_msg,
)

RUN = "t-1"
H = dict(run=RUN, sender="test", k=3, t_s=3.0)
rng = np.random.default_rng(0)


def _est(n=3):
    A = rng.normal(size=(12 * n, 12 * n))
    P = A @ A.T + 12 * n * np.eye(12 * n)
    return SwarmEstimate(3, 3.0, quat.random_quaternion(rng, n), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=3), 0.5 * (P + P.T))


def _rel(m=2, observer=2):
    return RelativeMeasurements(
        np.full(m, observer), np.array([j for j in range(m + 1) if j != observer][:m]), quat.random_quaternion(rng, m), rng.normal(size=(m, 3)),
        np.stack([np.diag(rng.uniform(0.1, 1, 6)) for _ in range(m)]),
    )


def _img_views():
    return [
        M.CameraView(camera=2, T_CB=[0, 1.0, 0, 0, 0, 1, 1, 0, 0], r_C_B_m=[0, 0.2, 0], width_px=5, height_px=3, fx_px=4.0, fy_px=4.0, cx_px=2.0, cy_px=1.0, target=-1,
                     images_mono8=[rng.integers(0, 256, (3, 5), dtype=np.uint8).tobytes()]),
        M.CameraView(camera=8, T_CB=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], r_C_B_m=[0, 0, 0], width_px=4, height_px=2, fx_px=9.0, fy_px=9.0, cx_px=1.5, cy_px=0.5, target=2, baseline_m=0.5,
                     images_mono8=[rng.integers(0, 256, (2, 4), dtype=np.uint8).tobytes(), bytes(8)]),
    ]


EXAMPLES = {
    "clock": M.Clock(**H, live_agents=[0, 2], mode="lockstep", recorder_waited_steps=2, recorder_waited_s=0.75),
    "recorded": M.Recorded(**{**H, "sender": "recorder"}),
    "sensors": M.Sensors(**H, sat=1, gyro_rate_B_rad_s=[1e-3, 2e-3, -3e-3], q_BI_star=[0, 0, 0, 1.0], r_H_gps_m=[1.0, 2, 3], sigma_star_rad=2.9e-5, sigma_gps_m=0.01),
    "cam": M.CameraOutput(**H, sat=1, detections=[M.Detection(target=2, camera=4, q_BjBi=[0, 0, 0.6, 0.8], r_ij_Bi_m=[0.1, 0.2, 9.9])], cameras_off=[3]),
    "meas": batch_msg(_rel(), np.array([1, 5]), run=RUN, sender="agent-2", k=1, t_s=1.0, observer=2),
    "est": estimate_msg(_est(), run=RUN, sender="agent-1", own=1),
    "full_est": full_estimate_msg(_est(), run=RUN, sender="agent-1", own=1),
    "select": select_msg([0, 2], [1, 0], **H, strategy="greedy", ref_agent=0, select_ms=1.5),
    "fault": M.Fault(**H, action="camera", phase="command", target=1, camera=2, state="off"),
    "health": M.Health(**H, sat=1, camera_ok=[True] * 5 + [False], malformed=2),
    "claim": M.Claim(**H, sat=2, token="abc123", running=True),
    "img": M.Images(**H, sat=1, targets=[0, 2], views=_img_views()),
    "truth": truth_msg(initial_truth(Scenario(n_sats=3, seed=2)), run=RUN, k=0),
    "rx": M.Delivery(**H, sat=2, items=[M.Delivered(arrival_t_s=6.5, batch=batch_msg(
        RelativeMeasurements(np.array([1]), np.array([2]), np.array([[0, 0, 0, 1.0]]), np.array([[1.0, 2, 3]]), np.eye(6)[None]),
        np.array([6]), run=RUN, sender="agent-1", k=5, t_s=5.0, observer=1))]),
    "links": M.LinkStats(**H, **{f: matrix(np.arange(9.0).reshape(3, 3)) for f in (
        "sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")},
        queue_bytes=[0, 120, 5], latencies=[M.Latency(sender=0, receiver=1, sent_k=6, latency_s=0.25)]),
    "rejoin": M.RejoinFate(**H, sat=2, peer=0, bytes=25959, fate="delivered", arrival_t_s=16.8),
}
_METER = M.replace(EXAMPLES["meas"], schema_version=M.SCHEMA_VERSION)  # a batch as the radio received it
EXAMPLES["rx"] = M.Delivery(**H, sat=0, items=[M.Delivered(arrival_t_s=2.7, batch=_METER)])
EXAMPLES["links"] = M.LinkStats(**H, **{f: matrix(np.arange(9.0).reshape(3, 3)) for f in M._LINK_COUNTERS}, queue_bytes=[0, 120, 4],
                                latencies=[M.Latency(sender=2, receiver=0, sent_k=2, latency_s=0.7)])
EXAMPLES["rejoin"] = M.RejoinFate(**H, sat=1, peer=2, bytes=12345, fate="delivered", arrival_t_s=3.4)
_B0 = batch_msg(_rel(2, observer=0), np.array([0, 3]), run=RUN, sender="agent-0", k=3, t_s=3.0, observer=0)
_B1 = batch_msg(RelativeMeasurements.empty(), np.zeros(0, int), run=RUN, sender="agent-1", k=3, t_s=3.0, observer=1)
EXAMPLES["batches"] = M.replace(step_batches_msg([_METER, _B1, _B0], run=RUN, k=3, t_s=3.0), schema_version=M.SCHEMA_VERSION)


def _raw(kind, **changes):
    return M.encode(M.replace(EXAMPLES[kind], **changes))


def test_every_kind_has_an_example():
    assert set(EXAMPLES) == set(M.MODELS)


@pytest.mark.parametrize("kind", sorted(M.MODELS))
def test_round_trip_exact_with_version(kind):
    msg = EXAMPLES[kind]
    raw = M.encode(msg)
    back = M.decode(kind, raw)
    assert back == msg
    assert M.Header.FromString(raw).schema_version == M.SCHEMA_VERSION == 1  # any payload reads as a Header
    assert M.Header.FromString(raw).run == RUN
    assert M.encode(back) == raw


def test_estimate_arrays_are_bit_exact():
    est = _est(4)
    back = estimate_from_full(M.decode("full_est", M.encode(full_estimate_msg(est, run=RUN, sender="a", own=2))), 4)
    for f in ("q_BI", "omega_BI_B", "r_H", "v_H", "bias_B", "P"):
        np.testing.assert_array_equal(getattr(back, f), getattr(est, f))
    with pytest.raises(ValueError, match="this swarm of 5"):
        estimate_from_full(M.decode("full_est", M.encode(full_estimate_msg(est, run=RUN, sender="a", own=2))), 5)
    m = M.decode("est", M.encode(estimate_msg(est, run=RUN, sender="a", own=2)))
    np.testing.assert_array_equal(array(m.P_pose), pose_cov_blocks(est.P, 4))
    np.testing.assert_array_equal(array(m.P_diag), np.diag(est.P))


def test_measurement_batches_round_trip():
    rel = _rel()
    msg = M.decode("meas", M.encode(batch_msg(rel, np.array([1, 5]), run=RUN, sender="a", k=1, t_s=1.0, observer=2)))
    back = relative_from_batches([msg])
    for f in ("observer", "target", "q_BjBi", "r_ij_Bi", "R_Bi"):
        np.testing.assert_array_equal(getattr(back, f), getattr(rel, f))
    assert list(msg.camera) == [1, 5] and list(msg.R_Bi.shape) == [2, 6, 6]
    empty = M.decode("meas", M.encode(batch_msg(RelativeMeasurements.empty(), np.zeros(0, int), run=RUN, sender="a", k=1, t_s=1.0, observer=2)))
    assert len(relative_from_batches([empty])) == 0
    with pytest.raises(ValueError, match="batch of observer 1"):
        batch_msg(rel, np.array([1, 5]), run=RUN, sender="a", k=1, t_s=1.0, observer=1)


def test_step_batches_carry_every_batch_bit_for_bit_in_observer_order():
    msg = M.decode("batches", M.encode(EXAMPLES["batches"]))
    assert list(msg.observers) == [0, 1, 2] and list(msg.counts) == [2, 0, 2]
    want = relative_from_batches([_B0, _B1, _METER])
    for skip, keep in ((None, [0, 0, 2, 2]), (0, [2, 2]), (1, [0, 0, 2, 2]), (2, [0, 0])):
        got = relative_from_step(M.decode("batches", M.encode(EXAMPLES["batches"])), skip=skip)
        rows = [r for r in range(4) if want.observer[r] != skip]
        assert got.observer.tolist() == keep
        for f in ("observer", "target", "q_BjBi", "r_ij_Bi", "R_Bi"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f)[rows])
    assert list(msg.camera) == [0, 3, 1, 5]
    empty = M.decode("batches", M.encode(step_batches_msg([], run=RUN, k=0, t_s=0.0)))
    assert len(relative_from_step(empty)) == 0 and not empty.observers


def test_select_pairs_round_trip():
    obs, tgt = pairs_from_select(M.decode("select", M.encode(EXAMPLES["select"])))
    assert obs.tolist() == [0, 2] and tgt.tolist() == [1, 0]


def _nan_R():
    m = M.replace(EXAMPLES["meas"])
    m.R_Bi.data[7] = float("nan")
    return M.encode(m)


def _asym_R():
    m = M.replace(EXAMPLES["meas"])
    m.R_Bi.data[1] = 0.3  # (0, 1) without (1, 0)
    return M.encode(m)


def _indefinite_R():
    m = M.replace(EXAMPLES["meas"])
    m.R_Bi.data[0] = -1.0
    return M.encode(m)


@pytest.mark.parametrize(
    "kind,payload,reason",
    [
        ("clock", b"\x00\xff garbage", "invalid clock"),
        ("clock", b"", "schema_version: missing"),
        ("clock", M.encode(M.Clock(schema_version=2, run=RUN, sender="world", mode="free")), "unknown version 2"),
        ("clock", _raw("clock", mode="sometimes"), "mode"),
        ("clock", _raw("clock", t_s=float("nan")), "t_s"),
        ("clock", _raw("clock", run="a/b"), "run"),
        ("sensors", _raw("sensors", gyro_rate_B_rad_s=[1.0, 2.0]), "gyro_rate_B_rad_s: 2 numbers"),
        ("sensors", _raw("sensors", q_BI_star=[0, 0, 0.5, 0.5]), "not a unit quaternion"),
        ("sensors", _raw("sensors", r_H_gps_m=[0, float("inf"), 0]), "r_H_gps_m: not finite"),
        ("sensors", _raw("sensors", sigma_gps_m=0.0), "sigma_gps_m"),
        ("meas", _raw("meas", camera=[1]), "camera: 1 values for 2 measurements"),
        ("meas", _raw("meas", target=[2, 0]), "cannot measure itself"),
        ("meas", _raw("meas", target=[0, 10_001]), "out of range"),
        ("meas", _raw("meas", q_BjBi=[0.0] * 8), "unit quaternion"),
        ("meas", _raw("meas", r_ij_Bi_m=[1.0] * 5), "r_ij_Bi_m: 5 numbers, expected 2 × 3"),
        ("meas", _nan_R(), "R_Bi: not finite"),
        ("meas", _asym_R(), "R_Bi: not symmetric"),
        ("meas", _indefinite_R(), "R_Bi: not positive-definite"),
        ("meas", _raw("meas", R_Bi=M.Matrix(shape=[2, 6, 6], data=[1.0] * 71)), "needs 72 numbers, got 71"),
        # A hostile shape: announced, never allocated.
        ("meas", _raw("meas", R_Bi=M.Matrix(shape=[1 << 30, 1 << 30, 6], data=[1.0])), "shape"),
        ("est", _raw("est", phase="maybe"), "phase"),
        ("est", _raw("est", own=5), "own: satellite 5 in an estimate of 3"),
        ("est", _raw("est", P_diag=matrix(-np.ones(36))), "P_diag"),
        ("est", _raw("est", v_H_m_s=[0.0] * 8), "v_H_m_s"),
        # Each array of an estimate, bad in its last number (the compiled check sees every row).
        ("est", _raw("est", bias_B_rad_s=[0.0, 0.0, float("nan")]), "bias_B_rad_s: not finite"),
        ("est", _raw("est", v_H_m_s=[0.0] * 8 + [float("inf")]), "v_H_m_s: not finite"),
        ("est", _raw("est", q_BI=[0.0, 0.0, 0.0, 1.0] * 2 + [0.0, 0.0, 0.6, 0.6]), "q_BI: not a unit quaternion"),
        ("est", _raw("est", P_pose=matrix(np.tile(np.eye(6), (3, 1, 1)) + np.triu(np.ones((6, 6)), 1) * (np.arange(3) == 2)[:, None, None])), "P_pose: not symmetric"),
        ("est", _raw("est", P_pose=matrix(np.tile(np.eye(6), (3, 1, 1)) * np.r_[1.0, 1.0, -1.0][:, None, None])), "P_pose: not positive-definite"),
        ("est", _raw("est", P_diag=matrix(np.r_[np.ones(35), np.nan])), "P_diag: not finite"),
        ("est", _raw("est", nis=-1.0), "nis"),
        ("est", _raw("est", own=3), "own: satellite 3 in an estimate of 3"),
        ("sensors", _raw("sensors", sigma_star_rad=float("nan")), "sigma_star_rad"),
        ("full_est", _raw("full_est", P=matrix(-np.eye(36))), "positive-definite"),
        ("select", _raw("select", target=[1]), "2 observers for 1 targets"),
        ("fault", _raw("fault", action="explode"), "action"),
        ("fault", _raw("fault", camera=None), "camera fault needs camera and state"),
        ("fault", M.encode(M.Fault(**H, action="drop", phase="command", target=1, rate=1.5)), "rate"),
        ("fault", M.encode(M.Fault(**H, action="kill-agent", phase="command")), "needs a target"),
        ("health", _raw("health", camera_ok=[True] * 5), "camera_ok: 5 values"),
        ("fault", M.encode(M.Fault(**H, action="netem", phase="command", target=1)), "action netem needs netem"),
        ("fault", M.encode(M.Fault(**H, action="stall-world", phase="command")), "stall-world needs down_s > 0"),
        ("fault", M.encode(M.Fault(**H, action="stall-agent", phase="command", down_s=2.0)), "needs a target"),
        ("fault", M.encode(M.Fault(**H, action="link", phase="command", target=1)), "link fault needs state, delay_s or rate"),
        ("fault", M.encode(M.Fault(**H, action="link", phase="command", target=1, peer=1, state="off")), "no link to itself"),
        ("fault", M.encode(M.Fault(**H, action="link", phase="command", target=1, peer=10_001, state="off")), "peer: satellite id 10001 out of range"),
        ("fault", M.encode(M.Fault(**H, action="link", phase="command", target=1, delay_s=-1.0)), "delay_s"),
        ("rejoin", _raw("rejoin", fate="teleported"), "fate"),
        ("rejoin", _raw("rejoin", arrival_t_s=None), "needs its arrival time"),
        ("links", _raw("links", lost=matrix(-np.ones((3, 3)))), "lost: a negative count"),
        ("links", _raw("links", sent=matrix(np.ones((2, 3)))), "sent: shape"),
        ("rx", M.encode(M.Delivery(**H, sat=0, items=[M.Delivered(arrival_t_s=1.0, batch=M.replace(_METER, q_BjBi=[0.0] * 8))])), "items.0.batch: .*unit quaternion"),
        ("rx", M.encode(M.Delivery(**H, sat=2, items=[M.Delivered(arrival_t_s=1.0, batch=_METER)])), "own batch"),
        ("batches", _raw("batches", counts=[2, 0]), "counts: 2 values for 3 observers"),
        ("batches", _raw("batches", observers=[0, 2, 1]), "not ascending"),
        ("batches", _raw("batches", observers=[0, 1, 1]), "not ascending"),
        ("batches", _raw("batches", counts=[2, 1, 2]), "for 5 rows"),
        ("batches", _raw("batches", target=[1, 0, 0, 1]), "satellite 0 cannot measure itself"),
        ("batches", _raw("batches", target=[1, 3, 0, 10_001]), "out of range"),
        ("batches", _raw("batches", q_BjBi=[0.0] * 16), "unit quaternion"),
        ("batches", _raw("batches", r_ij_Bi_m=[1.0] * 11), "r_ij_Bi_m: 11 numbers, expected 4 × 3"),
        ("batches", _raw("batches", R_Bi=M.Matrix(shape=[4, 6, 6], data=[float("nan")] * 144)), "R_Bi: not finite"),
        ("batches", _raw("batches", R_Bi=M.Matrix(shape=[1 << 30, 1 << 30, 6], data=[1.0])), "shape"),
        ("img", _raw("img", views=[M.replace(EXAMPLES["img"].views[0], width_px=0)]), "width_px"),
        ("img", _raw("img", views=[M.replace(EXAMPLES["img"].views[0], images_mono8=[bytes(14)])]), "needs 15 bytes, got 14"),
        ("img", _raw("img", views=[M.replace(EXAMPLES["img"].views[0], T_CB=[2.0] + [0.0] * 8)]), "rotation"),
        # A message of another type on this key: decoded, then refused for what it lacks.
        ("est", M.encode(EXAMPLES["clock"]), "invalid est message: phase"),
        ("truth", M.encode(EXAMPLES["health"]), "invalid truth message"),
        ("fault", M.encode(EXAMPLES["health"]), "action"),
        # Truncated.
        ("est", M.encode(EXAMPLES["est"])[:-9], "invalid est"),
        ("meas", M.encode(EXAMPLES["meas"])[:40], "invalid meas"),
    ],
)
def test_malformed_payloads_are_refused_with_the_reason(kind, payload, reason):
    with pytest.raises(M.MessageError, match=reason):
        M.decode(kind, payload)


def test_oversized_payloads_are_refused_before_parsing():
    # ~9 MB of packed doubles: more than any batch may have; refused on its length alone.
    big = M.encode(M.MeasBatch(run=RUN, sender="agent-0", observer=0, q_BjBi=np.zeros(1_200_000).tolist()))
    assert len(big) > M.MAX_PAYLOAD_DEFAULT
    with pytest.raises(M.MessageError, match="more than the"):
        M.decode("meas", big)


def test_keys_and_senders():
    k = M.Keys(RUN)
    est = EXAMPLES["est"]  # agent-1's, own = 1
    M.check_key(k.est(1), "est", 1, est)
    with pytest.raises(M.MessageError, match="key says satellite 2"):
        M.check_key(k.est(2), "est", 2, est)
    with pytest.raises(M.MessageError, match="may not publish"):
        M.check_key(k.est(1), "est", 1, M.replace(est, sender="agent-2"))
    with pytest.raises(M.MessageError, match="may not publish"):
        M.check_key(k.clock(), "clock", None, M.replace(EXAMPLES["clock"], sender="agent-0"))
    prior = M.replace(EXAMPLES["full_est"], sender="world")
    M.check_key(k.init(1), "full_est", 1, prior)
    with pytest.raises(M.MessageError, match="may not publish"):
        M.check_key(k.cov(1), "full_est", 1, prior)
    cmd = M.replace(EXAMPLES["fault"], phase="command", sender="cli")
    M.check_key(k.fault(), "fault", None, cmd)
    M.check_key(k.fault(), "fault", None, M.replace(cmd, sender="world"))  # the scenario's schedule
    done = M.replace(cmd, phase="done", sender="agent-7")
    M.check_key(k.fault_report("agent-7"), "fault", None, done)
    # An agent may not command, nor report as another; a report is not a command.
    for key, msg in ((k.fault(), M.replace(cmd, sender="agent-7")), (k.fault(), M.replace(cmd, sender="evil")),
                     (k.fault_report("agent-7"), M.replace(done, sender="agent-2")),
                     (k.fault_report("agent-7"), cmd), (k.fault(), done), (k.fault_report("evil"), M.replace(done, sender="evil"))):
        with pytest.raises(M.KeyMismatch):
            M.check_key(key, "fault", None, msg)
    assert M.parse_key(k.fault_report("supervisor")) == (RUN, "fault", None)


def test_images_carry_pixels_exactly():
    msg = M.decode("img", M.encode(EXAMPLES["img"]))
    pix = M.pixels(msg)
    assert [p.shape for p in pix] == [(3, 5), (2, 4), (2, 4)]
    assert all(p.flags["WRITEABLE"] and p.flags["C_CONTIGUOUS"] for p in pix)
    assert [p.tobytes() for p in pix] == [im for v in EXAMPLES["img"].views for im in v.images_mono8]


def test_views_round_trip_through_an_images_message():
    from swarmcore.cameras import T_CB, Intrinsics
    from swarmvision.views import View

    intr = Intrinsics(6, 4, 5.0, 5.0, 2.5, 1.5)
    views = [
        View(1, 3, 7, 7.0, (rng.integers(0, 256, (4, 6), dtype=np.uint8),), T_CB[3].copy(), np.array([-0.2, 0, 0]), intr),
        View(1, 8, 7, 7.0, (np.ones((4, 6), np.uint8), np.zeros((4, 6), np.uint8)), np.eye(3), np.zeros(3), intr, target=2, baseline_m=0.5),
    ]
    msg = M.decode("img", M.encode(images_msg(views, run=RUN, k=7, t_s=7.0, sat=1, targets=np.array([2, 0]))))
    assert list(msg.targets) == [0, 2]
    obs = observation_from_images(msg)
    assert obs.targets.tolist() == [0, 2]
    back = obs.views
    assert len(back) == len(views)
    for a, b in zip(views, back, strict=True):
        assert (a.observer, a.camera, a.step, a.t, a.target, a.baseline_m, a.intrinsics) == (b.observer, b.camera, b.step, b.t, b.target, b.baseline_m, b.intrinsics)
        np.testing.assert_array_equal(a.T_CB, b.T_CB)
        np.testing.assert_array_equal(a.r_C_B, b.r_C_B)
        assert len(a.images) == len(b.images) and all(np.array_equal(x, y) for x, y in zip(a.images, b.images, strict=True))
    with pytest.raises(ValueError, match="images of shapes"):
        images_msg([View(1, 3, 7, 7.0, (np.zeros((3, 6), np.uint8),), T_CB[3].copy(), np.zeros(3), intr)], run=RUN, k=7, t_s=7.0, sat=1, targets=[])


def test_replace_as_dict_and_optional_fields():
    f = M.Fault(**H, action="kill-selector", phase="command")
    assert M.opt(f, "target") is None and f.target == 0
    d = M.as_dict(M.replace(f, phase="done", detail="x"), exclude=("schema_version", "run"))
    assert d == {"sender": "test", "k": 3, "t_s": 3.0, "action": "kill-selector", "phase": "done", "target": None, "camera": None, "state": None, "rate": None, "detail": "x", "netem": None, "down_s": None, "peer": None, "delay_s": None}
    assert f.phase == "command", "replace must not touch the original"
    g = M.replace(EXAMPLES["fault"], target=None)
    assert not g.HasField("target") and EXAMPLES["fault"].target == 1
    assert M.replace(EXAMPLES["clock"], live_agents=[5]).live_agents == [5]
    with pytest.raises(AttributeError, match="no field"):
        M.replace(f, bogus=1)


def test_codec_time_is_counted_once_for_nested_calls():
    M.codec_cpu_ms()  # reset
    for _ in range(200):
        M.decode("est", M.encode(estimate_msg(_est(6), run=RUN, sender="agent-1", own=1)))
    ms = M.codec_cpu_ms()
    assert ms > 0 and M.codec_cpu_ms(reset=False) == 0.0


def test_keys_and_parsing():
    k = M.Keys("r1")
    assert M.parse_key(k.meas(3)) == ("r1", "meas", 3)
    assert M.parse_key(k.sensors(2)) == ("r1", "sensors", 2)
    assert M.parse_key(k.cam(0)) == ("r1", "cam", 0)
    assert M.parse_key(k.img(5)) == ("r1", "img", 5)
    assert M.parse_key(k.clock()) == ("r1", "clock", None)
    assert M.parse_key(k.cov(4)) == ("r1", "full_est", 4)
    assert M.parse_key(k.claim("tok")) == ("r1", "claim", None)
    assert M.parse_key(k.alive("agent", 7)) == ("r1", "alive", 7)
    for bad in ("swarm/r1/meas/x", "swarm/r1/nope", "other/r1/clock", "swarm/r1/sat/1/gyro"):
        with pytest.raises(M.MessageError):
            M.parse_key(bad)
    with pytest.raises(ValueError, match="run id"):
        M.Keys("bad/run")
    with pytest.raises(ValueError, match="run id"):
        M.Keys("run\n")


def test_shallow_decoding_of_estimates_checks_what_it_reads():
    """Roles that read only who / which step / which phase of a peer's estimate decode it
    shallowly: the arrays are neither converted nor checked, the rest is."""
    bad = M.replace(EXAMPLES["est"])
    bad.P_pose.data[0] = float("nan")
    raw = M.encode(bad)
    assert M.decode("est", raw, shallow=True).own == 1
    with pytest.raises(M.MessageError, match="P_pose: not finite"):
        M.decode("est", raw)
    for change, reason in ((dict(phase="x"), "phase"), (dict(own=3), "own"), (dict(q_BI=[1.0] * 5), "q_BI"), (dict(schema_version=7), "version")):
        with pytest.raises(M.MessageError, match=reason):
            M.decode("est", _raw("est", **change), shallow=True)
    assert M.SHALLOW_KINDS == ("est", "batches")
    assert M.decode("meas", M.encode(EXAMPLES["meas"]), shallow=True) == EXAMPLES["meas"]  # other kinds: always in full
    with pytest.raises(M.MessageError, match="R_Bi: not finite"):
        M.decode("meas", _nan_R(), shallow=True)



def _with(a: np.ndarray, index, value) -> np.ndarray:
    """A copy of ``a`` with ``a[index] = value``."""
    b = a.copy()
    b[index] = value
    return b

def test_compiled_batch_checks_give_the_numpy_verdicts():
    from swarmrt.bus import fastcheck as F

    base = EXAMPLES["meas"]
    q0 = np.asarray(base.q_BjBi).reshape(-1, 4)
    r0 = np.asarray(base.r_ij_Bi_m).reshape(-1, 3)
    R0 = array(base.R_Bi)
    cases = {"sound": (q0, r0, R0), "empty": (np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 6, 6)))}
    cases["q NaN"] = (_with(q0, (1, 2), np.nan), r0, R0)
    cases["q not unit"] = (_with(q0, 0, q0[0] * 1.001), r0, R0)
    cases["q within tolerance"] = (_with(q0, 0, q0[0] * (1 + 5e-7)), r0, R0)
    cases["r inf"] = (q0, _with(r0, (1, 0), np.inf), R0)
    cases["R NaN upper"] = (q0, r0, _with(R0, (1, 0, 5), np.nan))
    cases["R asymmetric"] = (q0, r0, _with(R0, (0, 4, 1), R0[0, 4, 1] + 1e-3))
    cases["R round-off"] = (q0, r0, _with(R0, (0, 4, 1), R0[0, 4, 1] + 1e-12 * R0[0].max()))
    cases["R indefinite"] = (q0, r0, _with(R0, (1, 3, 3), -R0[1, 3, 3]))
    cases["R singular"] = (q0, r0, _with(R0, 1, np.ones((6, 6))))
    want = {"sound": 0, "empty": 0, "q NaN": 1, "q not unit": 2, "q within tolerance": 0, "r inf": 3, "R NaN upper": 4,
            "R asymmetric": 5, "R round-off": 0, "R indefinite": 6, "R singular": 6}
    for name, (q, r, R) in cases.items():
        got = (F.check_batch(q, r, R, 2 * M.QUAT_TOL, M.SYM_TOL), F.check_batch_numpy(q, r, R, 2 * M.QUAT_TOL, M.SYM_TOL))
        assert got == (want[name], want[name]), name
    assert F.HAVE_NUMBA  # the compiled form is the one the agents use


def test_satellite_ids_are_checked_against_the_swarm_size():
    raw = M.encode(EXAMPLES["meas"])  # observer 2, targets 0 and 1
    assert M.decode("meas", raw, n_sats=3) == EXAMPLES["meas"]
    with pytest.raises(M.MessageError, match=r"observer: satellite id 2 out of range \(0-1\)"):
        M.decode("meas", raw, n_sats=2)
    with pytest.raises(M.MessageError, match="live_agents: satellite id 2 out of range"):
        M.decode("clock", M.encode(EXAMPLES["clock"]), n_sats=2)
    with pytest.raises(M.MessageError, match="own: satellite id 1 out of range"):
        M.decode("est", M.encode(EXAMPLES["est"]), shallow=True, n_sats=1)


def test_an_agent_reads_the_ideal_radios_message_shallowly_and_checks_each_estimator_message_it_reads():
    """The ideal radio's StepBatches as an agent decodes it: everything but the peers'
    estimator messages in full, and each of those checked when the estimator reads it
    (check_estimator_message, naming the sender); a full decode (the recorder's) refuses
    the whole message for one bad peer, naming it."""
    good = M.CiState(q_BI=[0, 0, 0, 1.0], omega_BI_B_rad_s=[0, 0, 0.0], r_H_m=[1, 2, 3.0], v_H_m_s=[0, 0, 0.0],
                     P_pose=M.Matrix(shape=[6, 6], data=np.eye(6).ravel().tolist()))
    bad = M.CiState()
    bad.CopyFrom(good)
    bad.P_pose.data[0] = float("nan")
    ests = {0: good, 1: bad, 2: good}
    batches = [M.replace(b, estimator=M.EstimatorMessage(kind="ci", version=1, ci=ests[b.observer])) for b in (_METER, _B1, _B0)]
    raw = M.encode(M.replace(step_batches_msg(batches, run=RUN, k=3, t_s=3.0), schema_version=M.SCHEMA_VERSION))
    with pytest.raises(M.MessageError, match=r"estimators\[1\].*P_pose: not finite"):
        M.decode("batches", raw, n_sats=3)
    msg = M.decode("batches", raw, shallow=True, n_sats=3)
    M.check_estimator_message(msg.estimators[0], 0, 3)
    M.check_estimator_message(msg.estimators[2], 2, 3)
    with pytest.raises(M.MessageError, match=r"estimators\[1\].*P_pose: not finite"):
        M.check_estimator_message(msg.estimators[1], 1, 3)
    # The rest is checked in full in the shallow reading too.
    with pytest.raises(M.MessageError, match="counts"):
        M.decode("batches", _raw("batches", counts=[2, 0]), shallow=True, n_sats=3)
    with pytest.raises(M.MessageError, match="R_Bi: not finite"):
        b = M.replace(_B0)
        b.R_Bi.data[0] = float("nan")
        M.decode("batches", M.encode(M.replace(step_batches_msg([b], run=RUN, k=3, t_s=3.0), schema_version=M.SCHEMA_VERSION)),
                 shallow=True, n_sats=3)
