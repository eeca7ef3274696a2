"""What the fuzzers feed hostile bytes to, and the valid inputs they start from.

One target per kind of input that crosses a trust boundary: a bus message (per kind: the
receiver's whole path, :func:`receive`, which is :func:`swarmrt.bus.receive.receive`, the
function every role, the recorder and the live view open samples with, followed by the
role's conversions), a scenario file, a credential or keys file, an
MCAP recording. Each target takes bytes and returns normally when the input was used or
refused with the error its loader documents; any other exception is a finding. The same
functions serve the atheris harnesses (``fuzz/fuzz_*.py``), the corpus replay in CI
(``tests/test_fuzz_corpus.py``) and the seed corpus (:func:`seeds`, written by
``python scripts/fuzz.py --seeds``).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from swarmcore import quat
from swarmcore.links import LinkCounters
from swarmcore.mekf import RelativeMeasurements, SwarmEstimate
from swarmcore.scenario import Scenario
from swarmcore.world import initial_truth
from swarmrt.bus import messages as M
from swarmrt.bus.convert import (
    absolute_from_sensors,
    array,
    batch_msg,
    detections_from_msg,
    estimate_arrays,
    estimate_from_full,
    estimate_msg,
    full_estimate_msg,
    gyro_from_sensors,
    matrix,
    observation_from_images,
    pairs_from_select,
    relative_from_batches,
    relative_from_step,
    select_msg,
    sensors_msg,
    step_batches_msg,
    truth_msg,
)
from swarmrt.bus.receive import receive as bus_receive

__all__ = ["RUN", "N_SATS", "KEYS", "MESSAGE_KINDS", "SHALLOW_READERS", "TARGETS", "receive", "seeds", "target"]

RUN = "fz"
N_SATS = 3  # the swarm a fuzzed receiver belongs to
ME = 1  # the receiving agent's own satellite
#: The key each kind arrives on at agent ME of a swarm of N_SATS (meas: a peer's batch).
KEYS = {
    "clock": f"swarm/{RUN}/clock",
    "sensors": f"swarm/{RUN}/sat/{ME}/sensors",
    "cam": f"swarm/{RUN}/sat/{ME}/cam",
    "img": f"swarm/{RUN}/sat/{ME}/img",
    "meas": f"swarm/{RUN}/meas/2",
    "batches": f"swarm/{RUN}/batches",
    "est": f"swarm/{RUN}/est/2",
    "full_est": f"swarm/{RUN}/cov/2",
    "select": f"swarm/{RUN}/select",
    "fault": f"swarm/{RUN}/fault",
    "health": f"swarm/{RUN}/health/2",
    "truth": f"swarm/{RUN}/truth",
    "claim": f"swarm/{RUN}/claim/tok3n",
    "rx": f"swarm/{RUN}/rx/{ME}",
    "links": f"swarm/{RUN}/links",
    "rejoin": f"swarm/{RUN}/rejoin/{ME}",
    "recorded": f"swarm/{RUN}/recorded",
}
MESSAGE_KINDS = tuple(sorted(M.MODELS))


# -- the receiver's path -------------------------------------------------------------------
#: The kinds each role reads shallowly (its Node.subscribe(..., shallow=True)): the world and
#: the selector read estimates for their header; an agent on the ideal radio reads ``batches``
#: shallowly and checks each peer's estimator message as its estimator reads it.
SHALLOW_READERS = {"est": "world and selector", "batches": "agent (ideal radio)"}


def receive(kind: str, payload: bytes, key: str | None = None, n: int = N_SATS, convert: bool = True, shallow: bool = False):
    """What a node does with a sample (:func:`swarmrt.bus.receive.receive`, the function
    :meth:`swarmrt.node.Node._decode` calls), then what the receiving role does with the
    message (the conversions of :mod:`swarmrt.bus.convert`). ``shallow``: as a role that
    subscribed shallowly reads it (:data:`SHALLOW_READERS`). Returns the message, or raises
    :class:`~swarmrt.bus.messages.MessageError`."""
    key = KEYS[kind] if key is None else key
    run, k, _sat = M.parse_key(key)
    if k != kind:
        raise ValueError(f"key {key} is not a {kind} key")  # a harness mistake, never a message's
    msg = bus_receive(key, payload, run, n_sats=n, shallow=shallow).msg
    if shallow:
        _read_shallow(kind, msg, n)
    elif convert:
        _CONVERT.get(kind, _nothing)(msg, n)
    return msg


def _read_shallow(kind: str, msg, n: int) -> None:
    """What a shallow reader reads of the message: an estimate's header and scalars (nothing
    more to do); an agent's ``batches``: the batches in full, and each peer's estimator
    message checked as ``sat_agent.protocol`` checks it before its estimator reads it (a
    refused one is counted there, not an error of the sample)."""
    if kind == "batches":
        relative_from_step(msg, skip=ME)
        for o, e in zip(msg.observers, msg.estimators):
            with contextlib.suppress(M.MessageError):
                M.check_estimator_message(e, int(o), n)


def _nothing(msg, n: int) -> None:
    M.forget_arrays(msg)


def _sensors(msg, n):
    absolute_from_sensors(msg)
    gyro_from_sensors(msg)


def _est(msg, n):
    estimate_arrays(msg)
    array(msg.P_pose)
    array(msg.P_diag)


def _links(msg, n):
    LinkCounters(**{name: np.rint(array(getattr(msg, name))).astype(int) for name in LinkCounters.__dataclass_fields__})


_CONVERT: dict[str, Callable] = {
    "sensors": _sensors,
    "cam": lambda msg, n: detections_from_msg(msg, [True] * 5 + [False]),
    "meas": lambda msg, n: relative_from_batches([msg]),
    "batches": lambda msg, n: relative_from_step(msg, skip=ME),
    "rx": lambda msg, n: relative_from_batches([it.batch for it in msg.items]),
    "est": _est,
    "full_est": lambda msg, n: estimate_from_full(msg, n),
    "truth": lambda msg, n: estimate_arrays(msg),
    "select": lambda msg, n: pairs_from_select(msg),
    "links": _links,
    "img": lambda msg, n: observation_from_images(msg),
}


def message_target(kind: str) -> Callable[[bytes], None]:
    """Bytes on kind's key: the receiver's path (swarm of N_SATS) and the recorder's (any
    swarm: ids up to MAX_SAT_ID); only :class:`MessageError` may come out."""

    def run(data: bytes) -> None:
        with contextlib.suppress(M.MessageError):  # a role that reads this kind in full
            receive(kind, data)
        try:  # the recorder (and the live view): no swarm size, ids up to MAX_SAT_ID
            msg = bus_receive(KEYS[kind], data, RUN).msg
        except M.MessageError:
            pass
        else:
            M.forget_arrays(msg)
        if kind in SHALLOW_READERS:  # the world's and selector's reading of estimates, an agent's of batches
            with contextlib.suppress(M.MessageError):
                receive(kind, data, shallow=True)

    run.__name__ = f"message_{kind}"
    return run


# -- files ---------------------------------------------------------------------------------
SHM = "/dev/shm"  # a tmpfs on Linux (Docker gives each container one)


class _Scratch:
    """One private scratch folder per process for targets that read files: in memory
    (:data:`SHM`) where the machine has one. On a disk the targets waited for it: every
    execution rewrites a file in place, renames one over another and deletes one, and the
    disk's write-back of them stalled the next execution at random. The mcap target took
    4-23 ms an execution with its files on ext4, 3-4 ms in /dev/shm (the same machine, the
    same inputs, the same CPU time give or take 0.5 ms)."""

    _dir: Path | None = None

    @classmethod
    def path(cls, name: str) -> Path:
        if cls._dir is None:
            base = SHM if os.path.isdir(SHM) and os.access(SHM, os.W_OK) else tempfile.gettempdir()
            _sweep(Path(base))
            cls._dir = Path(tempfile.mkdtemp(prefix=f"swarm-fuzz-{os.getpid()}-", dir=base))
            atexit.register(shutil.rmtree, cls._dir, True)  # at a normal end (see _sweep)
        return cls._dir / name

    @classmethod
    def write(cls, name: str, data: bytes) -> Path:
        p = cls.path(name)
        p.write_bytes(data)
        return p


def _sweep(base: Path) -> None:
    """Remove the scratch folders of fuzzing processes that are gone. libFuzzer ends a
    harness with exit(), which runs none of Python's atexit handlers: each run (each job of
    ``-fork``, each restart of ``--keep-going``) left its folder behind, in memory in SHM."""
    for d in base.glob("swarm-fuzz-*-*"):
        try:
            os.kill(int(d.name.split("-")[2]), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
        except (ValueError, OSError):  # not one of ours, or a process of another user's: left alone
            pass


def scenario_target(data: bytes) -> None:
    """A scenario file: a Scenario (whose step count is a number) or a ScenarioError."""
    from swarmrt.scenario_files import ScenarioError, load_scenario

    p = _Scratch.write("scenario.yaml", data)
    try:
        sc = load_scenario(p)
    except ScenarioError as exc:
        if not str(exc).startswith(f"{p}:"):
            raise AssertionError(f"a scenario error that does not name the file: {exc}") from None
        return
    assert sc.steps >= 1


def credentials_target(data: bytes) -> None:
    """A credential file, an ``agents.json``, a keys directory's ``router.json`` and password
    dictionary: each is read or refused with SystemExit naming the file."""
    from swarmrt.security import load_agent_passwords, load_credential, load_router_keys

    for name, load in (("cred.json", load_credential), ("agents.json", load_agent_passwords)):
        p = _Scratch.write(name, data)
        try:
            load(p)
        except SystemExit as exc:
            _clear(exc, "credential " if load is load_credential else "agent passwords ")
    keys = _Scratch.path("keys")
    keys.mkdir(exist_ok=True)
    (keys / "router.json").write_bytes(data)
    (keys / "passwords").write_bytes(data)
    try:
        load_router_keys(keys)
    except SystemExit as exc:
        _clear(exc, "router")
    (keys / "router.json").unlink()  # the default router.json: the dictionary is `passwords`
    try:
        load_router_keys(keys)
    except SystemExit as exc:
        _clear(exc, "router")


def _clear(exc: SystemExit, prefix: str) -> None:
    """A loader's refusal is a sentence that says which file (``prefix`` + its path)."""
    if not isinstance(exc.code, str) or not exc.code.startswith(prefix):
        raise AssertionError(f"not a clear refusal (expected {prefix!r}...): {exc.code!r}") from None


