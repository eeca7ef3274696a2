"""One receive path: every reader of the bus opens a sample with
:func:`swarmrt.bus.receive.receive`, and that function does what the roles need.

The structural half is an AST scan: no module of the project outside the receive module
and the codec calls ``decode``, ``validate`` or ``check_key`` of :mod:`swarmrt.bus.messages`
itself (the fuzz campaigns once exercised a copy of the receiver that had drifted from the
roles': it knew nothing of estimates with an ``ids`` list nor of shallow ``batches``)."""

import ast
from pathlib import Path

import pytest

from swarmrt.bus import messages as M
from swarmrt.bus.convert import estimate_msg
from swarmrt.bus.receive import receive

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("swarmcore", "swarmvision", "swarmrt", "world_sim", "sat_agent", "selector", "swarm", "fuzz", "scripts")
FORBIDDEN = {"decode", "validate", "check_key"}

# Modules that may call them, each for a reason that is not opening a bus sample.
# The modules that define them (decode validates) and re-export them: not scanned.
CODEC = {"swarmrt.bus.messages": "swarmrt/bus/messages.py", "swarmrt.bus.codec": "swarmrt/bus/codec.py",
         "swarmrt.bus.validation": "swarmrt/bus/validation.py", "swarmrt.bus.keys": "swarmrt/bus/keys.py"}
ALLOWED = {
    "swarmrt/bus/receive.py": "the receive path itself",
    # Recordings read from disk after the recorder opened every sample with receive(): the
    # reader checks each against the swarm size it infers from the truth messages (a size
    # the recorder did not know), and skips what does not fit.
    "swarm/record/recording.py": "recordings read from disk (already received by the recorder)",
    # The same: two campaigns' recordings compared message by message (make soak-twice).
    "scripts/twice_diff.py": "recordings read from disk (already received by the recorder)",
    # The codec's benchmark measures decode itself, on payloads it encoded.
    "swarm/bench/bus.py": "codec benchmark",
    # A fault command the CLI built, validated before it is sent (an encoder's check).
    "swarm/supervise/faults.py": "validates an outgoing command",
}


def _calls(path: Path) -> list[tuple[int, str]]:
    """Calls of the codec's decode/validate/check_key in one file, however imported."""
    tree = ast.parse(path.read_text(), str(path))
    names: dict[str, str] = {}  # local name -> the codec function it is
    modules: set[str] = set()  # local names of the swarmrt.bus.messages module
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module in CODEC:
            for a in node.names:
                if a.name in FORBIDDEN:
                    names[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom) and node.module == "swarmrt.bus":
            modules.update(a.asname or a.name for a in node.names if f"swarmrt.bus.{a.name}" in CODEC)
        elif isinstance(node, ast.Import):
            modules.update(a.asname for a in node.names if a.name in CODEC and a.asname)
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id in names:
            out.append((node.lineno, names[f.id]))
        elif isinstance(f, ast.Attribute) and f.attr in FORBIDDEN and (
                (isinstance(f.value, ast.Name) and f.value.id in modules) or ast.unparse(f.value) in CODEC):
            out.append((node.lineno, f.attr))
    return out


def _sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py") if "/v1/" not in str(p))


def test_no_module_outside_the_receive_path_decodes_a_sample_itself():
    offenders = []
    for p in _sources():
        rel = str(p.relative_to(ROOT))
        if rel in ALLOWED or rel in CODEC.values():
            continue
        offenders += [f"{rel}:{line}: {fn}()" for line, fn in _calls(p)]
    assert not offenders, "open bus samples with swarmrt.bus.receive.receive, not by hand:\n" + "\n".join(offenders)


def test_the_allow_list_is_not_stale():
    # Every exemption is still needed (a module that stopped calling them leaves the list).
    for rel in ALLOWED:
        assert _calls(ROOT / rel), f"{rel} no longer calls decode/validate/check_key: remove it from ALLOWED"


