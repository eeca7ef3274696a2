"""Property tests (hypothesis) of everything that reads input from outside: every bus message
kind's decoder, validator and the conversions a receiver applies after them, the scenario
loader, the credential and keys loaders, the MCAP reader, load_recording and recover.

The property: only the documented error escapes (MessageError, ScenarioError, SystemExit
naming the file, RecordingError; recover none), it says what is wrong, and every input
takes bounded time (hypothesis's deadline). Where an oracle exists (a quaternion's norm, a
covariance's symmetry and Cholesky, the run and sender a key allows, the records a
truncated file still holds whole), the verdict is checked against it too.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import struct
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from fuzz import targets as F
from swarm.record.mcaplog import iter_messages, recover
from swarm.record.recording import RecordingError, load_recording
from swarmcore.scenario import Scenario
from swarmrt.bus import messages as M
from swarmrt.bus.convert import array
from swarmrt.scenario_files import ScenarioError, load_scenario
from swarmrt.security import Credential, load_agent_passwords, load_credential, load_router_keys

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflowing cast, an invalid value: findings too

KINDS = F.MESSAGE_KINDS
SEEDS = F.seed_messages()
SEED_BYTES = {k: [M.encode(m) for m in v] for k, v in SEEDS.items()}

# Modest budgets: the whole file runs in well under a minute; the slow variant at the end
# runs the message properties with many more examples.
# The deadline bounds each input's time, with room for a loaded 2-core machine; the compiled
# batch checks are loaded first (numba's import would otherwise land in one example's time).
M.prepare("meas")
FAST = settings(max_examples=25, deadline=timedelta(seconds=5), suppress_health_check=[HealthCheck.too_slow])
FILES = settings(max_examples=20, deadline=timedelta(seconds=5),
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _only_message_errors(kind: str, payload: bytes) -> None:
    """The receiver's and the recorder's whole path: nothing but MessageError."""
    F.TARGETS[f"msg_{kind}"](payload)


# -- bus messages: bytes ----------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@FAST
@given(data=st.binary(max_size=600))
def test_arbitrary_bytes_are_a_message_or_a_message_error(kind, data):
    _only_message_errors(kind, data)


@pytest.mark.parametrize("kind", KINDS)
@FAST
@given(st.data())
def test_truncated_and_bit_flipped_encodings(kind, data):
    raw = bytearray(data.draw(st.sampled_from(SEED_BYTES[kind])))
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    for _ in range(data.draw(st.integers(0, 4 if len(raw) else 0))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] ^= 1 << data.draw(st.integers(0, 7))
    _only_message_errors(kind, bytes(raw))


# -- bus messages: valid structure, hostile values ----------------------------------------------
_FLOATS = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 5e-324, 1.0, 2.0, -1.0]),
    st.floats(allow_nan=True, allow_infinity=True),
)
_U64 = st.one_of(st.sampled_from([0, 1, 2, 3, 5, 6, 7, 200, M.MAX_SAT_ID, M.MAX_SAT_ID + 1, 2**31 - 1, 2**32 - 1]),
                 st.integers(0, 2**32 - 1))
_I64 = st.one_of(_U64, st.sampled_from([-1, -2**31, -2**63]), st.integers(-2**63, 2**63 - 1))
_TEXT = st.one_of(st.sampled_from(["", "world", "agent-1", "agent-2", "cli", "fz", "fz ", "x" * 65, "x" * 300, "posterior",
                                   "prior", "camera", "done", "on", "delay 100ms", "lockstep"]), st.text(max_size=80))

_SCALAR = {  # protobuf FieldDescriptor.TYPE_* → values
    1: _FLOATS, 2: _FLOATS,  # double, float
    3: _I64, 18: _I64, 5: _I64.map(lambda v: max(-2**31, min(v, 2**31 - 1))), 17: _I64.map(lambda v: max(-2**31, min(v, 2**31 - 1))),
    4: _U64, 13: _U64,  # uint64, uint32
    8: st.booleans(), 9: _TEXT, 12: st.binary(max_size=64),
}


def _value(f, draw):
    return draw(_SCALAR[f.type])


def _hostile(msg, draw, depth: int = 0) -> None:
    """Set one field somewhere in ``msg`` (a random path through its sub-messages) to a
    hostile value of the field's type: NaN, infinities, huge and negative numbers, ids out of
    range, wrong lengths of arrays and shapes, odd strings."""
    fields = [f for f in msg.DESCRIPTOR.fields if depth or f.number > 2]  # keep schema_version and run most of the time
    if depth == 0 and draw(st.integers(0, 9)) == 0:
        fields = list(msg.DESCRIPTOR.fields)
    f = draw(st.sampled_from(fields))
    if f.message_type is not None:
        if f.is_repeated:
            items = getattr(msg, f.name)
            if len(items) and draw(st.booleans()):
                _hostile(items[draw(st.integers(0, len(items) - 1))], draw, depth + 1)
            elif draw(st.booleans()):
                items.add()  # one more, empty: every field of it at its zero value
            elif len(items):
                del items[draw(st.integers(0, len(items) - 1))]
        else:
            getattr(msg, f.name).SetInParent()
            if f.message_type.name == "Matrix" and draw(st.booleans()):
                m = getattr(msg, f.name)
                m.ClearField("shape")
                m.shape.extend(draw(st.lists(_U64, max_size=4)))
                if draw(st.booleans()):
                    m.ClearField("data")
                    m.data.extend(draw(st.lists(_FLOATS, max_size=40)))
            else:
                _hostile(getattr(msg, f.name), draw, depth + 1)
    elif f.is_repeated:
        vals = getattr(msg, f.name)
        how = draw(st.integers(0, 3))
        if how == 0 and len(vals):  # one value changed
            i = draw(st.integers(0, len(vals) - 1))
            vals[i] = _value(f, draw)
        elif how == 1 and len(vals):  # shorter
            del vals[draw(st.integers(0, len(vals) - 1)):]
        elif how == 2:  # longer
            vals.extend(draw(st.lists(_SCALAR[f.type], max_size=8)))
        else:  # anything
            msg.ClearField(f.name)
            vals.extend(draw(st.lists(_SCALAR[f.type], max_size=12)))
    else:
        setattr(msg, f.name, _value(f, draw))


@pytest.mark.parametrize("kind", KINDS)
@FAST
@given(st.data())
def test_valid_structure_hostile_values(kind, data):
    _hostile_values_case(kind, data)


def _hostile_values_case(kind, data):
    msg = type(SEEDS[kind][0])()
    msg.CopyFrom(data.draw(st.sampled_from(SEEDS[kind])))
    for _ in range(data.draw(st.integers(1, 3))):
        _hostile(msg, data.draw)
    try:  # the validator on the message itself (as a sender would check what it built)
        M.validate(msg, kind, n_sats=F.N_SATS)
    except M.MessageError as exc:
        assert str(exc).startswith(f"invalid {kind} message: ")
    else:
        M.forget_arrays(msg)
    _only_message_errors(kind, msg.SerializeToString())


# Where each kind keeps quaternions, and covariances as (field, block size).
_QUATS = {"sensors": "q_BI_star", "meas": "q_BjBi", "batches": "q_BjBi", "est": "q_BI", "full_est": "q_BI", "truth": "q_BI"}
_COVS = {"meas": ("R_Bi", 6), "batches": ("R_Bi", 6), "est": ("P_pose", 6), "full_est": ("P", 36)}


@pytest.mark.parametrize("kind", sorted(_QUATS))
@FAST
@given(scale=st.one_of(st.floats(0.5, 1.5), st.floats(1 - 1e-5, 1 + 1e-5), st.sampled_from([0.0, -1.0, 1 + 2e-6, 1 - 2e-6])),
       which=st.integers(0, 100))
def test_non_unit_quaternions_are_refused_exactly_when_not_unit(kind, scale, which):
    msg = SEEDS[kind][0]
    f = _QUATS[kind]
    q = np.asarray(getattr(msg, f), dtype=float).reshape(-1, 4)
    r = which % len(q)
    q[r] *= scale
    bad = abs(float(q[r] @ q[r]) - 1.0) > 2 * M.QUAT_TOL
    raw = M.encode(M.replace(msg, **{f: q.ravel().tolist()}))
    if bad:
        with pytest.raises(M.MessageError, match="unit quaternion"):
            F.receive(kind, raw)
    else:
        F.receive(kind, raw)


def _spd_verdict(A: np.ndarray) -> str | None:
    """The oracle: what the decoder must say of a stack of covariances."""
    scale = np.abs(A).max(axis=(1, 2))
    if not (np.abs(A - A.transpose(0, 2, 1)).max(axis=(1, 2)) <= M.SYM_TOL * scale).all():
        return "not symmetric"
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return "not positive-definite"
    return None


@pytest.mark.parametrize("kind", sorted(_COVS))
@FAST
@given(st.data())
def test_asymmetric_and_indefinite_covariances_are_refused(kind, data):
    msg = SEEDS[kind][0]
    f, b = _COVS[kind]
    A = array(getattr(msg, f)).reshape(-1, b, b).copy()
    k = data.draw(st.integers(0, len(A) - 1))
    i, j = data.draw(st.integers(0, b - 1)), data.draw(st.integers(0, b - 1))
    how = data.draw(st.sampled_from(["asym", "neg-diag", "rank-1", "sym-pert", "tiny-asym"]))
    if how == "asym":
        A[k, i, j] += data.draw(st.floats(-10, 10))
    elif how == "tiny-asym":
        A[k, i, j] *= 1 + data.draw(st.floats(-1e-8, 1e-8))
    elif how == "neg-diag":
        A[k, i, i] = -data.draw(st.floats(0, 10))
    elif how == "rank-1":
        v = np.asarray(data.draw(st.lists(st.floats(-3, 3), min_size=b, max_size=b)))
        A[k] = np.outer(v, v)
    else:
        d = data.draw(st.floats(-10, 10))
        A[k, i, j] += d
        if i != j:
            A[k, j, i] += d
    want = _spd_verdict(A)
    raw = M.encode(M.replace(msg, **{f: M.Matrix(shape=list(getattr(msg, f).shape), data=A.ravel().tolist())}))
    if want is None:
        F.receive(kind, raw)
    else:
        with pytest.raises(M.MessageError, match=want):
            F.receive(kind, raw)


_MAY_SEND = {"fault": {"cli", "world"}, "select": {"selector", "world"}}  # commands; the selection (or the world's fallback)


@pytest.mark.parametrize("kind", KINDS)
@FAST
@given(run=st.one_of(st.just(F.RUN), _TEXT.filter(lambda s: 1 <= len(s) <= 64 and re.fullmatch(r"[A-Za-z0-9_.-]+", s) is not None)),
       sender=st.one_of(st.sampled_from(["world", "selector", "cli", "agent-0", "agent-1", "agent-2", "agent-10", "supervisor"]), _TEXT))
def test_wrong_run_or_sender_for_the_key(kind, run, sender):
    msg = SEEDS[kind][0]
    raw = M.encode(M.replace(msg, run=run, sender=sender))
    if run == F.RUN and sender in _MAY_SEND.get(kind, {msg.sender}):
        F.receive(kind, raw)
        return
    with pytest.raises(M.MessageError) as exc:
        F.receive(kind, raw)
    if run == F.RUN and 1 <= len(sender) <= 64 and kind not in ("select", "fault"):
        assert isinstance(exc.value, M.KeyMismatch)  # another's sender on this key: counted as such


@FAST
@given(st.text(max_size=120))
def test_keys_are_parsed_or_refused(key):
    try:
        _run, kind, sat = M.parse_key(key)
    except M.MessageError as exc:
        assert "unexpected key" in str(exc)
        return
    assert kind in M.MODELS or kind == "alive"
    assert sat is None or sat >= 0


@FAST
@given(shape=st.lists(_U64, max_size=4), data=st.lists(st.floats(allow_nan=False), max_size=64))
@example(shape=[2**32 - 1, 2**32 - 1, 0], data=[])  # CI found it: numpy's "cannot reshape", not "too big"
@example(shape=[0, 2**31, 2**31], data=[])
def test_matrix_conversion(shape, data):
    m = M.Matrix(shape=shape, data=data)
    try:
        a = array(m)
    except M.MessageError as exc:
        assert ("needs" in str(exc) and math.prod(shape) != len(data)) or "too big" in str(exc)
    else:
        assert a.shape == tuple(shape) and a.size == len(data)


# -- scenario files ----------------------------------------------------------------------------------
SHIPPED = sorted((Path(__file__).resolve().parents[1] / "scenarios").glob("*.yaml"))


def _load_text(tmp_path, text: bytes | str):
    p = tmp_path / "s.yaml"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    try:
        return load_scenario(p), p
    except ScenarioError as exc:
        assert str(exc).startswith(f"{p}:"), str(exc)
        return exc, p


@FILES
@given(text=st.one_of(st.binary(max_size=400), st.text(max_size=400)))
def test_any_text_is_a_scenario_or_a_scenario_error(tmp_path, text):
    _load_text(tmp_path, text)


_YAMLISH = st.recursive(
    st.one_of(st.none(), st.booleans(), _FLOATS, _I64, _TEXT),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(_TEXT, inner, max_size=4)),
    max_leaves=12,
)


def _paths(d, prefix=()):
    for k, v in d.items():
        yield (*prefix, k)
        if isinstance(v, dict):
            yield from _paths(v, (*prefix, k))


_FIELD_LINE = re.compile(r"^  (?:\(top level\): )?([A-Za-z_]\w*)")


@FILES
@given(st.data())
def test_a_hostile_field_value_is_a_scenario_error_naming_a_field(tmp_path, data):
    base = yaml.safe_load(data.draw(st.sampled_from(SHIPPED)).read_text()) or {}
    full = Scenario.model_validate(base).model_dump(mode="json", by_alias=True)
    path = data.draw(st.sampled_from(sorted(_paths(full))))
    node = base
    for part in path[:-1]:
        node = node.setdefault(part, {}) if isinstance(node.get(part), dict | None) else node[part]
    node[path[-1]] = data.draw(_YAMLISH)
    got, _p = _load_text(tmp_path, yaml.safe_dump(base))
    if isinstance(got, ScenarioError):
        lines = str(got).splitlines()
        if len(lines) > 1:  # a validation error: each line names a field of the scenario
            names = [m[1] for line in lines[1:] if (m := _FIELD_LINE.match(line))]
            assert names and all(n in Scenario.model_fields for n in names), str(got)
    else:
        assert got.steps >= 1


# -- credentials and keys -------------------------------------------------------------------------------
_JSONISH = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(allow_nan=False), st.integers(), st.text(max_size=20)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=3)),
    max_leaves=8,
)
_CRED_KEY = st.sampled_from(["user", "password", "ca"])


def _refused(fn, path, prefix):
    try:
        return fn(path)
    except SystemExit as exc:
        assert isinstance(exc.code, str) and exc.code.startswith(f"{prefix} {path}:"), exc.code
        return None


@FILES
@given(raw=st.one_of(st.binary(max_size=200), _JSONISH.map(lambda v: json.dumps(v).encode()),
                     st.dictionaries(_CRED_KEY, st.one_of(_JSONISH, st.sampled_from(["world", "agent-3", "ca.pem", ""])))
                     .map(lambda v: json.dumps(v).encode())))
def test_credentials_load_or_fail_naming_the_file(tmp_path, raw):
    p = tmp_path / "cred.json"
    p.write_bytes(raw)
    cred = _refused(load_credential, p, "credential")
    if cred is not None:
        d = json.loads(raw)
        assert isinstance(cred, Credential) and cred.user == d["user"] and cred.password == d["password"]
    _refused(load_agent_passwords, p, "agent passwords")


@FILES
@given(ids=st.dictionaries(st.integers(0, M.MAX_SAT_ID), st.text(max_size=30), max_size=20))
def test_agent_passwords_round_trip(tmp_path, ids):
    p = tmp_path / "agents.json"
    p.write_text(json.dumps({str(k): v for k, v in ids.items()}))
    assert load_agent_passwords(p) == ids


@FILES
@given(router=st.one_of(st.binary(max_size=100), _JSONISH.map(lambda v: json.dumps(v).encode()),
                        st.fixed_dictionaries({"passwords": st.one_of(st.just("passwords"), _JSONISH)},
                                              optional={"certificate": _JSONISH, "private_key": _JSONISH}).map(lambda v: json.dumps(v).encode())),
       dictionary=st.binary(max_size=100))
def test_router_keys_load_or_fail_naming_the_file(tmp_path, router, dictionary):
    (tmp_path / "router.json").write_bytes(router)
    (tmp_path / "passwords").write_bytes(dictionary)
    try:
        meta, path, users = load_router_keys(tmp_path)
    except SystemExit as exc:
        assert isinstance(exc.code, str) and exc.code.startswith("router"), exc.code
    else:
        assert isinstance(meta["passwords"], str) and path.is_file() and isinstance(users, set)


# -- recordings --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    return {fin: F.seed_mcap(d / f"{fin}.mcap", fin).read_bytes() for fin in (False, True)}


def _message_ends(raw: bytes) -> list[int]:
    """The end offset of every Message record (opcode 0x05) of an unchunked MCAP, in order."""
    out, pos = [], 8
    while pos + 9 <= len(raw):
        op = raw[pos]
        (length,) = struct.unpack_from("<Q", raw, pos + 1)
        end = pos + 9 + length
        if op == 0x05:
            out.append(end)
        if op == 0x0F and length == 0:  # the live tail's empty private record (mcaplog.py): the DataEnd after it ends the data
            pass
        if op == 0x0E:  # DataEnd
            break
        pos = end
    return out


def _read_mcap(tmp_path, raw: bytes) -> int:
    """Every reader on the bytes; returns what recover salvaged."""
    p = tmp_path / "r.mcap"
    p.write_bytes(raw)
    got = list(iter_messages(p))
    for n in (F.N_SATS, None):
        with contextlib.suppress(RecordingError):
            load_recording(p, n, None)
    out = tmp_path / "out.mcap"
    count = recover(p, out)
    back = list(iter_messages(out))
    assert len(back) == count == len(got)
    assert [m[2] for m in back] == [m[2] for m in got]
    return count


@FILES
@given(st.data())
def test_truncated_recordings_keep_every_whole_message(tmp_path, recordings, data):
    raw = recordings[False]  # as a killed recorder leaves it: records one after the other
    cut = data.draw(st.integers(0, len(raw)))
    whole = sum(1 for end in _message_ends(raw) if end <= cut)
    count = _read_mcap(tmp_path, raw[:cut])
    # recover salvages at least every message record that the cut left whole (the streaming
    # reader keeps them), and never more than were there
    assert whole <= count <= len(_message_ends(raw)) or (cut == len(raw) and count == len(_message_ends(raw)))


@FILES
@given(st.data())
def test_corrupted_recordings_are_read_refused_or_salvaged(tmp_path, recordings, data):
    raw = bytearray(recordings[data.draw(st.booleans())])
    how = data.draw(st.sampled_from(["flip", "garbage", "splice", "zero"]))
    if how == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
    elif how == "garbage":
        raw = bytearray(b"\x89MCAP0\r\n" + data.draw(st.binary(max_size=400)))
    elif how == "splice":
        i = data.draw(st.integers(0, len(raw)))
        raw[i:i] = data.draw(st.binary(min_size=1, max_size=64))
    else:
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i : i + 8] = bytes(8)
    _read_mcap(tmp_path, bytes(raw))


# -- longer runs (CI runs them too: `slow`) ---------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=300, deadline=timedelta(seconds=10), suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_valid_structure_hostile_values_long(kind, data):
    _hostile_values_case(kind, data)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=300, deadline=timedelta(seconds=10), suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=2000))
def test_arbitrary_bytes_long(kind, data):
    _only_message_errors(kind, data)