def mcap_target(data: bytes) -> None:
    """A recording: read (every message), loaded into a run result or refused with
    RecordingError, and salvaged by ``recover`` (never an exception)."""
    from swarm.record.mcaplog import iter_messages, recover
    from swarm.record.recording import RecordingError, _shape, load_recording

    p = _Scratch.write("run.mcap", data)
    # The file read once, and both loads given what the reader yielded: the very messages
    # each would read from p itself (twice: its shape, then its contents), the same function
    # on the same bytes; reading them there too parsed every input five times.
    messages = list(iter_messages(p))
    rec = None
    with contextlib.suppress(RecordingError):
        rec = load_recording(p, N_SATS, None, messages=messages)
    # load_recording(p, None, None) loads the shape _shape(p, None) finds: when that is the
    # shape just loaded, it would do the same work again to the same end.
    with contextlib.suppress(RecordingError):
        if rec is None or _shape(p, None, messages) != (rec.n, rec.K):
            load_recording(p, None, None, messages=messages)
    out = _Scratch.path("run.recovered.mcap")
    count = recover(p, out)
    assert count == len(messages), f"recover salvaged {count} messages of the {len(messages)} the reader reads"
    assert sum(1 for _ in iter_messages(out)) == count, "recover wrote a file that does not read back"
    os.unlink(out)


