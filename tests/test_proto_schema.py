"""The .proto files are the single source of truth, and a recording needs nothing of ours.

* the committed generated code is what the schema files generate;
* every bus message starts with the common header (fields 1–5);
* a recording of a real run decodes with tools not written here — the ``mcap`` reader with
  ``mcap-protobuf-support`` (classes built from the embedded schemas) and Debian's
  ``protoc --decode`` — to exactly the values the project reads.
"""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from swarmrt.bus import messages as M
from swarmrt.bus.convert import array

ROOT = Path(__file__).resolve().parent.parent
PROTO = ROOT / "proto"


def test_generated_code_is_what_the_schema_files_generate(tmp_path):
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "gen_proto.py"), "--out", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    fresh = sorted((tmp_path / "swarmrt" / "bus" / "v1").glob("*_pb2.py*"))  # the code and its type stubs
    committed = sorted((ROOT / "swarmrt" / "bus" / "v1").glob("*_pb2.py*"))
    want = sorted(f.stem + suffix for f in (PROTO / "swarm" / "v1").glob("*.proto") for suffix in ("_pb2.py", "_pb2.pyi"))
    assert [f.name for f in fresh] == [f.name for f in committed] == want
    stale = [f.name for f, g in zip(fresh, committed, strict=True) if f.read_bytes() != g.read_bytes()]
    assert not stale, f"run scripts/gen_proto.py: {stale} differ from what proto/ generates"


def test_every_bus_message_starts_with_the_header():
    want = [(f.name, f.number, f.type) for f in M.Header.DESCRIPTOR.fields]
    assert [w[:2] for w in want] == [("schema_version", 1), ("run", 2), ("sender", 3), ("k", 4), ("t_s", 5)]
    for kind, cls in M.MODELS.items():
        d = cls.DESCRIPTOR
        assert d.full_name.startswith("swarm.v1."), kind
        assert [(f.name, f.number, f.type) for f in d.fields if f.number <= 5] == want, d.full_name
        numbers = [f.number for f in d.fields]
        assert len(numbers) == len(set(numbers))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from swarm_harness import run_swarm, scenario

    sc = scenario(n_sats=3, duration_s=5, selection={"strategy": "random", "budget": 3})
    out = tmp_path_factory.mktemp("proto") / "run"
    rec, _summary, codes, _ = run_swarm(sc, out)
    assert codes["world"] == 0
    return out / "run.mcap", rec, sc


@pytest.mark.integration
def test_mcap_reader_decodes_every_project_channel_from_its_embedded_schema(recording):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path, rec, _sc = recording
    ours = {cls.DESCRIPTOR.full_name: cls for cls in M.MODELS.values()}
    seen = {}
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = r.get_summary()
        for ch in summary.channels.values():
            s = summary.schemas[ch.schema_id]
            assert ch.message_encoding == "protobuf" and s.encoding == "protobuf", ch.topic
        for schema, ch, _raw, msg in r.iter_decoded_messages():
            if ch.topic.startswith("/foxglove/"):
                continue
            name = schema.name
            seen[name] = seen.get(name, 0) + 1
            # The class was built from the file's schema, not taken from our generated code.
            assert type(msg) is not ours.get(name) and type(msg).DESCRIPTOR.full_name == name
            if name == "swarm.v1.Estimate" and msg.phase == "posterior":
                f = msg.own
                np.testing.assert_array_equal(np.reshape(msg.q_BI, (-1, 4)), rec.est.q_BI[msg.k, f])
                np.testing.assert_array_equal(np.asarray(msg.P_diag.data), rec.est.P_diag[msg.k, f])
            elif name == "swarm.v1.Truth":
                np.testing.assert_array_equal(np.reshape(msg.r_H_m, (-1, 3)), rec.truth.r_H_m[msg.k])
    for name in ("Clock", "Sensors", "CameraOutput", "MeasBatch", "Estimate", "Select", "Health", "Truth", "Liveliness"):
        assert seen.get(f"swarm.v1.{name}", 0) > 0, (name, seen)


def _protoc_decode(message: str, proto_file: str, data: bytes) -> str:
    protoc = shutil.which("protoc")
    assert protoc, "protoc not found: install Debian's protobuf-compiler (scripts/apt-packages.txt)"
    p = subprocess.run([protoc, f"-I{PROTO}", f"--decode=swarm.v1.{message}", proto_file], input=data, capture_output=True, timeout=60)
    assert p.returncode == 0, p.stderr.decode()
    return p.stdout.decode()


