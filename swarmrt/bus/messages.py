"""Every message on the bus and every key expression, in one place.

Messages are Protocol Buffers, schema version 1: ``proto/swarm/v1/*.proto`` is the single
source of truth (one file per message family; ``proto/README.md`` gives the conventions
and the evolution rules), and the classes here are the code generated from it
(``swarm/v1/*_pb2.py``, made by ``scripts/gen_proto.py``). Any language with a protobuf
code generator reads them; the recorder embeds the schemas in the MCAP file.

Fields 1–5 of every message are the header: ``schema_version``, ``run``, ``sender``,
``k`` (step), ``t_s`` (simulation time). Units and frames are in every field name. Arrays
are packed ``repeated double`` (per-satellite rows concatenated, row-major) and
covariances :class:`Matrix` values (``shape`` + ``data``); both are little-endian
float64 on the wire, so values round-trip bit for bit.

:func:`decode` checks what a schema cannot: the schema version, bounded payload size,
finite numbers, unit quaternions (``|‖q‖ − 1| ≤ QUAT_TOL``), symmetric positive-definite
covariances, array lengths that match their shapes, ids within ``MAX_SAT_ID``, allowed
values of the string enumerations. :func:`check_key` checks a message against the key it
came on (the satellite in the key, the sender). A failure raises :class:`MessageError`
naming the problem; the receiving process counts it, logs it and carries on.

Generated classes are built with keywords and read by attribute, as before
(``Clock(run=..., k=3)``, ``msg.k``); :func:`replace` and :func:`as_dict` stand in for
what pydantic gave (``model_copy(update=...)``, ``model_dump()``). Repeated fields read
as sequences (``np.asarray(msg.q_BI)`` is a fast copy); an optional field that is unset
reads as its zero value, ``msg.HasField(name)`` (or :func:`opt`) tells.

Key space (one run id per swarm, so swarms can share a router)::

    swarm/<run>/clock                world → all           Clock
    swarm/<run>/sat/<i>/sensors      world → agent i       Sensors
    swarm/<run>/sat/<i>/cam          world → agent i       CameraOutput
    swarm/<run>/sat/<i>/img          world → agent i       Images  (rendered scenarios)
    swarm/<run>/meas/<i>             agent i → the radio   MeasBatch (the world, the recorder; with the
                                                           selector or a tool that asks for them)
    swarm/<run>/batches              world → all agents    StepBatches (links.enabled false, an estimator whose
                                                           radio is "all": every batch of a step, one message)
    swarm/<run>/batches/<i>          world → agent i       StepBatches (links.enabled false, radio "graph": the
                                                           batches of i's graph neighbours, its radio's delivery)
    swarm/<run>/est/<i>              agent i → all         Estimate
    swarm/<run>/cov/<i>              agent i (queryable)   FullEstimate
    swarm/<run>/init/<i>             world (queryable)     FullEstimate (the prior)
    swarm/<run>/claim/<token>        world (queryable)     Claim (a satellite id for --id auto)
    swarm/<run>/select               selector → all        Select
    swarm/<run>/fault                CLI / world → all     Fault (commands: the CLI's, the world's schedule)
    swarm/<run>/fault/<reporter>     that role → all       Fault (what <reporter> carried out: done / failed)
    swarm/<run>/health/<i>           agent i → all         Health
    swarm/<run>/truth                world → recorder      Truth   (agents never subscribe)
    swarm/<run>/rx/<i>               world → agent i       Delivery (links.enabled: what the radio delivered)
    swarm/<run>/links                world → recorder      LinkStats (links.enabled: per-link counters)
    swarm/<run>/rejoin/<i>[/<j>/<B>] world (queryable)     RejoinFate (links.enabled: a restart's state transfer)
    swarm/<run>/alive/<role>/<id>    liveliness tokens

Who may use which key is defined here too (:func:`grants`): the router's access rules are
generated from it (:mod:`swarmrt.security`), and :func:`check_key` holds every receiver to
the same table whatever the router let through.
"""

from __future__ import annotations

import collections
import functools
import itertools
import math
import re
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from google.protobuf.message import DecodeError, Message

from swarm.v1.claim_pb2 import Claim
from swarm.v1.clock_pb2 import Clock
from swarm.v1.common_pb2 import Header, Matrix
from swarm.v1.estimate_pb2 import Estimate, FullEstimate
from swarm.v1.estimators_pb2 import CiState, EstimatorMessage, PairwiseState
from swarm.v1.fault_pb2 import Fault
from swarm.v1.health_pb2 import Health
from swarm.v1.images_pb2 import CameraView, Images
from swarm.v1.links_pb2 import Delivered, Delivery, Latency, LinkStats, RejoinFate
from swarm.v1.measurements_pb2 import MeasBatch, StepBatches
from swarm.v1.recording_pb2 import BusGap, Liveliness, Malformed
from swarm.v1.selection_pb2 import Select
from swarm.v1.sensors_pb2 import CameraOutput, Detection, Sensors
from swarm.v1.truth_pb2 import Truth
from swarmcore.scenario import FAULT_ACTIONS, STALL_FAULTS, TARGETED_FAULTS

SCHEMA_VERSION = 1
MAX_SAT_ID = 10_000
QUAT_TOL = 1e-6  # |‖q‖ − 1| a unit quaternion may show (checked as |‖q‖² − 1| ≤ 2e-6; ours: ~1e-16)
SYM_TOL = 1e-9  # |A − Aᵀ| relative to max |A| a covariance may show (round-off only)
MiB = 1 << 20
MAX_PAYLOAD_BYTES = {"img": 64 * MiB, "full_est": 64 * MiB, "batches": 64 * MiB}
MAX_PAYLOAD_DEFAULT = 8 * MiB  # every other kind (an estimate of 100 satellites is ~60 KB)

__all__ = [
    "SCHEMA_VERSION",
    "MAX_SAT_ID",
    "QUAT_TOL",
    "MAX_PAYLOAD_BYTES",
    "SHALLOW_KINDS",
    "MessageError",
    "KeyMismatch",
    "Grants",
    "grants",
    "IDENTITIES",
    "Header",
    "Matrix",
    "Clock",
    "Sensors",
    "Detection",
    "CameraOutput",
    "MeasBatch",
    "StepBatches",
    "Estimate",
    "FullEstimate",
    "EstimatorMessage",
    "CiState",
    "PairwiseState",
    "MAX_OPAQUE_BYTES",
    "Select",
    "Fault",
    "Health",
    "Truth",
    "Claim",
    "Images",
    "CameraView",
    "Delivery",
    "Delivered",
    "Latency",
    "LinkStats",
    "RejoinFate",
    "Liveliness",
    "BusGap",
    "Malformed",
    "Keys",
    "MODELS",
    "FAULT_ACTIONS",
    "encode",
    "decode",
    "validate",
    "check_estimator_message",
    "check_key",
    "parse_key",
    "replace",
    "as_dict",
    "opt",
    "pixels",
    "batch_arrays",
    "step_batch_arrays",
    "detection_arrays",
    "forget_arrays",
    "prepare",
    "file_descriptor_set",
    "codec_cpu_ms",
    "counted",
]


class MessageError(ValueError):
    """A payload that is not a valid message of the expected kind."""


class KeyMismatch(MessageError):
    """A valid message on a key its sender, observer or satellite field says it may not
    use (someone speaking for another): dropped and counted apart from other malformed
    messages, whatever the router let through."""