#: Every harness's target: ``msg_<kind>`` per message kind, ``scenario``, ``credentials``, ``mcap``.
TARGETS: dict[str, Callable[[bytes], None]] = {
    **{f"msg_{kind}": message_target(kind) for kind in MESSAGE_KINDS},
    "scenario": scenario_target,
    "credentials": credentials_target,
    "mcap": mcap_target,
}


def target(name: str) -> Callable[[bytes], None]:
    try:
        return TARGETS[name]
    except KeyError:
        raise ValueError(f"unknown fuzz target {name!r} (one of {', '.join(TARGETS)})") from None


# -- seeds: valid inputs, made by the project's own builders ----------------------------------
def _estimate(rng, n: int = N_SATS) -> SwarmEstimate:
    A = rng.normal(size=(12 * n, 12 * n))
    P = A @ A.T + 12 * n * np.eye(12 * n)
    return SwarmEstimate(3, 3.0, quat.random_quaternion(rng, n), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                         rng.normal(size=(n, 3)), rng.normal(size=3), 0.5 * (P + P.T))


def _rel(rng, observer: int, targets) -> RelativeMeasurements:
    m = len(targets)
    return RelativeMeasurements(np.full(m, observer), np.asarray(targets), quat.random_quaternion(rng, m), rng.normal(size=(m, 3)),
                                np.stack([np.diag(rng.uniform(0.1, 1, 6)) for _ in range(m)]) if m else np.zeros((0, 6, 6)))