def _numbers(text: str, field: str) -> list[float]:
    """Every top-level-or-nested ``field: value`` of protoc's text output, as floats."""
    return [float(v) for v in re.findall(rf"^\s*{field}: (\S+)$", text, flags=re.M)]


@pytest.mark.integration
def test_protoc_decode_of_recorded_messages_equals_the_python_values(recording):
    from swarm.record.mcaplog import iter_messages

    path, rec, _sc = recording
    done = set()
    for topic, _schema, data, _lt, _pt in iter_messages(path):
        if not topic.startswith("swarm/"):
            continue
        kind = topic.split("/")[2]
        if kind == "est" and "est" not in done:
            m = M.decode("est", data)
            if m.phase != "posterior" or m.k < 2:
                continue
            text = _protoc_decode("Estimate", "swarm/v1/estimate.proto", data)
            assert _numbers(text, "own") == [m.own] or (m.own == 0 and "own:" not in text)
            assert _numbers(text, "k") == [m.k]
            assert _numbers(text, "q_BI") == rec.est.q_BI[m.k, m.own].ravel().tolist()
            assert _numbers(text, "r_H_m") == rec.est.r_H_m[m.k, m.own].ravel().tolist()
            # P_pose { shape: ... data: ... }: the nested Matrix of the pose covariances.
            block = text[text.index("P_pose {"): text.index("}", text.index("P_pose {"))]
            assert _numbers(block, "shape") == [3, 6, 6]
            assert _numbers(block, "data") == list(m.P_pose.data)
            done.add("est")
        elif kind == "meas" and "meas" not in done:
            m = M.decode("meas", data)
            if not len(m.target):
                continue
            text = _protoc_decode("MeasBatch", "swarm/v1/measurements.proto", data)
            assert _numbers(text, "target") == list(m.target)
            assert _numbers(text, "q_BjBi") == list(m.q_BjBi)
            block = text[text.index("R_Bi {"):]
            assert _numbers(block, "data") == array(m.R_Bi).ravel().tolist()
            done.add("meas")
        elif kind == "batches" and "batches" not in done:
            # What an agent of another language reads of its peers: the radio's one message.
            m = M.decode("batches", data)
            if len(m.observers) < 2 or not len(m.target):
                continue
            text = _protoc_decode("StepBatches", "swarm/v1/measurements.proto", data)
            assert _numbers(text, "observers") == list(m.observers)
            assert _numbers(text, "counts") == list(m.counts)
            assert _numbers(text, "q_BjBi") == list(m.q_BjBi)
            block = text[text.index("R_Bi {"):]
            assert _numbers(block, "data") == array(m.R_Bi).ravel().tolist()
            done.add("batches")
        elif kind == "truth" and "truth" not in done:
            m = M.decode("truth", data)
            text = _protoc_decode("Truth", "swarm/v1/truth.proto", data)
            assert _numbers(text, "t_s") == [rec.t_s[m.k]] or (m.k == 0 and "t_s:" not in text)
            assert _numbers(text, "q_BI") == rec.truth.q_BI[m.k].ravel().tolist()
            done.add("truth")
    assert done == {"est", "meas", "batches", "truth"}


def test_a_recording_of_the_json_wire_format_is_refused_with_the_reason(tmp_path):
    from swarm.record.mcaplog import CheckpointWriter
    from swarm.record.recording import load_recording

    w = CheckpointWriter(tmp_path / "old.mcap")
    cid = w.channel("swarm/old-run/truth", w.schema("swarm.Truth", "jsonschema", b"{}"))
    w.add(cid, b'{"v": 1, "run": "old-run", "sender": "world", "k": 0, "t_s": 0.0, "q_BI": [[0, 0, 0, 1]]}', 1)
    w.close()
    with pytest.raises(ValueError, match="JSON messages of swarm-coloc before the protobuf wire format"):
        load_recording(tmp_path / "old.mcap")


