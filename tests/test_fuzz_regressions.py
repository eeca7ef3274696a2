"""Every input the fuzzers (or reading the loaders for them) found to break a loader, kept:
each is now refused with the loader's documented error, naming the problem, or read."""

import dataclasses
import json

import numpy as np
import pytest

from fuzz import targets as F
from swarm.record.mcaplog import CheckpointWriter, iter_messages, recover
from swarm.record.recording import RecordingError, load_recording
from swarmrt.bus import messages as M
from swarmrt.security import MAX_KEYS_FILE_BYTES, load_agent_passwords, load_credential, load_router_keys


# -- credentials and keys ---------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("[" * 100_000, "nested too deeply"),  # was RecursionError out of json
        ('{"user": "world", "password": "p", "ca": 5}', '"ca" must be'),  # was TypeError (Path / int)
        ('{"user": "world", "password": "p", "ca": "a\\u0000b"}', '"ca" must be'),  # was ValueError: embedded null byte
        ('{"user": "world", "password": "p", "ca": ["x"]}', '"ca" must be'),
        ('{"user": "nobody", "password": "p"}', "not a swarm identity"),
        ("\xff\xfe", "credential"),
    ],
)
def test_malformed_credentials_are_refused_naming_the_file(tmp_path, text, reason):
    p = tmp_path / "cred.json"
    p.write_bytes(text.encode("latin-1") if text.startswith("\xff") else text.encode())
    with pytest.raises(SystemExit) as exc:
        load_credential(p)
    assert str(exc.value.code).startswith(f"credential {p}:") and reason in str(exc.value.code)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ('{"0": {"a": 1}}', "password is a dict"),  # was read as the password "{'a': 1}"
        ('{"-5": "x"}', "not a satellite id"),  # was satellite -5
        ('{"99999": "x"}', "not a satellite id"),
        ('{"1e3": "x"}', "not a satellite id"),
        ("[1, 2]", "expected a JSON object"),
        ('{"0": ' + "[" * 100_000, "nested too deeply"),  # was RecursionError
    ],
)
def test_malformed_agent_passwords_are_refused(tmp_path, text, reason):
    p = tmp_path / "agents.json"
    p.write_text(text)
    with pytest.raises(SystemExit) as exc:
        load_agent_passwords(p)
    assert str(exc.value.code).startswith(f"agent passwords {p}:") and reason in str(exc.value.code)
    p.write_text('{"0": "a", "12": "b"}')
    assert load_agent_passwords(p) == {0: "a", 12: "b"}


def test_huge_keys_files_are_refused_without_reading_them_whole(tmp_path):
    p = tmp_path / "cred.json"
    with open(p, "wb") as f:
        f.truncate(MAX_KEYS_FILE_BYTES + 10)
    with pytest.raises(SystemExit, match="larger than"):
        load_credential(p)
    with pytest.raises(SystemExit, match="larger than"):
        load_agent_passwords(p)


@pytest.mark.parametrize(
    ("router", "reason"),
    [
        ("[]", "expected a JSON object"),  # was TypeError (list indices)
        ("{}", "expected a JSON object"),  # was KeyError: 'passwords'
        ('{"passwords": 3}', "expected a JSON object"),  # was TypeError (Path / int)
        ('{"passwords": "passwords", "certificate": "c.pem"}', "go together"),  # was KeyError: 'private_key'
        ("{", "router keys"),  # was json's bare JSONDecodeError
    ],
)
def test_malformed_router_keys_are_refused(tmp_path, router, reason):
    (tmp_path / "router.json").write_text(router)
    (tmp_path / "passwords").write_text("world:x\n")
    with pytest.raises(SystemExit) as exc:
        load_router_keys(tmp_path)
    assert reason in str(exc.value.code)


def test_a_binary_password_dictionary_is_refused(tmp_path):
    (tmp_path / "passwords").write_bytes(b"\xff\xfeworld:x\n")  # was UnicodeDecodeError
    with pytest.raises(SystemExit, match="password dictionary"):
        load_router_keys(tmp_path)
    (tmp_path / "passwords").write_text("world:x\nagent-0:y\n")
    assert load_router_keys(tmp_path)[2] == {"world", "agent-0"}


# -- recordings -----------------------------------------------------------------------------------
MSGS = F.seed_messages()
TRUTH = MSGS["truth"][0]


def _recording(path, items):
    w = CheckpointWriter(path)
    for t, (topic, data) in enumerate(items):
        w.add(w.channel(topic, w.schema("swarm.v1.Any", "protobuf", b""), "protobuf"), data, 1000 + t)
    w.close(finalize=False)
    return path