def seed_messages() -> dict[str, list]:
    """Valid messages of every kind, as agent ME of a swarm of N_SATS receives them on
    :data:`KEYS` (several per kind where the kind has forms: empty, full, optional fields)."""
    rng = np.random.default_rng(2026)
    H: dict[str, Any] = dict(run=RUN, k=3, t_s=3.0)  # the header fields every message has
    b0 = batch_msg(_rel(rng, 0, [1, 2]), np.array([0, 3]), run=RUN, sender="agent-0", k=3, t_s=3.0, observer=0)
    b2 = batch_msg(_rel(rng, 2, [0, 1]), np.array([1, 5]), run=RUN, sender="agent-2", k=3, t_s=3.0, observer=2)
    b2_empty = batch_msg(_rel(rng, 2, []), np.zeros(0, int), run=RUN, sender="agent-2", k=3, t_s=3.0, observer=2)
    for b in (b0, b2, b2_empty):
        b.schema_version = M.SCHEMA_VERSION
    abs_meas = type("Abs", (), {"q_BI": quat.random_quaternion(rng, 1)[0], "r_H": rng.normal(size=3)})()
    img_view = M.CameraView(camera=2, T_CB=[0, 1.0, 0, 0, 0, 1, 1, 0, 0], r_C_B_m=[0, 0.2, 0], width_px=5, height_px=3, fx_px=4.0,
                            fy_px=4.0, cx_px=2.0, cy_px=1.0, target=-1, images_mono8=[rng.integers(0, 256, (3, 5), dtype=np.uint8).tobytes()])
    stereo = M.CameraView(camera=8, T_CB=[1.0, 0, 0, 0, 1, 0, 0, 0, 1], r_C_B_m=[0, 0, 0], width_px=4, height_px=2, fx_px=9.0, fy_px=9.0,
                          cx_px=1.5, cy_px=0.5, target=2, baseline_m=0.5, images_mono8=[bytes(range(8)), bytes(8)])
    counters: dict[str, Any] = {f: matrix(np.arange(9.0).reshape(3, 3)) for f in M._LINK_COUNTERS}
    return {
        "clock": [M.Clock(**H, sender="world", live_agents=[0, 1, 2], mode="lockstep", malformed=2, recorder_waited_steps=1, recorder_waited_s=0.5),
                  M.Clock(**H, sender="world", live_agents=[], mode="free", done=True)],
        "sensors": [sensors_msg(run=RUN, k=3, t_s=3.0, sat=ME, gyro=rng.normal(size=3) * 1e-3, absm=abs_meas, sigma_star=2.9e-5, sigma_gps=0.01),
                    sensors_msg(run=RUN, k=0, t_s=0.0, sat=ME, gyro=None, absm=None, sigma_star=2.9e-5, sigma_gps=0.01)],
        "cam": [M.CameraOutput(**H, sender="world", sat=ME, detections=[M.Detection(target=2, camera=4, q_BjBi=[0, 0, 0.6, 0.8], r_ij_Bi_m=[0.1, 0.2, 9.9]),
                                                                        M.Detection(target=0, camera=5, q_BjBi=[0, 0, 0, 1.0], r_ij_Bi_m=[1, 0, 0])],
                               cameras_off=[3])],
        "img": [M.Images(**H, sender="world", sat=ME, targets=[0, 2], views=[img_view, stereo])],
        "meas": [b2, b2_empty],
        "batches": [step_batches_msg([b0, b2], run=RUN, k=3, t_s=3.0)],
        "est": [estimate_msg(_estimate(rng), run=RUN, sender="agent-2", own=2, nis=1.5, step_ms=2.0, batches_used=[0, 1],
                             batches_missing=[2]),
                estimate_msg(_estimate(rng), run=RUN, sender="agent-2", own=2, phase="prior")],
        "full_est": [full_estimate_msg(_estimate(rng), run=RUN, sender="agent-2", own=2)],
        "select": [select_msg([0, 2], [1, 0], **H, sender="selector", strategy="greedy", ref_agent=0, select_ms=1.5),
                   select_msg([], [], **H, sender="world", strategy="all", fallback=True)],
        "fault": [M.Fault(**H, sender="cli", action="camera", phase="command", target=1, camera=2, state="off"),
                  M.Fault(**H, sender="world", action="drop", phase="command", target=0, rate=0.5),
                  M.Fault(**H, sender="cli", action="netem", phase="command", target=2, netem="delay 100ms"),
                  M.Fault(**H, sender="world", action="restart-router", phase="command", down_s=2.0),
                  M.Fault(**H, sender="world", action="stall-agent", phase="command", target=1, down_s=3.5),
                  M.Fault(**H, sender="cli", action="link", phase="command", target=0, peer=2, delay_s=1.5, rate=0.25)],
        "recorded": [M.Recorded(**H, sender="recorder")],
        "health": [M.Health(**H, sender="agent-2", sat=2, camera_ok=[True] * 5 + [False], malformed=2, drop_rate=0.25, host="node-2")],
        "truth": [truth_msg(initial_truth(Scenario(n_sats=N_SATS, seed=2)), run=RUN, k=3)],
        "claim": [M.Claim(**H, sender="world", sat=2, token="tok3n", password="secret", running=True)],
        "rx": [M.Delivery(**H, sender="world", sat=ME, items=[M.Delivered(arrival_t_s=2.7, batch=b2), M.Delivered(arrival_t_s=2.9, batch=b0)])],
        "links": [M.LinkStats(**H, sender="world", **counters, queue_bytes=[0, 120, 4],
                              latencies=[M.Latency(sender=2, receiver=0, sent_k=2, latency_s=0.7)])],
        "rejoin": [M.RejoinFate(**H, sender="world", sat=ME, peer=2, bytes=12345, fate="delivered", arrival_t_s=3.4),
                   M.RejoinFate(**H, sender="world", sat=ME, peer=0, bytes=99, fate="lost")],
    }