MODELS: dict[str, type[Message]] = {
    "clock": Clock,
    "sensors": Sensors,
    "cam": CameraOutput,
    "meas": MeasBatch,
    "batches": StepBatches,
    "est": Estimate,
    "full_est": FullEstimate,
    "select": Select,
    "fault": Fault,
    "health": Health,
    "truth": Truth,
    "claim": Claim,
    "img": Images,
    "rx": Delivery,
    "links": LinkStats,
    "rejoin": RejoinFate,
}

# Fault actions are declared once, with the scenario's FaultSpec (swarmcore/scenario.py).
_FAULT_NEEDS_TARGET = TARGETED_FAULTS


# -- CPU time spent on messages ---------------------------------------------------------
# Building, encoding, decoding, validating and converting messages, per process: what
# `swarm bench run` sets against the filter's own CPU time. Thread CPU time, counted once
# for nested calls (a conversion that encodes), from any thread (queryables reply on
# Zenoh's threads).
class _Tally(threading.local):
    """Per thread: whether a counted call is under way, and the nanoseconds counted
    (each thread adds to its own cell; :func:`codec_cpu_ms` sums them: no lock per call)."""

    def __init__(self):
        self.busy = False
        self.cell = [0]
        with _cells_lock:
            _cells.append(self.cell)


_cells: list[list[int]] = []
_cells_lock = threading.Lock()
_tally = _Tally()


def counted(fn):
    """Add the thread CPU time of ``fn`` to the process's message-handling total."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        t = _tally
        if t.busy:
            return fn(*args, **kwargs)
        t.busy = True
        t0 = time.thread_time_ns()
        try:
            return fn(*args, **kwargs)
        finally:
            t.cell[0] += time.thread_time_ns() - t0
            t.busy = False

    return wrapper


def codec_cpu_ms(reset: bool = True) -> float:
    """CPU time (ms) this process spent on messages since the last reset."""
    with _cells_lock:
        ns = 0
        for c in _cells:
            v = c[0]
            ns += v
            if reset:
                c[0] -= v  # a concurrent add on another thread is kept, not lost
    return ns / 1e6


# -- encoding and decoding -------------------------------------------------------------
@counted
def encode(msg) -> bytes:
    """The wire bytes of a message; stamps the schema version when the builder left it out."""
    if not msg.schema_version:
        msg.schema_version = SCHEMA_VERSION
    return msg.SerializeToString()


@counted
def decode(kind: str, payload: bytes | bytearray | memoryview, shallow: bool = False, n_sats: int | None = None):
    """Parse and validate a payload of the given kind; :class:`MessageError` on any defect.

    ``shallow``: for a receiver that reads only the header and the scalars of an estimate
    (who, which step, prior or posterior), check only those (:data:`SHALLOW_KINDS`); its
    arrays are then not to be read. Everything else is always checked in full."""
    cls = MODELS.get(kind)
    if cls is None:
        raise MessageError(f"unknown message kind {kind!r}")
    limit = MAX_PAYLOAD_BYTES.get(kind, MAX_PAYLOAD_DEFAULT)
    if len(payload) > limit:
        raise MessageError(f"invalid {kind} message: {len(payload)} bytes, more than the {limit} a {kind} message may have")
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except DecodeError as exc:
        raise MessageError(f"invalid {kind} message: not a {cls.DESCRIPTOR.full_name} ({exc})") from None
    validate(msg, kind, shallow, n_sats)
    return msg


def validate(msg, kind: str | None = None, shallow: bool = False, n_sats: int | None = None) -> None:
    """Check what the schema cannot (see the module doc); :class:`MessageError` names the field.
    ``n_sats``: the swarm's size, which every satellite id must be below (else ``MAX_SAT_ID``)."""
    kind = kind or _KIND_OF[type(msg)]
    top = MAX_SAT_ID if n_sats is None else n_sats - 1
    try:
        _header(msg)
        ((shallow and _SHALLOW.get(kind)) or _VALIDATORS[kind])(msg, top)
    except MessageError as exc:
        raise MessageError(f"invalid {kind} message: {exc}") from None


def _header(m) -> None:
    if m.schema_version != SCHEMA_VERSION:
        if m.schema_version == 0:
            raise MessageError("schema_version: missing (not a swarm.v1 message)")
        raise MessageError(f"schema_version: unknown version {m.schema_version} (this receiver reads {SCHEMA_VERSION})")
    if not _run_ok(m.run):
        raise MessageError(f"run: {m.run[:80]!r} is not a run id (1-64 letters, digits, '_', '-', '.')")
    if not 1 <= len(m.sender) <= 64:
        raise MessageError(f"sender: {len(m.sender)} characters (1-64 allowed)")
    if not math.isfinite(m.t_s):
        raise MessageError(f"t_s: {m.t_s} is not finite")


@functools.lru_cache(maxsize=256)
def _run_ok(run: str) -> bool:
    return _RUN_RE.fullmatch(run) is not None


# -- field checks (vectorised: an agent at n = 40 validates ~80 messages a step) ----------
def _id(top: int, name: str, v: int) -> None:
    if v > top:
        raise MessageError(f"{name}: satellite id {v} out of range (0-{top})")


def _ids(top: int, name: str, vals) -> None:
    big = max(vals, default=0)  # a short list of ints: Python's max beats a numpy round trip
    if big > top:
        raise MessageError(f"{name}: satellite id {big} out of range (0-{top})")


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    if not np.isfinite(a).all():
        raise MessageError(f"{name}: not finite (NaN or infinity)")
    return a


def _rows(name: str, vals, width: int, rows: int | None = None) -> np.ndarray:
    """A packed array of ``rows`` × ``width`` numbers (any whole number of rows if ``rows`` is None)."""
    size = len(vals)
    if size % width or (rows is not None and size != rows * width):
        want = f"{rows} × {width}" if rows is not None else f"a multiple of {width}"
        raise MessageError(f"{name}: {size} numbers, expected {want}")
    return _finite(name, np.asarray(vals, dtype=float).reshape(-1, width))


def _optional_vec(name: str, vals, width: int) -> np.ndarray | None:
    if len(vals) == 0:
        return None
    return _rows(name, vals, width, 1)[0]


def _unit(name: str, q: np.ndarray) -> None:
    """|‖q‖² − 1| ≤ 2·QUAT_TOL, i.e. ‖q‖ within QUAT_TOL of 1 (to first order)."""
    if len(q):
        err = float(np.abs(np.einsum("ij,ij->i", q, q) - 1.0).max())
        if not err <= 2 * QUAT_TOL:
            raise MessageError(f"{name}: not a unit quaternion (|‖q‖² − 1| = {err:.3g} > {2 * QUAT_TOL:g})")


def _matrix(name: str, m: Matrix, shape: tuple[int, ...]) -> np.ndarray:
    if tuple(m.shape) != shape:
        raise MessageError(f"{name}: shape {list(m.shape)}, expected {list(shape)}")
    need = math.prod(shape)
    if len(m.data) != need:
        raise MessageError(f"{name}: shape {list(shape)} needs {need} numbers, got {len(m.data)}")
    return _finite(name, np.asarray(m.data, dtype=float).reshape(shape))