def _truths(K):
    return [("swarm/fz/truth", M.encode(M.replace(TRUTH, k=k))) for k in range(K)]


def test_a_damaged_step_number_asks_for_no_terabytes(tmp_path):
    # A flipped bit in one truth's step: the run's arrays were sized by it (8 TiB, MemoryError).
    p = _recording(tmp_path / "r.mcap", [*_truths(4), ("swarm/fz/truth", M.encode(M.replace(TRUTH, k=2**40)))])
    for n in (3, None):
        rec = load_recording(p, n, None)
        assert (rec.n, rec.K) == (3, 4)
    only_far = _recording(tmp_path / "far.mcap", [("swarm/fz/truth", M.encode(M.replace(TRUTH, k=2**40)))])
    with pytest.raises(RecordingError, match="fewer than half"):
        load_recording(only_far, 3, None)


def test_messages_naming_satellites_beyond_the_swarm_are_skipped(tmp_path):
    meas = M.replace(MSGS["meas"][0], k=1, target=[50, 0])  # was IndexError on the (K, n, n) arrays
    est4 = F.estimate_msg(F._estimate(np.random.default_rng(1), 4), run="fz", sender="agent-1", own=1)  # was a broadcast ValueError
    truth4 = F.truth_msg(F.initial_truth(F.Scenario(n_sats=4, seed=2)), run="fz", k=1)
    links2 = M.replace(MSGS["links"][0], queue_bytes=[0, 1], **{f: F.matrix(np.zeros((2, 2))) for f in M._LINK_COUNTERS})
    p = _recording(tmp_path / "r.mcap", [*_truths(3), ("swarm/fz/meas/2", M.encode(meas)), ("swarm/fz/est/1", M.encode(est4)),
                                         ("swarm/fz/truth", M.encode(truth4)), ("swarm/fz/links", M.encode(links2))])
    rec = load_recording(p, 3, None)
    assert not rec.taken.any() and not rec.alive.any() and rec.links is None
    assert load_recording(p).n == 3  # the size most truth messages have


def test_undecodable_liveliness_and_gap_records_are_skipped(tmp_path):
    # Were DecodeError out of load_recording.
    p = _recording(tmp_path / "r.mcap", [*_truths(2), ("swarm/fz/alive", b"\xff\xff\xff"), ("swarm/fz/_gap", b"\xff\xff\xff")])
    rec = load_recording(p, 3, None)
    assert rec.bus is not None and rec.bus.liveliness == [] and rec.bus.gaps == []


def test_a_recording_without_truth_is_a_recording_error(tmp_path):
    p = _recording(tmp_path / "r.mcap", [("swarm/fz/clock", M.encode(MSGS["clock"][0]))])
    with pytest.raises(RecordingError, match="no truth messages"):
        load_recording(p)
    garbage = tmp_path / "g.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    with pytest.raises(RecordingError):
        load_recording(garbage)
    assert list(iter_messages(garbage)) == []
    assert recover(garbage, tmp_path / "g2.mcap") == 0


def test_seed_recordings_load(tmp_path):
    for finalize in (False, True):
        p = F.seed_mcap(tmp_path / f"s{finalize}.mcap", finalize)
        rec = load_recording(p, 3, None)
        assert rec.K == 3 and rec.alive.all() and rec.links is not None and rec.bus is not None
        assert len(rec.bus.gaps) == 1 and rec.bus.liveliness and json.dumps(rec.bus.counts)


def _same(x, y) -> bool:
    """Equal field by field, arrays element by element (NaN equal to NaN)."""
    if isinstance(x, np.ndarray):
        return isinstance(y, np.ndarray) and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    if dataclasses.is_dataclass(x):
        return type(x) is type(y) and all(_same(getattr(x, f.name), getattr(y, f.name)) for f in dataclasses.fields(x))
    if isinstance(x, (list, tuple)):
        return type(x) is type(y) and len(x) == len(y) and all(_same(a, b) for a, b in zip(x, y))
    return bool(x == y)


def test_a_recording_loads_the_same_from_the_messages_read_already(tmp_path):
    # fuzz_mcap reads each input once and gives both loads what the reader yielded.
    far = M.encode(M.replace(TRUTH, k=2**40))
    files = [F.seed_mcap(tmp_path / f"s{fin}.mcap", fin) for fin in (False, True)]
    files.append(_recording(tmp_path / "r.mcap", [*_truths(3), ("swarm/fz/truth", far), ("swarm/fz/truth", far), ("swarm/fz/alive", b"\xff")]))
    for p in files:
        messages = list(iter_messages(p))
        for n in (3, None):
            a, b = load_recording(p, n, None), load_recording(p, n, None, messages=messages)
            assert a.bus is not None and (a.alive.any() or p.name == "r.mcap"), p.name  # there is something to compare
            assert _same(a, b), (p.name, n)