def seed_mcap(path: Path, finalize: bool) -> Path:
    """A small recording of a 3-satellite run (3 steps: truth, estimates, batches, selection,
    a fault, links, a rejoin, health, clock, liveliness and a bus gap), as the recorder writes
    it: ``finalize`` chunked and compressed, else as a killed recorder leaves it."""
    from swarm.record.mcaplog import CheckpointWriter
    from swarmrt.bus.messages import BusGap, Liveliness, file_descriptor_set

    msgs = seed_messages()
    w = CheckpointWriter(path)
    chans: dict[str, int] = {}

    def put(topic: str, msg, t: int) -> None:
        if topic not in chans:
            cls = type(msg)
            chans[topic] = w.channel(topic, w.schema(cls.DESCRIPTOR.full_name, "protobuf", file_descriptor_set(cls)), "protobuf")
        w.add(chans[topic], M.encode(msg) if hasattr(msg, "schema_version") else msg.SerializeToString(), t, t - 1000)

    t = 1_000_000
    for k in range(3):
        tr = truth_msg(initial_truth(Scenario(n_sats=N_SATS, seed=2)), run=RUN, k=k)
        put(f"swarm/{RUN}/truth", tr, t)
        put(f"swarm/{RUN}/clock", M.replace(msgs["clock"][0], k=k), t + 1)
        for i in range(N_SATS):
            e = M.replace(msgs["est"][0], k=k, own=i, sender=f"agent-{i}")
            put(f"swarm/{RUN}/est/{i}", e, t + 2 + i)
        put(f"swarm/{RUN}/meas/2", M.replace(msgs["meas"][0], k=k), t + 10)
        put(f"swarm/{RUN}/select", M.replace(msgs["select"][0], k=k), t + 11)
        put(f"swarm/{RUN}/health/2", M.replace(msgs["health"][0], k=k), t + 12)
        t += 1_000_000
        w.flush()
    put(f"swarm/{RUN}/fault", M.replace(msgs["fault"][0], k=2), t)
    put(f"swarm/{RUN}/links", M.replace(msgs["links"][0], k=2), t + 1)
    put(f"swarm/{RUN}/rejoin/{ME}", M.replace(msgs["rejoin"][0], k=2), t + 2)
    put(f"swarm/{RUN}/alive", Liveliness(key=f"swarm/{RUN}/alive/agent/1", role="agent", id="1", alive=True), t + 3)
    put(f"swarm/{RUN}/_gap", BusGap(observer="recorder", down_unix_ns=t, up_unix_ns=t + 5, last_step_before=1, first_step_after=2), t + 4)
    w.close(finalize=finalize)
    return path


