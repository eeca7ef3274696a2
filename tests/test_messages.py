"""Every bus message round-trips exactly; malformed payloads are refused with a reason."""

import json

import numpy as np
import pytest

from swarm.bus import messages as M
from swarm.bus.convert import (
    batch_msg,
    estimate_from_full,
    estimate_msg,
    full_estimate_msg,
    images_msg,
    relative_from_batches,
    observation_from_images,
)
from swarmcore import quat
from swarmcore.mekf import RelativeMeasurements, SwarmEstimate

RUN = "t-1"
H = dict(run=RUN, sender="test", k=3, t_s=3.0)
rng = np.random.default_rng(0)


def _est(n=3):
    A = rng.normal(size=(12 * n, 12 * n))
    return SwarmEstimate(
        3, 3.0, quat.random_quaternion(rng, n), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
        rng.normal(size=(n, 3)), rng.normal(size=3), A @ A.T,
    )


EXAMPLES = {
    "clock": M.Clock(**H, live_agents=[0, 2]),
    "sensors": M.Sensors(**H, sat=1, gyro_rate_B_rad_s=[1e-3, 2e-3, -3e-3], q_BI_star=[0, 0, 0, 1.0], r_H_gps_m=[1.0, 2, 3], sigma_star_rad=2.9e-5, sigma_gps_m=0.01),
    "cam": M.CameraOutput(**H, sat=1, detections=[M.Detection(target=2, camera=4, q_BjBi=[0, 0, 0.6, 0.8], r_ij_Bi_m=[0.1, 0.2, 9.9])], cameras_off=[3]),
    "meas": M.MeasBatch(**H, observer=1, meas=[M.RelMeas(observer=1, target=0, camera=0, q_BjBi=[0, 0, 0, 1.0], r_ij_Bi_m=[1.0, 0, 0], R_Bi=list(np.eye(6).ravel()))]),
    "est": estimate_msg(_est(), run=RUN, sender="agent-1", own=1),
    "full_est": full_estimate_msg(_est(), run=RUN, sender="agent-1", own=1),
    "select": M.Select(**H, pairs=[(0, 1), (2, 0)], strategy="greedy", ref_agent=0, select_ms=1.5),
    "fault": M.Fault(**H, action="camera", target=1, camera=2, state="off"),
    "health": M.Health(**H, sat=1, camera_ok=[True] * 5 + [False], malformed=2),
    "claim": M.Claim(**H, sat=2, token="abc123", running=True),
    "img": M.Images(**H, sat=1, targets=[0, 2], views=[
        M.ViewMeta(camera=2, T_CB=[0, 1.0, 0, 0, 0, 1, 1, 0, 0], r_C_B_m=[0, 0.2, 0], width_px=5, height_px=3, fx_px=4.0, fy_px=4.0, cx_px=2.0, cy_px=1.0),
        M.ViewMeta(camera=8, T_CB=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], r_C_B_m=[0, 0, 0], width_px=4, height_px=2, fx_px=9.0, fy_px=9.0, cx_px=1.5, cy_px=0.5, target=2, baseline_m=0.5, n_images=2),
    ]).with_pixels([rng.integers(0, 256, (3, 5), dtype=np.uint8), rng.integers(0, 256, (2, 4), dtype=np.uint8), np.zeros((2, 4), np.uint8)]),
    "truth": M.Truth(**H, q_BI=[[0, 0, 0, 1.0]], omega_BI_B_rad_s=[[0, 0, 0.1]], r_H_m=[[1, 2, 3.0]], v_H_m_s=[[0, 0, 0.0]], gyro_bias_B_rad_s=[[0, 0, 0.0]]),
    "rx": M.Delivery(**H, sat=2, items=[M.Delivered(arrival_t_s=6.5, batch=M.MeasBatch(**{**H, "k": 5}, observer=1, meas=[
        M.RelMeas(observer=1, target=2, camera=6, q_BjBi=[0, 0, 0, 1.0], r_ij_Bi_m=[1.0, 2, 3], R_Bi=list(np.eye(6).ravel()))]))]),
    "links": M.LinkStats(**H, **{f: M.B64Array.of(np.arange(9.0).reshape(3, 3)) for f in (
        "sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")},
        queue_bytes=[0, 120, 5], latencies=[(0, 1, 6, 0.25)]),
    "rejoin": M.RejoinFate(**H, sat=2, peer=0, bytes=25959, fate="delivered", arrival_t_s=16.8),
}