# -- scenario files -----------------------------------------------------------------------------
_LAUGHS = "a: &a [x,x,x,x,x,x,x,x,x,x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 10) + "]\n" for i in range(7))


@pytest.mark.parametrize(
    ("name", "raw", "reason"),
    [
        # the fuzzer's first find (committed as fuzz/corpus/scenario/crash-not-utf8): was UnicodeDecodeError
        ("not-utf8", b"name: x\n\xff\xfe\n", "not UTF-8"),
        ("deep-flow", b"n_sats: " + b"[" * 5000 + b"]" * 5000, "nested too deeply"),  # was RecursionError (PyYAML's composer)
        ("deep-block", b"n_sats:\n" + b"".join(b" " * i + b"- \n" for i in range(3000)), "nested too deeply"),
        # a billion laughs: 10^8 values from 8 aliases; was 86 s (and gigabytes) formatting the error
        ("laughs", (_LAUGHS + "n_sats: *h\n").encode(), "values once its aliases are expanded"),
        ("recursive-alias", b"n_sats: &r [*r]\n", "nested deeper"),
        ("huge-int", b"seed: " + b"9" * 5000 + b"\n", "not valid YAML"),  # was a bare ValueError out of PyYAML
        ("inf-duration", b"duration_s: .inf\n", "duration_s: Input should be a finite number"),  # loaded; steps then OverflowError
        ("nan-inertia", b"spacecraft: {inertia_kg_m2: [.nan, 1, 1]}\n", "spacecraft.inertia_kg_m2"),  # was accepted
        ("nan-vision", b"vision: {mono: {tag_size_m: .nan}}\n", "vision.mono.tag_size_m"),
    ],
)
def test_hostile_scenario_files_are_scenario_errors(tmp_path, name, raw, reason):
    from swarmrt.scenario_files import ScenarioError, load_scenario

    p = tmp_path / f"{name}.yaml"
    p.write_bytes(raw)
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    assert str(exc.value).startswith(f"{p}:") and reason in str(exc.value)
    assert len(str(exc.value)) < 5000


def test_scenario_errors_show_a_bounded_part_of_large_values(tmp_path):
    from swarmrt.scenario_files import ScenarioError, load_scenario

    p = tmp_path / "s.yaml"
    p.write_text(_LAUGHS.split("\nf")[0] + "\nspacecraft: {inertia_kg_m2: *d}\n")  # 10^4 values, every one wrong
    with pytest.raises(ScenarioError, match=r"spacecraft\.inertia_kg_m2") as exc:
        load_scenario(p)
    assert len(str(exc.value)) < 10_000 and "more" in str(exc.value)


def test_huge_scenario_files_are_refused_unread(tmp_path):
    from swarmrt.scenario_files import MAX_SCENARIO_BYTES, ScenarioError, load_scenario

    p = tmp_path / "big.yaml"
    with open(p, "wb") as f:
        f.truncate(MAX_SCENARIO_BYTES + 1)
    with pytest.raises(ScenarioError, match="larger than"):
        load_scenario(p)


def test_overrides_too_are_bounded():
    from swarmrt.scenario_files import ScenarioError, load_scenario

    with pytest.raises(ScenarioError, match="nested too deeply"):
        load_scenario(None, ["name=" + "[" * 5000])
    with pytest.raises(ScenarioError, match="aliases"):
        load_scenario(None, ["graph.matrix=" + _LAUGHS.replace("\n", ", ").join("{}")])
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(None, ["seed=" + "9" * 5000])


# -- conversions ------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [[2**31, 2**31, 4], [2**16, 2**16, 2**16, 2**16], [0, 5], [3, 0, 7], [0, 2**31 - 1, 2**31 - 1]])
def test_a_matrix_whose_shape_overflows_int64_is_a_message_error(shape):
    from swarmrt.bus.convert import array

    m = M.Matrix(shape=shape, data=[])
    if 0 in shape and max(shape) < 2**31 - 1:
        assert array(m).shape == tuple(shape)
    elif 0 in shape:  # found by the property test: numpy's "array is too big" was a bare ValueError
        with pytest.raises(M.MessageError, match="too big"):
            array(m)
    else:  # the product wrapped to 0 in int64: was a bare "cannot reshape" ValueError
        with pytest.raises(M.MessageError, match="needs"):
            array(m)