@pytest.mark.integration
def test_recover_keeps_every_channels_protobuf_schema(recording, tmp_path):
    from swarm.record.mcaplog import iter_records, recover

    path, _rec, _sc = recording
    torn = tmp_path / "torn.mcap"
    data = path.read_bytes()
    torn.write_bytes(data[: int(len(data) * 0.8)])  # as a writer killed mid-file leaves it
    n = recover(torn, tmp_path / "back.mcap")
    assert n > 0
    back = list(iter_records(tmp_path / "back.mcap"))
    assert len(back) == n
    original = {ch.topic: (s.name, s.encoding, s.data, ch.message_encoding) for s, ch, _m in iter_records(path)}
    for s, ch, m in back:
        assert (s.name, s.encoding, s.data, ch.message_encoding) == original[ch.topic]
        if ch.topic.startswith("swarm/") and "/est/" in ch.topic:
            assert M.decode("est", m.data).run == M.Header.FromString(m.data).run


@pytest.mark.parametrize("kind", ["ci", "pairwise"])
def test_protoc_decodes_an_estimators_message_in_a_batch_to_the_python_values(kind):
    """An estimator's message as it rides in a batch (MeasBatch.estimator): what a
    participant of another language, or protoc, reads of it is the estimator's numbers."""
    import numpy as np

    from swarmcore.estimators import builtin_estimator
    from swarmcore.mekf import RelativeMeasurements
    from swarmcore.scenario import Scenario
    from swarmcore.world import initial_estimate, initial_truth
    from swarmrt.bus.convert import batch_msg
    from swarmrt.estimators import codec_for

    sc = Scenario(n_sats=3, estimator={"kind": kind})
    e = builtin_estimator(sc, 1)
    e.start(initial_estimate(sc, initial_truth(sc), 1, e.prior_ids()))
    if kind == "pairwise":
        e.sigma[2] = np.arange(144.0).reshape(12, 12) / 7  # type: ignore[attr-defined]
    payload = e.transmit(0)
    msg = batch_msg(RelativeMeasurements.empty(), np.zeros(0, dtype=int), run="r", sender="agent-1", k=0, t_s=0.0, observer=1,
                    estimator=codec_for(sc).to_msg(payload))
    text = _protoc_decode("MeasBatch", "swarm/v1/measurements.proto", M.encode(msg))
    assert f'kind: "{kind}"' in text and "version: 1" in text
    body = text[text.index(f"{kind} {{"):]
    assert _numbers(body, "q_BI") == payload.q_BI.tolist()
    assert _numbers(body, "r_H_m") == payload.r_H.tolist()
    cov = payload.P_pose if kind == "ci" else payload.P
    name = "P_pose" if kind == "ci" else "P"
    block = body[body.index(f"{name} {{"): body.index("}", body.index(f"{name} {{"))]
    assert _numbers(block, "data") == cov.ravel().tolist()
    if kind == "pairwise":
        assert _numbers(body, "partners") == [2]


def test_the_scenario_model_knows_exactly_the_schemas_fault_actions_and_which_need_a_target():
    """The schema's FaultAction (proto/swarm/v1/fault.proto) is the one list: the bus
    validator and the Rust agent's checks take theirs from it, and the scenario model (in the
    core, which imports no schema) holds the same actions, needing a target exactly where
    the schema's numbering (below 50) says so."""
    from swarmcore.scenario import FAULT_ACTIONS, TARGETED_FAULTS
    from swarmrt.bus.validation import WIRE_FAULT_ACTIONS, WIRE_FAULT_PHASES, WIRE_TARGETED_FAULTS

    assert sorted(WIRE_FAULT_ACTIONS) == sorted(FAULT_ACTIONS)
    assert sorted(WIRE_TARGETED_FAULTS) == sorted(TARGETED_FAULTS)
    assert WIRE_FAULT_PHASES == ("command", "done", "failed")
    assert "kill-agent" in WIRE_TARGETED_FAULTS and "kill-router" not in WIRE_TARGETED_FAULTS


def test_a_fault_with_an_action_or_phase_the_schema_does_not_declare_is_refused_by_name():
    from swarmrt.bus.validation import validate
    from swarmrt.bus.wire import MessageError

    ok = M.Fault(schema_version=M.SCHEMA_VERSION, run="r", sender="cli", k=0, t_s=0.0, action="kill-router", phase="command")
    validate(ok, n_sats=4)
    for field, bad in (("action", "unspecified"), ("action", "kill_agent"), ("phase", "unspecified")):
        m = M.Fault()
        m.CopyFrom(ok)
        setattr(m, field, bad)
        with pytest.raises(MessageError, match=field):
            validate(m, n_sats=4)
    needs = M.Fault()
    needs.CopyFrom(ok)
    needs.action = "kill-agent"
    with pytest.raises(MessageError, match="needs a target"):
        validate(needs, n_sats=4)