def test_every_kind_has_an_example():
    assert set(EXAMPLES) == set(M.MODELS)


@pytest.mark.parametrize("kind", sorted(M.MODELS))
def test_round_trip_exact_with_version(kind):
    msg = EXAMPLES[kind]
    raw = M.encode(msg)
    back = M.decode(kind, raw)
    assert back == msg
    header = raw.partition(b"\n")[0] if kind == "img" else raw
    assert json.loads(header)["v"] == M.SCHEMA_VERSION == 1
    assert M.encode(back) == raw


def test_estimate_arrays_are_bit_exact():
    est = _est(4)
    back = estimate_from_full(M.decode("full_est", M.encode(full_estimate_msg(est, run=RUN, sender="a", own=2))), 4)
    for f in ("q_BI", "omega_BI_B", "r_H", "v_H", "bias_B", "P"):
        np.testing.assert_array_equal(getattr(back, f), getattr(est, f))
    with pytest.raises(ValueError, match="this swarm has 5"):
        estimate_from_full(M.decode("full_est", M.encode(full_estimate_msg(est, run=RUN, sender="a", own=2))), 5)


def test_measurement_batches_round_trip():
    rel = RelativeMeasurements(
        np.array([2, 2]), np.array([0, 1]), quat.random_quaternion(rng, 2), rng.normal(size=(2, 3)),
        np.stack([np.diag(rng.uniform(0.1, 1, 6)) for _ in range(2)]),
    )
    msg = M.decode("meas", M.encode(batch_msg(rel, np.array([1, 5]), run=RUN, sender="a", k=1, t_s=1.0, observer=2)))
    back = relative_from_batches([msg])
    for f in ("observer", "target", "q_BjBi", "r_ij_Bi", "R_Bi"):
        np.testing.assert_array_equal(getattr(back, f), getattr(rel, f))


@pytest.mark.parametrize(
    "kind,payload,reason",
    [
        ("clock", b"\x00\xff garbage", "invalid clock"),
        ("clock", b'{"v": 2, "run": "t-1", "sender": "w", "k": 0, "t_s": 0, "live_agents": []}', "v"),
        ("clock", b'{"v": 1, "run": "t-1", "sender": "w", "k": -1, "t_s": 0, "live_agents": []}', "k"),
        ("sensors", b'{"v": 1, "run": "t-1", "sender": "w", "k": 0, "t_s": 0, "sat": 0, "gyro_rate_B_rad_s": [1, 2], "sigma_star_rad": 1, "sigma_gps_m": 1}', "gyro_rate_B_rad_s"),
        ("meas", b'{"v": 1, "run": "t-1", "sender": "a", "k": 0, "t_s": 0, "observer": 1, "meas": [{"observer": 2, "target": 0, "camera": 0, "q_BjBi": [0,0,0,1], "r_ij_Bi_m": [1,0,0], "R_Bi": [' + b",".join([b"1"] * 36) + b"]}]}", "batch of observer 1"),
        ("select", b'{"v": 1, "run": "t-1", "sender": "s", "k": 0, "t_s": 0, "pairs": [[0, 1]], "strategy": "x", "bogus": 1}', "bogus"),
        ("fault", b'{"v": 1, "run": "t-1", "sender": "c", "k": 0, "t_s": 0, "action": "explode"}', "action"),
    ],
)
def test_malformed_payloads_are_refused_with_the_reason(kind, payload, reason):
    with pytest.raises(M.MessageError, match=reason):
        M.decode(kind, payload)