@pytest.mark.parametrize("value", [1e300, 2.0**64, 0.5, 2.0**53 + 2])
def test_link_counters_are_whole_numbers_a_receiver_can_read_as_integers(value):
    # Were accepted: 1e300 became INT64_MIN in LinkCounters (numpy's cast of an out-of-range float).
    a = np.arange(9.0).reshape(3, 3)
    a[1, 2] = value
    raw = M.encode(M.replace(MSGS["links"][0], delivered=F.matrix(a)))
    with pytest.raises(M.MessageError, match="delivered: not a count"):
        M.decode("links", raw)
    a[1, 2] = 2.0**53
    M.decode("links", M.encode(M.replace(MSGS["links"][0], delivered=F.matrix(a))))


def test_a_camera_view_with_huge_entries_is_refused_without_overflow():
    # msg_img's finding (fuzz/corpus/msg_img/crash-matmul-overflow): T_CB of 1e200s gave
    # "overflow encountered in matmul" on the way to its (right) verdict.
    img = MSGS["img"][0]
    view = M.replace(img.views[0], T_CB=[1e200, 0, 0, 0, 1, 0, 0, 0, 1])
    raw = M.encode(M.replace(img, views=[view]))
    with np.errstate(all="raise"), pytest.raises(M.MessageError, match=r"views\.0\.T_CB: not a rotation matrix"):
        M.decode("img", raw)


@pytest.mark.parametrize(("kind", "field"), [("full_est", "P"), ("est", "P_pose")])
def test_a_covariance_whose_asymmetry_overflows_is_not_symmetric_without_a_warning(kind, field):
    # Found writing the fuzz targets: entries ±1e308 made A − Aᵀ overflow ("overflow encountered in subtract").
    A = F.array(getattr(MSGS[kind][0], field)).copy()
    A.reshape(-1, A.shape[-1])[0, 1], A.reshape(-1, A.shape[-1])[1, 0] = 1e308, -1e308
    raw = M.encode(M.replace(MSGS[kind][0], **{field: F.matrix(A)}))
    with np.errstate(all="raise"), pytest.raises(M.MessageError, match=f"{field}: not symmetric"):
        F.receive(kind, raw)


def test_a_damaged_mcap_time_is_not_a_bus_time(tmp_path):
    # fuzz_mcap's finding: a log or publish time ≥ 2^63 (MCAP times are uint64) was an
    # OverflowError building the int64 bus-latency arrays.
    w = CheckpointWriter(tmp_path / "r.mcap")
    cid = w.channel("swarm/fz/truth", w.schema("swarm.v1.Truth", "protobuf", b""), "protobuf")
    for k in range(3):
        w.add(cid, M.encode(M.replace(TRUTH, k=k)), 1000 + k, 900 + k)
    w.add(cid, M.encode(M.replace(TRUTH, k=1, t_s=1.5)), 2**64 - 1, 2**63)
    w.close(finalize=False)
    rec = load_recording(tmp_path / "r.mcap", 3, None)
    assert rec.bus is not None and rec.bus.times is not None and len(rec.bus.times.k) == 3 and rec.bus.latency_ms()["world"]["n"] == 3


def test_a_recording_that_breaks_the_indexed_reader_midway_reads_each_message_once(tmp_path):
    """A message record naming a channel that does not exist, partway through a checkpoint
    recording: the indexed reader fails there, and the record-by-record reader that takes
    over read the messages before it a second time (a checkpoint of 29 messages read as 56,
    counted again by recover and load_recording; found by the MCAP fuzz harness)."""
    import struct
    from pathlib import Path

    seed = Path(__file__).resolve().parents[1] / "fuzz" / "corpus" / "mcap" / "checkpoint.mcap"
    data = seed.read_bytes()
    messages, i = [], 8  # past the magic: opcode (1 byte), length (u64), body
    while i + 9 <= len(data):
        op, length = data[i], struct.unpack_from("<Q", data, i + 1)[0]
        if op == 0x05:  # Message: channel id (u16) first
            messages.append(i)
        i += 9 + length
    clean = list(iter_messages(seed))
    assert len(messages) == len(clean) > 20
    for which in (4, len(messages) // 2, len(messages) - 1):
        bad = bytearray(data)
        struct.pack_into("<H", bad, messages[which] + 9, 777)
        p = tmp_path / f"bad-{which}.mcap"
        p.write_bytes(bytes(bad))
        got = [(t, d, lt, pt) for t, _s, d, lt, pt in iter_messages(p)]
        assert len(got) == len(set(got)) == len(clean) - 1, (which, len(got), len(set(got)))
