"""Foxglove channels: the frame convention, and every derived message validates against
the official schema embedded in the recording."""

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation
from swarm_harness import run_swarm, scenario

from swarm.record.foxglove import q_BH
from swarmcore import quat
from swarmcore.dynamics import T_IH


def test_foxglove_quaternion_puts_body_axes_in_the_hcw_frame():
    rng = np.random.default_rng(4)
    q_BI = quat.random_quaternion(rng, 5)
    n, t = 1.08e-3, 777.0
    q = q_BH(q_BI, n, t)
    v_B = rng.normal(size=(5, 3))
    # A body vector in H coordinates: T_IHᵀ T(q_BI)ᵀ v_B.
    expected = np.einsum("ij,njk,nk->ni", T_IH(n, t).T, np.swapaxes(quat.attitude_matrix(q_BI), 1, 2), v_B)
    # Foxglove (like scipy) reads (x, y, z, w) as the active rotation child → parent.
    np.testing.assert_allclose(Rotation.from_quat(q).apply(v_B), expected, atol=1e-12)


@pytest.mark.integration
def test_derived_channels_validate_against_their_schemas(tmp_path):
    sc = scenario(n_sats=3, duration_s=6)
    _rec, _summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    counts = {}
    with open(tmp_path / "run" / "run.mcap", "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        channels = {c.topic: c for c in r.get_summary().channels.values()}
        schemas = r.get_summary().schemas
        fox = [t for t in channels if t.startswith("/foxglove/")]
        for t in fox:
            s = schemas[channels[t].schema_id]
            assert channels[t].message_encoding == "protobuf" and s.encoding == "protobuf" and s.name.startswith("foxglove.")
        for _s, ch, _m, msg in r.iter_decoded_messages(topics=fox):
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
            if ch.topic == "/foxglove/tf":
                assert [tf.child_frame_id for tf in msg.transforms] == ["sat0", "sat1", "sat2"]
                assert all(tf.parent_frame_id == "hcw" for tf in msg.transforms)
                q = np.array([[tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w] for tf in msg.transforms])
                np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
            elif ch.topic.startswith("/foxglove/est/"):
                assert len(msg.entities) == 3 and all(len(e.spheres) == 1 and len(e.cubes) == 1 for e in msg.entities)
                assert all(e.spheres[0].size.x > 0 for e in msg.entities)
    K = sc.steps
    assert counts["/foxglove/tf"] == K and counts["/foxglove/truth"] == K
    assert all(counts[f"/foxglove/est/{i}"] == K for i in range(3))
    assert counts["/foxglove/measurements"] == 3 * K


def test_link_states_take_the_worst_event_of_the_step():
    from swarm.record.foxglove import LINK_STATES, link_states

    names = [s for s, _ in LINK_STATES]
    z = np.zeros((3, 3), dtype=int)
    prev = {k: z.copy() for k in ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")}
    cur = {k: v.copy() for k, v in prev.items()}
    cur["sent"][0, 1] = 1  # 0 → 1: sent, nothing arrived: in flight
    cur["sent"][1, 0] = cur["delivered"][1, 0] = 1  # 1 → 0: delivered within its step
    cur["delivered"][0, 2] = cur["delivered_late"][0, 2] = 1  # 0 → 2: a late delivery ...
    cur["lost"][0, 2] = 1  # ... and a loss in the same step: lost wins
    cur["delivered"][2, 0] = cur["delivered_late"][2, 0] = 1  # 2 → 0: late
    cur["dropped_queue"][2, 1] = 1  # 2 → 1: dropped at the queue
    cur["unreachable"][1, 2] = 1  # 1 → 2: unreachable
    s = link_states(prev, cur)
    got = {(i, j): names[s[i, j]] for i in range(3) for j in range(3) if s[i, j] >= 0}
    assert got == {(0, 1): "in_flight", (1, 0): "delivered", (0, 2): "lost", (2, 0): "delivered_late",
                   (2, 1): "dropped_queue", (1, 2): "unreachable"}
    # Counters are cumulative: the next step with no new event draws nothing.
    assert (link_states(cur, cur) == -1).all()
    # The first step counts from zero.
    assert (link_states(None, cur) == s).all()


@pytest.mark.integration
def test_links_channel_shows_each_directed_link_in_the_state_of_its_step(tmp_path):
    """/foxglove/links: one SceneUpdate per step; each directed link with traffic is the half
    segment from the sender's true position to the midpoint, coloured and labelled by the
    state the recorded LinkStats counters give for that step."""
    from swarm.record.foxglove import LINK_STATES, link_states
    from swarm.record.mcaplog import iter_messages
    from swarm.record.recording import load_recording
    from swarmrt.bus.convert import array
    from swarmrt.bus.messages import decode

    links = {
        "enabled": True,
        "latency": {"fixed_s": 2.0, "speed_of_light": False, "jitter": {"distribution": "uniform", "scale_s": 0.5}},
        "loss": {"model": "gilbert_elliott", "rate": 0.3, "mean_burst": 3},
        "rate_Bps": 1000.0,
        "queue_bytes": 2000,  # about three batches: some copies are dropped at the queue
        "overrides": [{"from": 2, "to": 0, "dead": True}],  # unreachable
    }
    sc = scenario(n_sats=3, duration_s=12, links=links)
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    names = [s for s, _ in LINK_STATES]
    colours = dict(LINK_STATES)
    # The expected state of every step, from the recorded LinkStats (the world's counters).
    counters = {}
    for topic, _schema, data, _lt, _pt in iter_messages(tmp_path / "run" / "run.mcap"):
        if not topic.startswith("/") and topic.endswith("/links"):
            m = decode("links", data)
            counters[m.k] = {c: np.rint(array(getattr(m, c))).astype(int) for c in
                             ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")}
    assert sorted(counters) == list(range(sc.steps))
    expected = {k: link_states(counters.get(k - 1), counters[k]) for k in counters}
    seen_states = set()
    n_msgs = 0
    with open(tmp_path / "run" / "run.mcap", "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        summ = r.get_summary()
        ch = next(c for c in summ.channels.values() if c.topic == "/foxglove/links")
        assert ch.message_encoding == "protobuf" and summ.schemas[ch.schema_id].name == "foxglove.SceneUpdate"
        for k, (_s, _c, _m, msg) in enumerate(r.iter_decoded_messages(topics=["/foxglove/links"])):
            n_msgs += 1
            (ent,) = msg.entities
            assert ent.id == "links" and ent.frame_id == "hcw"
            exp = expected[k]
            meta = {tuple(int(x) for x in kv.key.split("->")): kv.value for kv in ent.metadata}
            assert meta == {(i, j): names[exp[i, j]] for i in range(3) for j in range(3) if exp[i, j] >= 0}, k
            seen_states |= set(meta.values())
            r_H = rec.truth.r_H_m[k]
            drawn = {}
            for line in ent.lines:
                state = next(n for n, rgb in colours.items() if np.allclose(rgb, (line.color.r, line.color.g, line.color.b)))
                pts = np.array([[p.x, p.y, p.z] for p in line.points]).reshape(-1, 2, 3)
                for a, b in pts:
                    i = int(np.argmin(np.linalg.norm(r_H - a, axis=1)))
                    np.testing.assert_allclose(a, r_H[i], atol=1e-9)
                    j = next(j for j in range(3) if j != i and np.allclose(b, 0.5 * (r_H[i] + r_H[j]), atol=1e-9))
                    drawn[(i, j)] = state
            assert drawn == meta
    assert n_msgs == sc.steps
    # The run exercised every state but "delivered" on time (latency 2 s: nothing is on time).
    assert {"in_flight", "delivered_late", "lost", "dropped_queue", "unreachable"} <= seen_states
    assert summary["links"]["totals"]["dropped_queue"] > 0
    assert load_recording(tmp_path / "run" / "run.mcap", 3, sc.steps).links is not None