def test_images_carry_pixels_exactly_and_refuse_a_short_payload():
    msg = EXAMPLES["img"]
    raw = M.encode(msg)
    back = M.decode("img", raw)
    assert [p.tolist() for p in back.pixels] == [p.tolist() for p in msg.pixels]
    assert all(p.flags["WRITEABLE"] and p.flags["C_CONTIGUOUS"] for p in back.pixels)
    with pytest.raises(M.MessageError, match="need 31 pixel bytes, got 30"):
        M.decode("img", raw[:-1])
    with pytest.raises(M.MessageError, match="no newline"):
        M.decode("img", raw.partition(b"\n")[0])
    with pytest.raises(M.MessageError, match="width_px"):
        M.decode("img", raw.replace(b'"width_px":5', b'"width_px":0'))
    with pytest.raises(M.MessageError, match="do not match"):
        msg.model_copy().with_pixels([np.zeros((3, 5), np.uint8)])


def test_views_round_trip_through_an_images_message():
    from swarmcore.cameras import T_CB, Intrinsics
    from swarmvision.views import View

    intr = Intrinsics(6, 4, 5.0, 5.0, 2.5, 1.5)
    views = [
        View(1, 3, 7, 7.0, (rng.integers(0, 256, (4, 6), dtype=np.uint8),), T_CB[3].copy(), np.array([-0.2, 0, 0]), intr),
        View(1, 8, 7, 7.0, (np.ones((4, 6), np.uint8), np.zeros((4, 6), np.uint8)), np.eye(3), np.zeros(3), intr, target=2, baseline_m=0.5),
    ]
    msg = M.decode("img", M.encode(images_msg(views, run=RUN, k=7, t_s=7.0, sat=1, targets=np.array([2, 0]))))
    assert msg.targets == [0, 2]
    obs = observation_from_images(msg)
    assert obs.targets.tolist() == [0, 2]
    back = obs.views
    assert len(back) == len(views)
    for a, b in zip(views, back, strict=True):
        assert (a.observer, a.camera, a.step, a.t, a.target, a.baseline_m, a.intrinsics) == (b.observer, b.camera, b.step, b.t, b.target, b.baseline_m, b.intrinsics)
        np.testing.assert_array_equal(a.T_CB, b.T_CB)
        np.testing.assert_array_equal(a.r_C_B, b.r_C_B)
        assert len(a.images) == len(b.images) and all(np.array_equal(x, y) for x, y in zip(a.images, b.images, strict=True))


def test_bad_array_payload():
    est = json.loads(M.encode(EXAMPLES["est"]))
    est["P_pose"]["b64"] = est["P_pose"]["b64"][:-8]
    msg = M.decode("est", json.dumps(est).encode())
    with pytest.raises(M.MessageError, match="bytes"):
        msg.P_pose.array()


def test_keys_and_parsing():
    k = M.Keys("r1")
    assert M.parse_key(k.meas(3)) == ("r1", "meas", 3)
    assert M.parse_key(k.sensors(2)) == ("r1", "sensors", 2)
    assert M.parse_key(k.cam(0)) == ("r1", "cam", 0)
    assert M.parse_key(k.img(5)) == ("r1", "img", 5)
    assert M.parse_key(k.clock()) == ("r1", "clock", None)
    assert M.parse_key(k.cov(4)) == ("r1", "full_est", 4)
    assert M.parse_key(k.alive("agent", 7)) == ("r1", "alive", 7)
    for bad in ("swarm/r1/meas/x", "swarm/r1/nope", "other/r1/clock", "swarm/r1/sat/1/gyro"):
        with pytest.raises(M.MessageError):
            M.parse_key(bad)
    with pytest.raises(ValueError, match="run id"):
        M.Keys("bad/run")