def _spd(name: str, A: np.ndarray) -> None:
    """Symmetric (to round-off: SYM_TOL of the matrix's largest entry) and positive-definite
    (Cholesky succeeds), each of a stack of square matrices with finite entries."""
    if len(A) == 0:
        return
    scale = np.abs(A).max(axis=(1, 2))
    with np.errstate(over="ignore"):  # A − Aᵀ of entries near ±1e308 is ±inf: not round-off, so not symmetric
        asym = np.abs(A - A.transpose(0, 2, 1)).max(axis=(1, 2))
    if not (asym <= SYM_TOL * scale).all():
        raise MessageError(f"{name}: not symmetric")
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        raise MessageError(f"{name}: not positive-definite") from None


def _choice(name: str, v: str, allowed) -> None:
    if v not in allowed:
        raise MessageError(f"{name}: {v[:40]!r} is not one of {list(allowed)}")


def _nonneg(name: str, v: float) -> None:
    if not (math.isfinite(v) and v >= 0):
        raise MessageError(f"{name}: {v} is not a finite number ≥ 0")


def _clock(m: Clock, top: int) -> None:
    _ids(top, "live_agents", m.live_agents)
    _choice("mode", m.mode, ("lockstep", "free"))


def _small(name: str, vals, width: int) -> list[float] | None:
    """A short optional vector (a sensor reading: 3 or 4 numbers) checked in plain Python,
    which for a handful of numbers is ten times quicker than a numpy round trip."""
    if len(vals) == 0:
        return None
    if len(vals) != width:
        raise MessageError(f"{name}: {len(vals)} numbers, expected 1 × {width}")
    v = list(vals)
    if not all(map(math.isfinite, v)):
        raise MessageError(f"{name}: not finite (NaN or infinity)")
    return v


def _sensors(m: Sensors, top: int) -> None:
    _id(top, "sat", m.sat)
    _small("gyro_rate_B_rad_s", m.gyro_rate_B_rad_s, 3)
    q = _small("q_BI_star", m.q_BI_star, 4)
    if q is not None:
        err = abs(math.fsum(x * x for x in q) - 1.0)
        if not err <= 2 * QUAT_TOL:
            raise MessageError(f"q_BI_star: not a unit quaternion (|‖q‖² − 1| = {err:.3g} > {2 * QUAT_TOL:g})")
    _small("r_H_gps_m", m.r_H_gps_m, 3)
    for f in ("sigma_star_rad", "sigma_gps_m"):
        v = getattr(m, f)
        if not (math.isfinite(v) and v > 0):
            raise MessageError(f"{f}: {v} is not a finite number > 0")


def _cam(m: CameraOutput, top: int) -> None:
    _id(top, "sat", m.sat)
    dets = m.detections
    # One pass over the rows for the columns, then the checks on whole columns (the first
    # bad row is looked for only when a check fails).
    tgt = [d.target for d in dets]
    cam = [d.camera for d in dets]
    q, r = [], []
    for d in dets:
        q.extend(d.q_BjBi)
        r.extend(d.r_ij_Bi_m)
    n = len(tgt)
    if len(q) != 4 * n or len(r) != 3 * n:
        j = next(j for j, d in enumerate(dets) if len(d.q_BjBi) != 4 or len(d.r_ij_Bi_m) != 3)
        raise MessageError(f"detections.{j}: {len(dets[j].q_BjBi)} numbers in q_BjBi (4), {len(dets[j].r_ij_Bi_m)} in r_ij_Bi_m (3)")
    if n and (max(tgt) > top or m.sat in tgt or max(cam) > 5):
        for j in range(n):
            _id(top, f"detections.{j}.target", tgt[j])
            if tgt[j] == m.sat:
                raise MessageError(f"detections.{j}.target: satellite {m.sat} cannot see itself")
            if cam[j] > 5:
                raise MessageError(f"detections.{j}.camera: {cam[j]} is not a face camera (0-5)")
    qa = _rows("detections.q_BjBi", q, 4)
    _unit("detections.q_BjBi", qa)
    ra = _rows("detections.r_ij_Bi_m", r, 3)
    c = np.asarray(m.cameras_off, dtype=np.int64)
    if c.size and c.max() > 5:
        raise MessageError(f"cameras_off: {int(c.max())} is not a face camera (0-5)")
    # The receiver's next step is converting these very columns: keep them for it.
    _MEMO.put(m, (np.array(tgt, dtype=int), np.array(cam, dtype=int), qa, ra))


