"""The live 3-D view: the scene served over the Foxglove WebSocket protocol by the SDK,
decoded by a plain client with the advertised schemas; the same channels in the recording and
in ``swarm sim``'s scene.mcap; the layout that opens them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), PYTHONUNBUFFERED="1")


def test_optional_live_address_on_the_command_line():
    from swarm.cli import optional_values

    assert optional_values(["run", "s.yaml", "--live", "--out", "d"]) == ["run", "s.yaml", "--live", "127.0.0.1:8765", "--out", "d"]
    assert optional_values(["run", "--live"]) == ["run", "--live", "127.0.0.1:8765"]
    assert optional_values(["run", "--live", "s.yaml"]) == ["run", "--live", "127.0.0.1:8765", "s.yaml"]
    assert optional_values(["run", "--live", "0.0.0.0:9000", "s.yaml"]) == ["run", "--live", "0.0.0.0:9000", "s.yaml"]
    assert optional_values(["run", "--live", "[::1]:9000"]) == ["run", "--live", "[::1]:9000"]
    from swarm.live import parse_address

    assert parse_address("[::1]:80") == ("::1", 80) and parse_address("localhost:0") == ("localhost", 0)
    with pytest.raises(ValueError):
        parse_address("8765")


def test_layout_opens_every_scene_channel():
    """The shipped layout is layout(10), reads only the scene's topics, and every scene topic
    of a 10-satellite swarm is in it."""
    from swarm.live.layout import SHIPPED_SATS, layout, layout_topics
    from swarm.record.scene import scene_topics

    shipped = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    assert shipped == json.loads(json.dumps(layout(SHIPPED_SATS)))
    assert layout_topics(shipped) == set(scene_topics(SHIPPED_SATS))
    # Every panel in the tree has a config, and every config is placed.
    placed: list[str] = []

    def walk(node):
        if isinstance(node, str):
            placed.append(node)
        else:
            walk(node["first"])
            walk(node["second"])

    walk(shipped["layout"])
    assert sorted(placed) == sorted(shipped["configById"])


def test_sdk_server_carries_the_builders_bytes_to_a_client():
    """In one process: the SDK server (port 0), a scene built from values, a websockets
    client decoding with the advertised schemas. Nothing is built before someone subscribes;
    the bytes a client receives are the builder's."""
    import foxglove

    from swarm.live.client import collect
    from swarm.live.sink import LiveSink
    from swarm.record.scene import CameraRig, SceneBuilder

    sink = LiveSink()
    b = SceneBuilder(sink, 3, 1.1e-3, 0.2, CameraRig())
    sink.advertise(b.topics())
    server = foxglove.start_server(name="test", host="127.0.0.1", port=0, context=sink.context)
    try:
        rng = np.random.default_rng(1)
        q = rng.normal(size=(3, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        r = rng.normal(size=(3, 3)) * 10
        b.truth(0, 0.0, q, r, 1)
        assert sink.sent == 0  # no client: nothing built
        stop = threading.Event()

        def feed():
            k = 1
            while not stop.is_set():
                b.truth(k, float(k), q, r + k, 10 + k)
                b.estimate(0, k, float(k), [0, 1, 2], q, r + k + 0.01, np.tile(np.eye(6) * 1e-4, (3, 1, 1)), 10 + k)
                k += 1
                time.sleep(0.02)

        th = threading.Thread(target=feed, daemon=True)
        th.start()
        want = {"/foxglove/truth", "/foxglove/tf", "/foxglove/est/0", "/errors/0", "/foxglove/cameras"}
        got = collect(f"ws://127.0.0.1:{server.port}", topics=want, until=lambda ms: want <= {m.topic for m in ms}, timeout_s=30)
        stop.set()
        th.join(5)
    finally:
        t = threading.Thread(target=server.stop, daemon=True)
        t.start()
        t.join(2)
    truth = next(m for m in got if m.topic == "/foxglove/truth")
    k = int({kv.key: kv.value for kv in truth.msg.entities[0].metadata}["k"])
    pos = np.array([[e.cubes[0].pose.position.x, e.cubes[0].pose.position.y, e.cubes[0].pose.position.z] for e in truth.msg.entities])
    np.testing.assert_array_equal(pos, r + k)
    err = next(m for m in got if m.topic == "/errors/0")
    assert err.schema_name == "swarm_coloc.view.FilterErrors" and err.msg.k >= 1
    np.testing.assert_allclose(err.msg.pos_err_m, np.full(3, 0.01 * np.sqrt(3)), rtol=1e-9)
    np.testing.assert_allclose(err.msg.pos_3sigma_m, np.full(3, 3 * np.sqrt(3e-4)), rtol=1e-9)
    cams = next(m for m in got if m.topic == "/foxglove/cameras")
    assert [e.frame_id for e in cams.msg.entities] == ["sat0", "sat1", "sat2"]
    assert all(len(e.lines[0].points) == 6 * 16 for e in cams.msg.entities)  # 6 frusta of 8 segments


def test_sim_scene_file_has_the_scene_channels(tmp_path):
    """``swarm sim`` writes scene.mcap: every scene channel of the swarm (links with links:),
    one message per step, the truth's cubes at the true positions."""
    import swarm
    from swarm.record.mcaplog import iter_records
    from swarm.record.scene import scene_topics

    sc = swarm.load_scenario(None, n_sats=3, duration_s=5, seed=2,
                             overrides={"links.enabled": True, "links.latency.fixed_s": 0.5})
    res = swarm.simulate(sc, out=tmp_path / "sim")
    counts, schemas = {}, {}
    for schema, ch, _msg in iter_records(tmp_path / "sim" / "scene.mcap"):
        counts[ch.topic] = counts.get(ch.topic, 0) + 1
        schemas[ch.topic] = (schema.name, schema.encoding, ch.message_encoding)
    K = sc.steps
    assert set(counts) == set(scene_topics(3)) - {"/foxglove/faults"}
    assert all(s[1:] == ("protobuf", "protobuf") for s in schemas.values()), schemas
    assert counts["/foxglove/measurements"] == 3 * K and all(counts[t] == K for t in counts if t != "/foxglove/measurements")
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with open(tmp_path / "sim" / "scene.mcap", "rb") as f:
        for _s, _c, m, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/foxglove/truth"]):
            k = round(m.log_time / 1e9 / sc.dt_s)
            pos = np.array([[e.cubes[0].pose.position.x, e.cubes[0].pose.position.y, e.cubes[0].pose.position.z] for e in msg.entities])
            np.testing.assert_array_equal(pos, res.arrays()["truth_r"][k])


def _scene_messages(path, topics) -> dict[str, list]:
    """Per topic, the decoded messages of a file in order, with every timestamp cleared (a
    recording stamps receive times, a simulation simulated ones)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list] = {t: [] for t in topics}
    with open(path, "rb") as f:
        for _s, ch, _m, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=list(topics)):
            for e in getattr(msg, "entities", []):
                e.ClearField("timestamp")
            for d in getattr(msg, "deletions", []):
                d.ClearField("timestamp")
            for t in getattr(msg, "transforms", []):
                t.ClearField("timestamp")
            out[ch.topic].append(msg.SerializeToString(deterministic=True))
    return out


@pytest.mark.integration
def test_live_view_of_swarm_run(tmp_path):
    """``swarm run --live``: a WebSocket client connects, subscribes to every advertised
    channel and decodes each message with its advertised schema; a first client leaves and a
    second comes without harm. Every truth scene it got shows the recording's truth of that
    step, every error message agrees with the recording's estimates, the channels and schemas
    are the recording's, and the recorded scene equals swarm sim's scene.mcap message for
    message (one builder)."""
    import swarm
    from swarm.live.client import collect
    from swarm.record.mcaplog import iter_records
    from swarm.supervise.launch import free_port

    port = free_port()
    out = tmp_path / "run"
    sc_file = tmp_path / "sc.yaml"
    sc_file.write_text("name: live\nseed: 4\nn_sats: 3\nduration_s: 150\nemulator: {step_timeout_s: 20.0}\n")
    cmd = [sys.executable, "-m", "swarm.cli", "run", str(sc_file), "--out", str(out), "--live", f"127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    got: dict[str, list] = {}
    try:
        deadline = time.monotonic() + 240
        while not (out / "live.json").exists():
            assert proc.poll() is None, proc.stdout.read().decode() if proc.stdout else ""
            assert time.monotonic() < deadline, "the live view did not come up"
            time.sleep(0.2)
        url = json.loads((out / "live.json").read_text())["url"]
        assert url == f"ws://127.0.0.1:{port}"

        def read(name: str, until, timeout: float) -> None:
            got[name] = collect(url, until=until, timeout_s=timeout, ok_if_closed=True)

        # Client b reads every channel to the end of the run (the server goes away with it);
        # client a reads a little and leaves meanwhile; then client c comes.
        b = threading.Thread(target=read, args=("b", lambda ms: False, 600), daemon=True)
        b.start()
        read("a", lambda ms: len(ms) >= 3, 240)
        read("c", lambda ms: len(ms) >= 3, 240)
        assert proc.wait(timeout=600) == 0, proc.stdout.read().decode() if proc.stdout else ""
        b.join(60)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(30)
    assert len(got["a"]) >= 3 and len(got["c"]) >= 3 and len(got["b"]) > 10
    res = swarm.Result.load(out)
    a = res.arrays()
    # Channels and schemas as recorded.
    recorded = {}
    for schema, ch, _m in iter_records(out / "run.mcap"):
        if ch.topic.startswith("/"):
            recorded[ch.topic] = (schema.name, schema.encoding, ch.message_encoding)
    msgs = got["a"] + got["b"] + got["c"]
    seen = {m.topic for m in msgs}
    assert {"/foxglove/truth", "/foxglove/tf", "/foxglove/est/0", "/errors/0"} <= seen
    for m in msgs:
        assert recorded[m.topic][0] == m.schema_name and recorded[m.topic][2] == "protobuf"
    truths = [m for m in msgs if m.topic == "/foxglove/truth"]
    assert len(truths) >= 3
    for m in truths:
        meta = {kv.key: kv.value for kv in m.msg.entities[0].metadata}
        k = int(meta["k"])
        pos = np.array([[e.cubes[0].pose.position.x, e.cubes[0].pose.position.y, e.cubes[0].pose.position.z] for e in m.msg.entities])
        np.testing.assert_array_equal(pos, a["truth_r"][k])
    errs = res.errors
    for m in (m for m in msgs if m.topic.startswith("/errors/")):
        e = m.msg
        row = errs[(errs["k"] == e.k) & (errs["filter"] == e.own)].sort_values("sat")
        np.testing.assert_allclose(e.pos_err_m, row["pos_err_m"], rtol=1e-12, atol=1e-15)
    # One builder: the recorded scene and swarm sim's, message for message (timestamps aside).
    sim = tmp_path / "sim-scene.mcap"
    swarm.simulate(res.scenario, scene=sim)
    topics = ["/foxglove/truth", "/foxglove/measurements", "/foxglove/cameras", *(f"/foxglove/est/{i}" for i in range(3)),
              *(f"/errors/{i}" for i in range(3))]
    rec_scene, sim_scene = _scene_messages(out / "run.mcap", topics), _scene_messages(sim, topics)
    for t in topics:
        assert len(rec_scene[t]) == len(sim_scene[t]) > 0, t
        if t == "/foxglove/measurements":  # a step's batches are recorded in the order they arrived
            assert sorted(rec_scene[t]) == sorted(sim_scene[t])
        else:
            assert rec_scene[t] == sim_scene[t], t


def test_compose_keys_serve_the_live_view_and_tolerate_keys_made_before_it(tmp_path, capsys):
    """compose's keys service gives the live service the viewer's credential; a keys
    directory made before the viewer existed still runs the swarm (the live role is skipped,
    saying why)."""
    from swarm.supervise.compose_keys import ROLE_FILES, main
    from swarmrt.security import make_keys

    keys = make_keys(tmp_path / "keys", 3, tls_hosts=["router"])
    roles = tmp_path / "roles"
    for r in ("agent", "live"):
        (roles / r).mkdir(parents=True)
    assert main(["--keys", str(keys), "--roles", str(roles)]) == 0
    assert sorted(p.name for p in (roles / "live").iterdir()) == sorted(ROLE_FILES["live"]) == ["ca.pem", "viewer.json"]
    (keys / "viewer.json").unlink()
    for p in (roles / "live").iterdir():
        p.unlink()
    capsys.readouterr()
    assert main(["--keys", str(keys), "--roles", str(roles)]) == 0
    err = capsys.readouterr().err
    assert "lacks viewer.json" in err and "gave agent their credentials" in err
    assert not list((roles / "live").iterdir()) and (roles / "agent" / "claimant.json").is_file()
