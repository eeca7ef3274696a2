"""Foxglove channels: the frame convention, and every derived message validates against
the official schema embedded in the recording."""

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from swarm.foxglove import q_BH
from swarmcore import quat
from swarmcore.dynamics import T_IH

from swarm_harness import run_swarm, scenario


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
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
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