def _columns(m, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measurement columns of a MeasBatch or StepBatches of ``n`` rows (camera,
    q_BjBi, r_ij_Bi_m, R_Bi: lengths, shape, and every number in one compiled pass);
    returns (q (n, 4), r (n, 3), R (n, 6, 6))."""
    if len(m.camera) != n:
        raise MessageError(f"camera: {len(m.camera)} values for {n} measurements")
    if max(m.camera, default=0) > 6 + MAX_SAT_ID:
        raise MessageError(f"camera: {max(m.camera)} out of range")
    for name, vals, width in (("q_BjBi", m.q_BjBi, 4), ("r_ij_Bi_m", m.r_ij_Bi_m, 3)):
        if len(vals) != width * n:
            raise MessageError(f"{name}: {len(vals)} numbers, expected {n} × {width}")
    if tuple(m.R_Bi.shape) != (n, 6, 6):
        raise MessageError(f"R_Bi: shape {list(m.R_Bi.shape)}, expected {[n, 6, 6]}")
    if len(m.R_Bi.data) != 36 * n:
        raise MessageError(f"R_Bi: shape {[n, 6, 6]} needs {36 * n} numbers, got {len(m.R_Bi.data)}")
    q = np.asarray(m.q_BjBi, dtype=float).reshape(n, 4)
    r = np.asarray(m.r_ij_Bi_m, dtype=float).reshape(n, 3)
    R = np.asarray(m.R_Bi.data, dtype=float).reshape(n, 6, 6)
    fc = _fastcheck()
    code = fc.check_batch(q, r, R, 2 * QUAT_TOL, SYM_TOL)
    if code:
        raise MessageError(fc.REASONS[code])
    return q, r, R


#: Estimator names (the scenario's estimator.kind) and the largest plug-in message.
_KIND_RE = re.compile(r"^[a-z][a-z0-9_\-]{0,63}$")
MAX_OPAQUE_BYTES = 64 * 1024


def _estimator_msg(name: str, e: EstimatorMessage, top: int, sender: int) -> None:
    """An estimator's message: its kind, and its body's arrays (lengths, finite numbers,
    unit quaternion, SPD covariances, partner ids), or a bounded opaque blob."""
    if not e.kind:
        if e.WhichOneof("body") is not None:
            raise MessageError(f"{name}: a body without a kind")
        return
    if not _KIND_RE.match(e.kind):
        raise MessageError(f"{name}.kind: {e.kind[:40]!r} is not an estimator name ([a-z][a-z0-9_-], at most 64)")
    which = e.WhichOneof("body")
    if which == "ci":
        c = e.ci
        _unit(f"{name}.ci.q_BI", _rows(f"{name}.ci.q_BI", c.q_BI, 4, 1))
        for f in ("omega_BI_B_rad_s", "r_H_m", "v_H_m_s"):
            _rows(f"{name}.ci.{f}", getattr(c, f), 3, 1)
        _spd(f"{name}.ci.P_pose", _matrix(f"{name}.ci.P_pose", c.P_pose, (6, 6))[None])
    elif which == "pairwise":
        w = e.pairwise
        _unit(f"{name}.pairwise.q_BI", _rows(f"{name}.pairwise.q_BI", w.q_BI, 4, 1))
        for f in ("omega_BI_B_rad_s", "r_H_m", "v_H_m_s", "bias_B_rad_s"):
            _rows(f"{name}.pairwise.{f}", getattr(w, f), 3, 1)
        _spd(f"{name}.pairwise.P", _matrix(f"{name}.pairwise.P", w.P, (12, 12))[None])
        parts = list(w.partners)
        _ids(top, f"{name}.pairwise.partners", parts)
        if any(b <= a for a, b in itertools.pairwise(parts)):
            raise MessageError(f"{name}.pairwise.partners: not ascending and distinct")
        if sender in parts:
            raise MessageError(f"{name}.pairwise.partners: satellite {sender} cannot be its own partner")
        _matrix(f"{name}.pairwise.sigma", w.sigma, (len(parts), 12, 12))
    elif which == "opaque":
        if len(e.opaque) > MAX_OPAQUE_BYTES:
            raise MessageError(f"{name}.opaque: {len(e.opaque)} bytes (at most {MAX_OPAQUE_BYTES})")
    else:
        raise MessageError(f"{name}: kind {e.kind!r} without a body")


def _ci_states_sound(ests) -> bool:
    """Every message of a step a ``ci`` state, all sound, in one compiled pass (a receiver at
    n = 100 checks 99 a step: one at a time that was milliseconds); False sends them through
    :func:`_estimator_msg`, which names what is wrong."""
    kinds = {e.kind for e in ests}
    if len(kinds) != 1 or not _KIND_RE.match(next(iter(kinds))) or any(e.WhichOneof("body") != "ci" for e in ests):
        return False
    cs = [e.ci for e in ests]
    if any(len(c.q_BI) != 4 or len(c.omega_BI_B_rad_s) != 3 or len(c.r_H_m) != 3 or len(c.v_H_m_s) != 3
           or tuple(c.P_pose.shape) != (6, 6) or len(c.P_pose.data) != 36 for c in cs):
        return False
    q = np.array([c.q_BI for c in cs], dtype=float)
    rows = np.array([[c.omega_BI_B_rad_s, c.r_H_m, c.v_H_m_s] for c in cs], dtype=float).reshape(-1, 3)
    P = np.array([c.P_pose.data for c in cs], dtype=float).reshape(-1, 6, 6)
    return _fastcheck().check_batch(q, rows, P, 2 * QUAT_TOL, SYM_TOL) == 0


def _meas(m: MeasBatch, top: int) -> None:
    _id(top, "observer", m.observer)
    tgt = list(m.target)
    _ids(top, "target", tgt)
    if m.observer in tgt:
        raise MessageError(f"target: satellite {m.observer} cannot measure itself")
    if m.HasField("estimator"):
        _estimator_msg("estimator", m.estimator, top, m.observer)
    q, r, R = _columns(m, len(tgt))
    # The receiver's next step is converting these very arrays: keep them for it.
    _MEMO.put(m, (np.array(tgt, dtype=int), q, r, R))


def _step_batches(m: StepBatches, top: int) -> None:
    obs = _step_batches_rows(m, top)
    if m.estimators and not _ci_states_sound(m.estimators):
        for o, e in zip(obs, m.estimators):
            _estimator_msg(f"estimators[{o}]", e, top, o)


def _step_batches_shallow(m: StepBatches, top: int) -> None:
    """A StepBatches for a receiver that reads its peers' estimator messages one by one
    (an agent: its estimator reads a few of the n − 1, its graph neighbours'), checking
    each as it reads it (:func:`check_estimator_message`); everything else in full. At
    n = 100 checking the 99 messages up front was most of an agent's decoding, and the
    world had checked each when its sender put it."""
    _step_batches_rows(m, top)


def check_estimator_message(e: EstimatorMessage, sender: int, n_sats: int | None = None) -> None:
    """What :func:`decode` checks of one estimator message in a batch (sender ``sender``);
    :class:`MessageError` naming the defect. For receivers of a shallow StepBatches."""
    top = MAX_SAT_ID if n_sats is None else n_sats - 1
    _estimator_msg(f"estimators[{sender}]", e, top, sender)


def _step_batches_rows(m: StepBatches, top: int) -> list[int]:
    obs = list(m.observers)
    cnt = list(m.counts)
    if len(cnt) != len(obs):
        raise MessageError(f"counts: {len(cnt)} values for {len(obs)} observers")
    _ids(top, "observers", obs)
    if any(b <= a for a, b in itertools.pairwise(obs)):
        raise MessageError("observers: not ascending and distinct")
    n = sum(cnt)
    if len(m.target) != n:
        raise MessageError(f"target: {len(m.target)} values for {n} rows (the sum of counts)")
    tgt = np.asarray(m.target, dtype=int)
    if n and tgt.max() > top:
        raise MessageError(f"target: satellite id {int(tgt.max())} out of range (0-{top})")
    rows = np.repeat(np.asarray(obs, dtype=int), np.asarray(cnt, dtype=int))
    if (rows == tgt).any():
        raise MessageError(f"target: satellite {int(rows[rows == tgt][0])} cannot measure itself")
    if len(m.estimators) not in (0, len(obs)):
        raise MessageError(f"estimators: {len(m.estimators)} messages for {len(obs)} observers")
    q, r, R = _columns(m, n)
    _MEMO.put(m, (rows, tgt, q, r, R))
    return obs


@functools.cache
def _fastcheck():
    """:mod:`.fastcheck` (numba), loaded when first needed, not at import."""
    from swarmrt.bus import fastcheck

    return fastcheck


def prepare(kind: str) -> None:
    """Load now what decoding ``kind`` will need (measurement batches: the compiled
    checks, about a second with numba's import), so the first message is not late."""
    if kind in ("meas", "batches"):
        _fastcheck().warm_up()


class _Memo:
    """Arrays a validation computed, kept for the conversion that follows (at n = 40 an
    agent would otherwise convert every batch's columns twice a step). Keyed by the
    message's id with the message itself held, so an id cannot be reused while it is here;
    bounded in entries and in bytes (the arrays' and, as much again, the message's own copy
    of those numbers), oldest first out. A single value over the byte bound is not kept:
    its conversion is simply done again."""

    def __init__(self, size: int = 2048, max_bytes: int = 64 << 20):
        self._d: collections.OrderedDict[int, tuple] = collections.OrderedDict()
        self._size = size
        self._max_bytes = max_bytes
        self.bytes = 0  # what is held now, counted as above
        self._lock = threading.Lock()

    @staticmethod
    def _cost(value) -> int:
        return 2 * sum(int(getattr(a, "nbytes", 0)) for a in value)

    def put(self, msg, value) -> None:
        cost = self._cost(value)
        if cost > self._max_bytes:
            return
        with self._lock:
            old = self._d.pop(id(msg), None)
            if old is not None:
                self.bytes -= old[2]
            self._d[id(msg)] = (msg, value, cost)
            self.bytes += cost
            while len(self._d) > self._size or self.bytes > self._max_bytes:
                self.bytes -= self._d.popitem(last=False)[1][2]

    def take(self, msg):
        """The value kept for this very message (and forget it), or None."""
        with self._lock:
            hit = self._d.pop(id(msg), None)
            if hit is not None:
                self.bytes -= hit[2]
        return hit[1] if hit is not None and hit[0] is msg else None

    def __len__(self) -> int:
        return len(self._d)


_MEMO = _Memo()


def detection_arrays(m: CameraOutput) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(target (m,), camera (m,), q_BjBi (m, 4), r_ij_Bi_m (m, 3)) of a decoded camera output."""
    got = _MEMO.take(m)
    if got is not None:
        return got
    dets = m.detections
    return (
        np.array([d.target for d in dets], dtype=int),
        np.array([d.camera for d in dets], dtype=int),
        np.array([x for d in dets for x in d.q_BjBi], dtype=float).reshape(-1, 4),
        np.array([x for d in dets for x in d.r_ij_Bi_m], dtype=float).reshape(-1, 3),
    )


def forget_arrays(m) -> None:
    """Drop what a validation kept of ``m`` for a conversion that will not come."""
    _MEMO.take(m)


def batch_arrays(m: MeasBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(target (m,), q_BjBi (m, 4), r_ij_Bi_m (m, 3), R_Bi (m, 6, 6)) of a decoded batch."""
    got = _MEMO.take(m)
    if got is not None:
        return got
    n = len(m.target)
    return (
        np.asarray(m.target, dtype=int),
        np.asarray(m.q_BjBi, dtype=float).reshape(n, 4),
        np.asarray(m.r_ij_Bi_m, dtype=float).reshape(n, 3),
        np.asarray(m.R_Bi.data, dtype=float).reshape(n, 6, 6),
    )


def step_batch_arrays(m: StepBatches) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(observer (rows,), target (rows,), q_BjBi (rows, 4), r_ij_Bi_m (rows, 3), R_Bi (rows, 6, 6)) of a decoded StepBatches."""
    got = _MEMO.take(m)
    if got is not None:
        return got
    n = len(m.target)
    return (
        np.repeat(np.asarray(m.observers, dtype=int), np.asarray(m.counts, dtype=int)),
        np.asarray(m.target, dtype=int),
        np.asarray(m.q_BjBi, dtype=float).reshape(n, 4),
        np.asarray(m.r_ij_Bi_m, dtype=float).reshape(n, 3),
        np.asarray(m.R_Bi.data, dtype=float).reshape(n, 6, 6),
    )


def _state(m, bias: str = "bias_B_rad_s") -> int:
    """The per-satellite arrays of an estimate or truth message; returns n."""
    q = _rows("q_BI", m.q_BI, 4)
    n = q.shape[0]
    if n == 0:
        raise MessageError("q_BI: no satellites")
    _unit("q_BI", q)
    for f in ("omega_BI_B_rad_s", "r_H_m", "v_H_m_s"):
        _rows(f, getattr(m, f), 3, n)
    _rows(bias, getattr(m, bias), 3, n if bias == "gyro_bias_B_rad_s" else 1)
    return n


def _est_sound(m: Estimate) -> bool:
    """Every array of an estimate at once, compiled (:mod:`.fastcheck`): True when the
    numbers are sound; False sends the message through the checks below, which name what
    is wrong. (The recorder checks every agent's estimate every step: at n = 40 the
    checks one array at a time took 0.3 ms each.)"""
    n, rest = divmod(len(m.q_BI), 4)
    if n == 0 or rest or tuple(m.P_pose.shape) != (n, 6, 6) or tuple(m.P_diag.shape) != (12 * n,):
        return False
    if not (len(m.omega_BI_B_rad_s) == len(m.r_H_m) == len(m.v_H_m_s) == 3 * n and len(m.bias_B_rad_s) == 3):
        return False
    if len(m.P_pose.data) != 36 * n or len(m.P_diag.data) != 12 * n:
        return False
    rows = np.concatenate([np.asarray(f, dtype=float) for f in (m.omega_BI_B_rad_s, m.r_H_m, m.v_H_m_s, m.bias_B_rad_s)])
    d = np.asarray(m.P_diag.data, dtype=float)
    fc = _fastcheck()
    return (fc.check_batch(np.asarray(m.q_BI, dtype=float).reshape(n, 4), rows.reshape(-1, 3),
                           np.asarray(m.P_pose.data, dtype=float).reshape(n, 6, 6), 2 * QUAT_TOL, SYM_TOL) == 0
            and bool(np.isfinite(d).all() and (d > 0).all()))


def _own_row(m, n: int, top: int) -> None:
    """``own`` among the rows: rows 0..n-1 are satellites 0..n-1, or the ``ids`` listed."""
    ids = list(m.ids)
    if not ids:
        if m.own >= n:
            raise MessageError(f"own: satellite {m.own} in an estimate of {n}")
        return
    if len(ids) != n:
        raise MessageError(f"ids: {len(ids)} satellites for {n} rows")
    _ids(top, "ids", ids)
    if any(b <= a for a, b in itertools.pairwise(ids)):
        raise MessageError("ids: not ascending and distinct")
    if m.own not in ids:
        raise MessageError(f"own: satellite {m.own} is not among the rows {ids[:8]}{'…' if len(ids) > 8 else ''}")


def _rel_pose(m: Estimate, n: int) -> None:
    """``P_rel_pose`` (when present): [n, 6, 6], symmetric, positive-definite but on the own row."""
    if not m.HasField("P_rel_pose"):
        return
    A = _matrix("P_rel_pose", m.P_rel_pose, (n, 6, 6))
    ids = list(m.ids) or list(range(n))
    keep = np.asarray(ids) != m.own
    _spd("P_rel_pose", A[keep])


def _est(m: Estimate, top: int) -> None:
    _id(top, "own", m.own)
    _choice("phase", m.phase, ("prior", "posterior"))
    if m.estimator and not _KIND_RE.match(m.estimator):
        raise MessageError(f"estimator: {m.estimator[:40]!r} is not an estimator name")
    if _est_sound(m):
        _own_row(m, len(m.q_BI) // 4, top)
        _rel_pose(m, len(m.q_BI) // 4)
        for f in ("nis", "step_ms", "step_cpu_ms", "codec_cpu_ms"):
            _nonneg(f, getattr(m, f))
        _ids(top, "batches_used", m.batches_used)
        _ids(top, "batches_missing", m.batches_missing)
        return
    n = _state(m)
    _own_row(m, n, top)
    _spd("P_pose", _matrix("P_pose", m.P_pose, (n, 6, 6)))
    if m.ids:  # an estimator that keeps only some of its rows' variances: NaN where it keeps none
        if tuple(m.P_diag.shape) != (12 * n,) or len(m.P_diag.data) != 12 * n:
            raise MessageError(f"P_diag: shape {list(m.P_diag.shape)}, expected {[12 * n]}")
        d = np.asarray(m.P_diag.data, dtype=float)
        if np.isinf(d).any() or (d[~np.isnan(d)] <= 0).any():
            raise MessageError("P_diag: a variance ≤ 0 or infinite")
    else:
        d = _matrix("P_diag", m.P_diag, (12 * n,))
        if (d <= 0).any():
            raise MessageError("P_diag: a variance ≤ 0")
    _rel_pose(m, n)
    for f in ("nis", "step_ms", "step_cpu_ms", "codec_cpu_ms"):
        _nonneg(f, getattr(m, f))
    _ids(top, "batches_used", m.batches_used)
    _ids(top, "batches_missing", m.batches_missing)


def _est_shallow(m: Estimate, top: int) -> None:
    _id(top, "own", m.own)
    _choice("phase", m.phase, ("prior", "posterior"))
    n, rest = divmod(len(m.q_BI), 4)
    if n == 0 or rest:
        raise MessageError(f"q_BI: {len(m.q_BI)} numbers, expected a positive multiple of 4")
    _own_row(m, n, top)


def _full_est(m: FullEstimate, top: int) -> None:
    _id(top, "own", m.own)
    n = _state(m)
    _own_row(m, n, top)
    _spd("P", _matrix("P", m.P, (12 * n, 12 * n))[None])


def _select(m: Select, top: int) -> None:
    _ids(top, "observer", m.observer)
    _ids(top, "target", m.target)
    if len(m.observer) != len(m.target):
        raise MessageError(f"observer/target: {len(m.observer)} observers for {len(m.target)} targets")
    if any(a == b for a, b in zip(m.observer, m.target)):
        raise MessageError("target: a satellite cannot measure itself")
    if not 1 <= len(m.strategy) <= 64:
        raise MessageError(f"strategy: {len(m.strategy)} characters (1-64 allowed)")
    if m.HasField("ref_agent"):
        _id(top, "ref_agent", m.ref_agent)
    _nonneg("select_ms", m.select_ms)


def _fault(m: Fault, top: int) -> None:
    _choice("action", m.action, FAULT_ACTIONS)
    _choice("phase", m.phase, ("command", "done", "failed"))
    if m.HasField("target"):
        _id(top, "target", m.target)
    elif m.action in _FAULT_NEEDS_TARGET:
        raise MessageError(f"target: {m.action} needs a target satellite")
    if m.HasField("camera") and m.camera > 5:
        raise MessageError(f"camera: {m.camera} is not a face camera (0-5)")
    if m.HasField("state"):
        _choice("state", m.state, ("on", "off"))
    if m.action == "camera" and not (m.HasField("camera") and m.HasField("state")):
        raise MessageError("camera: a camera fault needs camera and state")
    if m.HasField("rate") and not 0.0 <= m.rate <= 1.0:
        raise MessageError(f"rate: {m.rate} is not in [0, 1]")
    if m.action == "drop" and not m.HasField("rate"):
        raise MessageError("rate: a drop fault needs a rate")
    if m.HasField("down_s") and not 0.0 <= m.down_s <= 3600.0:
        raise MessageError(f"down_s: {m.down_s} is not in [0, 3600] s")
    if m.action in STALL_FAULTS and m.phase == "command" and not (m.HasField("down_s") and m.down_s > 0.0):
        raise MessageError(f"down_s: {m.action} needs down_s > 0 (how long the process stays stopped, wall s)")
    if m.HasField("peer"):
        _id(top, "peer", m.peer)
        if m.HasField("target") and m.peer == m.target:
            raise MessageError(f"peer: satellite {m.peer} has no link to itself")
    if m.HasField("delay_s") and not 0.0 <= m.delay_s <= 3600.0:
        raise MessageError(f"delay_s: {m.delay_s} is not in [0, 3600] s")
    if m.action == "link" and m.phase == "command" and not (m.HasField("state") or m.HasField("delay_s") or m.HasField("rate")):
        raise MessageError("link: a link fault needs state, delay_s or rate")
    if m.HasField("netem") and not 1 <= len(m.netem) <= 200:
        raise MessageError(f"netem: {len(m.netem)} characters (1-200 allowed)")
    if m.action == "netem" and not m.HasField("netem"):
        raise MessageError("netem: action netem needs netem (tc netem arguments or 'clear')")
    if m.HasField("netem"):
        from swarmrt.netem import NetemError, validate_field

        try:
            canonical = validate_field(m.netem)
        except NetemError as exc:
            raise MessageError(f"netem: {exc}") from None
        if canonical != m.netem:
            raise MessageError(f"netem: {m.netem!r} is not in canonical form ({canonical!r})")
    if len(m.detail) > 1000:
        raise MessageError(f"detail: {len(m.detail)} characters (at most 1000)")


def _health(m: Health, top: int) -> None:
    _id(top, "sat", m.sat)
    if len(m.camera_ok) != 6:
        raise MessageError(f"camera_ok: {len(m.camera_ok)} values, expected 6")
    if not 0.0 <= m.drop_rate <= 1.0:
        raise MessageError(f"drop_rate: {m.drop_rate} is not in [0, 1]")
    if len(m.host) > 253:
        raise MessageError(f"host: {len(m.host)} characters (at most 253)")


def _claim(m: Claim, top: int) -> None:
    _id(top, "sat", m.sat)
    if not 1 <= len(m.token) <= 128:
        raise MessageError(f"token: {len(m.token)} characters (1-128 allowed)")
    if len(m.password) > 128:
        raise MessageError(f"password: {len(m.password)} characters (at most 128)")


def _truth(m: Truth, top: int) -> None:
    _state(m, "gyro_bias_B_rad_s")


def _img(m: Images, top: int) -> None:
    _id(top, "sat", m.sat)
    _ids(top, "targets", m.targets)
    for j, v in enumerate(m.views):
        p = f"views.{j}"
        if v.camera > 6 + MAX_SAT_ID:
            raise MessageError(f"{p}.camera: {v.camera} out of range")
        T = _rows(f"{p}.T_CB", v.T_CB, 3, 3)
        # (A rotation's entries are within ±1: checked first, so T Tᵀ of huge entries never overflows.)
        if not (np.abs(T) <= 1 + 1e-6).all() or np.abs(T @ T.T - np.eye(3)).max() > 1e-6:
            raise MessageError(f"{p}.T_CB: not a rotation matrix")
        _rows(f"{p}.r_C_B_m", v.r_C_B_m, 3, 1)
        for f in ("width_px", "height_px"):
            if not 1 <= getattr(v, f) <= 16384:
                raise MessageError(f"{p}.{f}: {getattr(v, f)} is not in 1-16384")
        for f in ("fx_px", "fy_px"):
            if not (np.isfinite(getattr(v, f)) and getattr(v, f) > 0):
                raise MessageError(f"{p}.{f}: {getattr(v, f)} is not a finite number > 0")
        _finite(f"{p}.cx_px/cy_px", np.array([v.cx_px, v.cy_px]))
        if v.target < -1:
            raise MessageError(f"{p}.target: {v.target} (−1 or a satellite id)")
        _nonneg(f"{p}.baseline_m", v.baseline_m)
        if len(v.images_mono8) not in (1, 2):
            raise MessageError(f"{p}.images_mono8: {len(v.images_mono8)} images (1 for a face camera, 2 for a stereo pair)")
        need = v.width_px * v.height_px
        for i, im in enumerate(v.images_mono8):
            if len(im) != need:
                raise MessageError(f"{p}.images_mono8.{i}: {v.height_px}×{v.width_px} image needs {need} bytes, got {len(im)}")


def _rx(m: Delivery, top: int) -> None:
    _id(top, "sat", m.sat)
    for j, it in enumerate(m.items):
        if not math.isfinite(it.arrival_t_s):
            raise MessageError(f"items.{j}.arrival_t_s: not finite")
        b = it.batch
        try:
            _header(b)
            _meas(b, top)
        except MessageError as exc:
            raise MessageError(f"items.{j}.batch: {exc}") from None
        if b.observer == m.sat:
            raise MessageError(f"items.{j}.batch: satellite {m.sat}'s own batch delivered to it")


_MAX_COUNT = 2.0**53  # the largest count float64 holds exactly
_LINK_COUNTERS = ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")


def _links(m: LinkStats, top: int) -> None:
    n = len(m.queue_bytes)
    if n == 0:
        raise MessageError("queue_bytes: no transmitters")
    _id(top, "queue_bytes (swarm size - 1)", n - 1)
    for f in _LINK_COUNTERS:
        a = _matrix(f, getattr(m, f), (n, n))
        if (a < 0).any():
            raise MessageError(f"{f}: a negative count")
        if not ((a <= _MAX_COUNT) & (a == np.rint(a))).all():  # a receiver reads them as integers
            raise MessageError(f"{f}: not a count (a whole number up to 2^53)")
    for j, lat in enumerate(m.latencies):
        _id(top, f"latencies.{j}.sender", lat.sender)
        _id(top, f"latencies.{j}.receiver", lat.receiver)
        if not (math.isfinite(lat.latency_s) and lat.latency_s >= 0):
            raise MessageError(f"latencies.{j}.latency_s: {lat.latency_s} is not a finite number ≥ 0")


def _rejoin(m: RejoinFate, top: int) -> None:
    _id(top, "sat", m.sat)
    _id(top, "peer", m.peer)
    _choice("fate", m.fate, ("delivered", "lost", "dropped", "unreachable"))
    if m.HasField("arrival_t_s") and not math.isfinite(m.arrival_t_s):
        raise MessageError("arrival_t_s: not finite")
    if m.fate == "delivered" and not m.HasField("arrival_t_s"):
        raise MessageError("arrival_t_s: a delivered transfer needs its arrival time")


_VALIDATORS: dict[str, Callable[[Any, int], None]] = {
    "clock": _clock,
    "sensors": _sensors,
    "cam": _cam,
    "meas": _meas,
    "batches": _step_batches,
    "est": _est,
    "full_est": _full_est,
    "select": _select,
    "fault": _fault,
    "health": _health,
    "truth": _truth,
    "claim": _claim,
    "img": _img,
    "rx": _rx,
    "links": _links,
    "rejoin": _rejoin,
}
_SHALLOW: dict[str, Callable[[Any, int], None]] = {"est": _est_shallow, "batches": _step_batches_shallow}
SHALLOW_KINDS = tuple(_SHALLOW)
_KIND_OF = {cls: kind for kind, cls in MODELS.items()}


# -- the message against its key ----------------------------------------------------------
_WORLD_KEYS = ("clock", "sensors", "cam", "img", "truth", "claim", "rx", "batches", "links", "rejoin")
_OWNER_FIELD = {"sensors": "sat", "cam": "sat", "img": "sat", "health": "sat", "meas": "observer", "est": "own", "full_est": "own", "rx": "sat", "rejoin": "sat"}


_REPORTER_RE = re.compile(r"world|selector|supervisor|cli|agent-\d+")


def check_key(key: str, kind: str, sat: int | None, msg) -> None:
    """The message agrees with the key it came on: the satellite the key names is the one
    the message is about, and the sender is the role that publishes on that key
    (:class:`KeyMismatch` otherwise)."""
    field = _OWNER_FIELD.get(kind)
    if sat is not None and field is not None and getattr(msg, field) != sat:
        raise KeyMismatch(f"key says satellite {sat}, message {field} says {getattr(msg, field)}")
    want: tuple[str, ...]
    if kind in _WORLD_KEYS or (kind == "full_est" and "/init/" in key):
        want = ("world",)
    elif kind in ("meas", "est", "health", "full_est"):
        want = (f"agent-{sat}",)
    elif kind == "select":
        want = ("selector", "world")
    else:  # fault: commands on fault (the CLI's, the world's schedule); outcomes on fault/<reporter>
        tail = key.rsplit("/", 1)[1]
        if tail == "fault":
            if msg.phase != "command":
                raise KeyMismatch(f"a fault {msg.phase!r} report on {key} (reports go on fault/<reporter>)")
            want = ("cli", "world")
        else:
            if msg.phase == "command":
                raise KeyMismatch(f"a fault command on {key} (commands go on fault)")
            if not _REPORTER_RE.fullmatch(tail):
                raise KeyMismatch(f"{tail[:64]!r} is not a role that carries out faults")
            want = (tail,)
    if msg.sender not in want:
        raise KeyMismatch(f"sender {msg.sender[:64]!r} may not publish on {key} (expected {' or '.join(want)})")


# -- helpers in place of pydantic's -------------------------------------------------------
def replace(msg, **changes):
    """A copy of ``msg`` with some fields changed (``None`` clears an optional field)."""
    out = type(msg)()
    out.CopyFrom(msg)
    fields = out.DESCRIPTOR.fields_by_name
    for name, v in changes.items():
        f = fields.get(name)
        if f is None:
            raise AttributeError(f"{out.DESCRIPTOR.full_name} has no field {name!r}")
        if v is None:
            out.ClearField(name)
        elif f.is_repeated:
            out.ClearField(name)
            getattr(out, name).extend(v)
        elif f.message_type is not None:
            getattr(out, name).CopyFrom(v)
        else:
            setattr(out, name, v)
    return out


def opt(msg, name: str):
    """An optional field's value, or None when it is unset."""
    return getattr(msg, name) if msg.HasField(name) else None


def as_dict(msg, exclude=()) -> dict:
    """Plain Python values of every field (unset optional fields as None), for JSON."""
    out = {}
    for f in msg.DESCRIPTOR.fields:
        if f.name in exclude:
            continue
        v = getattr(msg, f.name)
        if f.is_repeated:
            v = [as_dict(x) for x in v] if f.message_type is not None else list(v)
        elif f.message_type is not None:
            v = as_dict(v) if msg.HasField(f.name) else None
        elif f.has_presence and not msg.HasField(f.name):
            v = None
        out[f.name] = v
    return out


def file_descriptor_set(message_class) -> bytes:
    """The serialized FileDescriptorSet of a protobuf message class and everything it
    imports: the schema data of an MCAP channel with encoding "protobuf"."""
    from google.protobuf import descriptor_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd):
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        fds.file.append(proto)

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


def pixels(msg: Images) -> list[np.ndarray]:
    """Every view's images in view order, as writeable uint8 arrays (height × width)."""
    return [
        np.frombuffer(im, dtype=np.uint8).reshape(v.height_px, v.width_px).copy()
        for v in msg.views
        for im in v.images_mono8
    ]


# -- keys ----------------------------------------------------------------------------------
_RUN_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class Keys:
    """Key expressions of one run."""

    def __init__(self, run: str):
        if not _RUN_RE.fullmatch(run):
            raise ValueError(f"run id {run!r}: use 1-64 letters, digits, '_', '-' or '.'")
        self.run = run
        self.root = f"swarm/{run}"

    def clock(self) -> str:
        return f"{self.root}/clock"

    def sensors(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/sensors"

    def cam(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/cam"

    def img(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/img"

    def meas(self, i: int | str = "*") -> str:
        return f"{self.root}/meas/{i}"

    def est(self, i: int | str = "*") -> str:
        return f"{self.root}/est/{i}"

    def cov(self, i: int | str = "*") -> str:
        return f"{self.root}/cov/{i}"

    def init(self, i: int | str = "*") -> str:
        return f"{self.root}/init/{i}"

    def select(self) -> str:
        return f"{self.root}/select"

    def fault(self) -> str:
        """Fault commands (the CLI's, and the world's from the scenario's schedule)."""
        return f"{self.root}/fault"

    def fault_report(self, reporter: str = "*") -> str:
        """What ``reporter`` (``world``, ``supervisor``, ``agent-3``...) carried out."""
        return f"{self.root}/fault/{reporter}"

    def faults(self) -> str:
        """Commands and every report."""
        return f"{self.root}/fault/**"

    def health(self, i: int | str = "*") -> str:
        return f"{self.root}/health/{i}"

    def truth(self) -> str:
        return f"{self.root}/truth"

    def rx(self, i: int | str = "*") -> str:
        return f"{self.root}/rx/{i}"

    def batches(self, i: int | str | None = None) -> str:
        """The ideal radio (links.enabled false): every batch of a step, to every agent
        (``batches``); or what agent i's radio delivers, its graph neighbours' batches
        (``batches/<i>``, an estimator whose ``radio`` is ``"graph"``)."""
        return f"{self.root}/batches" if i is None else f"{self.root}/batches/{i}"

    def links(self) -> str:
        return f"{self.root}/links"

    def rejoin(self, i: int | str = "*", peer: int | str | None = None, size: int | str | None = None) -> str:
        """``rejoin/<i>``: the fates the world gives agent i's rejoin transfers (recorded);
        ``rejoin/<i>/<peer>/<bytes>``: agent i's question about one (a query)."""
        tail = "" if peer is None else f"/{peer}/{size}"
        return f"{self.root}/rejoin/{i}{tail}"

    def claim(self, token: str = "*") -> str:
        return f"{self.root}/claim/{token}"

    def alive(self, role: str = "*", ident: int | str = "*") -> str:
        return f"{self.root}/alive/{role}/{ident}"

    def everything(self) -> str:
        return f"{self.root}/**"


_KEY_RE = re.compile(
    r"^swarm/(?P<run>[^/]+)/(?:"
    r"(?P<clock>clock)|(?P<select>select)|(?P<fault>fault)(?:/[A-Za-z0-9_.-]+)?|(?P<truth>truth)|(?P<links>links)|(?P<batches>batches)"
    r"|sat/(?P<sat>\d+)/(?P<satkind>sensors|cam|img)"
    r"|(?P<idkind>meas|est|health|cov|init|rx|rejoin|batches)/(?P<id>\d+)(?:/\d+/\d+)?"
    r"|claim/(?P<token>[^/]+)"
    r"|alive/(?P<role>[^/]+)/(?P<ident>[^/]+))$"
)


def parse_key(key: str) -> tuple[str, str, int | None]:
    """``(run, kind, satellite id or None)`` of a key; :class:`MessageError` if unknown."""
    return _parse_key(str(key))


@functools.lru_cache(maxsize=4096)  # a run's ~5n keys recur every step
def _parse_key(key: str) -> tuple[str, str, int | None]:
    m = _KEY_RE.match(key)
    if not m:
        raise MessageError(f"unexpected key {str(key)[:200]!r}")
    run = m["run"]
    for k in ("clock", "select", "fault", "truth", "links", "batches"):
        if m[k]:
            return run, k, None
    if m["satkind"]:
        return run, m["satkind"], int(m["sat"])
    if m["idkind"]:
        kind = {"cov": "full_est", "init": "full_est"}.get(m["idkind"], m["idkind"])
        return run, kind, int(m["id"])
    if m["token"]:
        return run, "claim", None
    ident = m["ident"]
    return run, "alive", int(ident) if ident.isdigit() else None


# -- who may use which key ------------------------------------------------------------------
#: The identities of a swarm other than the agents (``agent-<i>``, bound to satellite i).
IDENTITIES = ("world", "selector", "recorder", "cli", "supervisor", "observer", "claimant", "mesh", "viewer")


class Grants(NamedTuple):
    """What one identity may do on the bus, as key expressions (the router allows nothing
    else: :mod:`swarmrt.security` turns this into Zenoh access-control rules)."""

    put: tuple[str, ...] = ()  # put (and delete)
    sub: tuple[str, ...] = ()  # declare a subscriber (and be sent what matches)
    query: tuple[str, ...] = ()  # get (and be sent the replies)
    serve: tuple[str, ...] = ()  # declare a queryable and reply (and be sent the queries)
    token: tuple[str, ...] = ()  # declare a liveliness token
    watch: tuple[str, ...] = ()  # liveliness subscribers and queries


def grants(keys: Keys, identity: str, links: bool = False) -> Grants:
    """The single table of who may say what. Agents hear their peers' batches only through
    the world, the radio: ``batches`` or their own ``batches/<i>`` (the ideal radio) or,
    when the scenario's ``links`` are on, their own ``rx/<i>``; never another agent's
    ``meas/<j>`` or ``batches/<j>``."""
    k = keys
    alive = f"{k.root}/alive/**"
    if identity == "world":
        return Grants(
            put=(k.clock(), k.sensors("*"), k.cam("*"), k.img("*"), k.truth(), k.links(), k.rx("*"), k.batches(),
                 k.batches("*"), k.rejoin("*"), k.select(), k.fault(), k.fault_report("world")),
            sub=(k.est(), k.health(), k.select(), k.faults(), k.meas()),
            serve=(k.init(), k.claim(), k.rejoin("*") + "/*/*"),
            token=(k.alive("world"),), watch=(alive,))
    if m := re.fullmatch(r"agent-(\d+)", identity):
        i = int(m[1])
        return Grants(
            put=(k.meas(i), k.est(i), k.health(i), k.fault_report(identity)),
            sub=(k.clock(), k.sensors(i), k.cam(i), k.img(i), *((k.rx(i),) if links else (k.batches(), k.batches(i))), k.fault()),
            query=(k.init(i), k.cov(), k.rejoin(i, "*", "*")),
            serve=(k.cov(i),), token=(k.alive("agent", i),), watch=(alive,))
    if identity == "selector":
        return Grants(put=(k.select(), k.fault_report("selector")), sub=(k.est(), k.fault(), k.health(), k.clock()),
                      query=(k.cov(),), token=(k.alive("selector"),), watch=(alive,))
    if identity == "recorder":
        return Grants(sub=(k.everything(),), token=(k.alive("recorder"),), watch=(alive,))
    if identity == "cli":  # swarm fault: commands; under compose it carries out process faults and reports them
        return Grants(put=(k.fault(), k.fault_report("cli")), sub=(k.faults(), k.clock(), k.health()),
                      token=(k.alive("cli"),), watch=(alive,))
    if identity == "supervisor":  # swarm run: carries out process faults and reports them
        return Grants(put=(k.fault_report("supervisor"),), sub=(k.faults(), k.clock()), token=(k.alive("supervisor"),),
                      watch=(alive,))
    if identity == "observer":  # read-only telemetry for tools and participants (never the truth)
        return Grants(sub=(k.clock(), k.est(), k.health(), k.select(), k.faults(), k.links()),
                      token=(k.alive("observer"),), watch=(alive,))
    if identity == "viewer":  # the live 3-D view (swarm.live): read-only, and a ground tool: it shows the truth
        return Grants(sub=(k.clock(), k.truth(), k.est(), k.meas(), k.links(), k.faults(), k.health(), k.select()),
                      token=(k.alive("viewer"),), watch=(alive,))
    if identity == "claimant":  # an agent started with --id auto, before it has a satellite
        return Grants(query=(k.claim(),), token=(k.alive("claimant"),))
    if identity == "mesh":  # a router meshed with this one (swarm run --routers 2): it forwards everyone's traffic
        every = (k.everything(),)
        return Grants(put=every, sub=every, query=every, serve=every, token=every, watch=every)
    raise ValueError(f"unknown identity {identity!r} (expected agent-<i> or one of {', '.join(IDENTITIES)})")