def seeds() -> dict[str, list[tuple[str, bytes]]]:
    """Every harness's seed inputs: ``{harness: [(file name, bytes), ...]}``."""
    out: dict[str, list[tuple[str, bytes]]] = {}
    for kind, msgs in seed_messages().items():
        out[f"msg_{kind}"] = [(f"valid-{i}", M.encode(m)) for i, m in enumerate(msgs)]
    root = Path(__file__).resolve().parents[1]
    out["scenario"] = [(p.name, p.read_bytes()) for p in sorted((root / "scenarios").glob("*.yaml"))]
    import json

    out["credentials"] = [
        ("credential", json.dumps({"user": "agent-3", "password": "pw"}).encode()),
        ("credential-tls", json.dumps({"user": "observer", "password": "pw", "ca": "ca.pem"}).encode()),
        ("agents", json.dumps({"0": "pw0", "1": "pw1"}).encode()),
        ("router", json.dumps({"passwords": "passwords", "n_sats": 3}).encode()),
        ("passwords", b"world:abc\nagent-0:def\n"),
    ]
    with tempfile.TemporaryDirectory() as d:
        out["mcap"] = [(f"{name}.mcap", seed_mcap(Path(d) / f"{name}.mcap", fin).read_bytes())
                       for name, fin in (("checkpoint", False), ("final", True))]
    return out