def test_the_scan_sees_every_way_of_calling_the_codec(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("from swarmrt.bus.messages import decode as d, check_key\nfrom swarmrt.bus import messages as M\n"
                 "import swarmrt.bus.messages\nfrom swarmrt.bus.validation import validate\nfrom swarmrt.bus import codec\n"
                 "def f(x):\n    d('clock', x)\n    check_key('k', 'clock', None, x)\n    M.validate(x)\n"
                 "    swarmrt.bus.messages.decode('clock', x)\n    x.decode()\n    validate(x)\n    codec.decode('clock', x)\n")
    assert _calls(p) == [(7, "decode"), (8, "check_key"), (9, "validate"), (10, "decode"), (12, "validate"), (13, "decode")]


def test_fuzz_targets_call_the_receive_function_itself():
    from fuzz import targets as F

    assert F.bus_receive is receive


# -- what the function does ------------------------------------------------------------------
RUN = "rp"
N = 4


def _est(n_rows: int, own: int = 2, ids=None, run: str = RUN, sender: str | None = None) -> bytes:
    import numpy as np

    from fuzz.targets import _estimate

    msg = estimate_msg(_estimate(np.random.default_rng(1), n_rows), run=run, sender=sender or f"agent-{own}", own=own)
    if ids is not None:
        msg.ids[:] = ids
    return M.encode(msg)


def test_a_valid_estimate_is_received_with_its_kind_and_satellite():
    r = receive(f"swarm/{RUN}/est/2", _est(N), RUN, n_sats=N)
    assert (r.kind, r.sat, r.msg.own, len(r.msg.q_BI)) == ("est", 2, 2, 4 * N)


def test_an_estimate_with_an_ids_list_has_one_row_per_listed_satellite():
    r = receive(f"swarm/{RUN}/est/2", _est(2, own=2, ids=[1, 2]), RUN, n_sats=N)
    assert list(r.msg.ids) == [1, 2]
    with pytest.raises(M.MessageError, match="ids: 3 satellites for 2 rows"):
        receive(f"swarm/{RUN}/est/2", _est(2, own=2, ids=[1, 2, 3]), RUN, n_sats=N)
    with pytest.raises(M.MessageError, match=r"an estimate of 2 satellites \(this swarm has 4\)"):
        receive(f"swarm/{RUN}/est/1", _est(2, own=1), RUN, n_sats=N)  # no ids: it must hold all N


@pytest.mark.parametrize("key, payload_run, says", [
    ("swarm/other/est/2", RUN, "run id 'other' is not this swarm's"),
    (f"swarm/{RUN}/est/2", "other", "message run id 'other'"),
    (f"swarm/{RUN}/est/7", RUN, "unknown satellite 7"),
    (f"swarm/{RUN}/bogus", RUN, "unexpected key"),
])
def test_the_key_and_run_are_checked_and_named(key, payload_run, says):
    with pytest.raises(M.MessageError, match=says):
        receive(key, _est(N, run=payload_run), RUN, n_sats=N)


def test_the_key_is_checked_against_the_content():
    with pytest.raises(M.KeyMismatch, match="key says satellite 3, message own says 2"):
        receive(f"swarm/{RUN}/est/3", _est(N), RUN, n_sats=N)
    with pytest.raises(M.KeyMismatch, match="may not publish"):
        receive(f"swarm/{RUN}/est/2", _est(N, sender="world"), RUN, n_sats=N)


def test_the_expected_kind_and_deletes():
    with pytest.raises(M.MessageError, match="where a full_est message was expected"):
        receive(f"swarm/{RUN}/est/2", _est(N), RUN, n_sats=N, expect="full_est")
    with pytest.raises(M.MessageError, match="unexpected delete"):
        receive(f"swarm/{RUN}/est/2", b"", RUN, delete=True)
    gone = receive(f"swarm/{RUN}/alive/agent/3", None, RUN, delete=True)
    assert (gone.kind, gone.sat, gone.role, gone.alive, gone.msg) == ("alive", 3, "agent", False, None)


def test_shallow_batches_leave_the_estimator_messages_to_the_agent():
    # One peer's estimator message is unsound: the full reading (the recorder's) refuses the
    # whole message, the shallow one (an agent's) takes it and the agent refuses that one
    # message when its estimator reads it (check_estimator_message).
    import numpy as np

    from fuzz.targets import seeds

    valid = next(data for name, data in seeds()["msg_batches"] if name.startswith("valid"))
    msg = M.StepBatches.FromString(valid)
    good = M.CiState(q_BI=[0, 0, 0, 1.0], omega_BI_B_rad_s=[0, 0, 0.0], r_H_m=[1, 2, 3.0], v_H_m_s=[0, 0, 0.0],
                     P_pose=M.Matrix(shape=[6, 6], data=np.eye(6).ravel().tolist()))
    for _ in msg.observers:
        msg.estimators.add(kind="ci", version=1, ci=good)
    msg.estimators[0].ci.P_pose.data[0] = float("nan")
    bad, key = M.encode(msg), f"swarm/{msg.run}/batches"
    receive(key, M.encode(M.replace(msg, estimators=[])), msg.run, n_sats=3)  # sound without them
    with pytest.raises(M.MessageError, match=r"estimators\[0\].*P_pose: not finite"):
        receive(key, bad, msg.run, n_sats=3)
    r = receive(key, bad, msg.run, n_sats=3, shallow={"batches", "est"})
    with pytest.raises(M.MessageError, match="P_pose: not finite"):
        M.check_estimator_message(r.msg.estimators[0], int(r.msg.observers[0]), 3)
    M.check_estimator_message(r.msg.estimators[1], int(r.msg.observers[1]), 3)
