"""What the schema cannot say, checked (:func:`validate`): the header, finite numbers, unit
quaternions, symmetric positive-definite covariances, array lengths against their shapes,
ids within the swarm, string enumerations; the shallow readings (:data:`SHALLOW_KINDS`) and
the lazy check of one peer's estimator message (:func:`check_estimator_message`); and the
memo of the arrays validation computed, which the conversions reuse (:func:`batch_arrays`,
:func:`step_batch_arrays`, :func:`detection_arrays`, :func:`forget_arrays`). A failure is a
:class:`~swarmrt.bus.wire.MessageError` naming the field."""

from __future__ import annotations

import collections
import functools
import itertools
import math
import re
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from swarmcore.scenario import STALL_FAULTS
from swarmrt.bus.v1.claim_pb2 import Claim
from swarmrt.bus.v1.clock_pb2 import Clock, Recorded
from swarmrt.bus.v1.common_pb2 import Matrix
from swarmrt.bus.v1.estimate_pb2 import Estimate, FullEstimate
from swarmrt.bus.v1.estimators_pb2 import EstimatorMessage
from swarmrt.bus.v1.fault_pb2 import Fault, FaultAction, FaultPhase
from swarmrt.bus.v1.health_pb2 import Health
from swarmrt.bus.v1.images_pb2 import Images
from swarmrt.bus.v1.links_pb2 import Delivery, LinkStats, RejoinFate
from swarmrt.bus.v1.measurements_pb2 import MeasBatch, StepBatches
from swarmrt.bus.v1.selection_pb2 import Select
from swarmrt.bus.v1.sensors_pb2 import CameraOutput, Sensors
from swarmrt.bus.v1.truth_pb2 import Truth
from swarmrt.bus.wire import MAX_SAT_ID, MODELS, QUAT_TOL, RUN_ID_RE, SCHEMA_VERSION, SYM_TOL, MessageError


def wire_names(enum, prefix: str, below: int | None = None) -> tuple[str, ...]:
    """The names a schema enum's values go by on the wire (proto/swarm/v1/fault.proto): the
    value's name without ``prefix``, lower case, "-" for "_" (``FAULT_ACTION_KILL_AGENT``:
    ``kill-agent``); the unspecified value (0) left out; ``below``: only the values numbered
    below it."""
    return tuple(v.name.removeprefix(prefix).lower().replace("_", "-") for v in enum.DESCRIPTOR.values
                 if v.number and (below is None or v.number < below))


# The fault actions and phases as the schema declares them, the list the Rust agent's checks
# are generated from; swarmcore.scenario's (the scenario model's, which imports no schema)
# are the same (tests/test_proto_schema.py). Numbered below 50: the action needs a satellite.
WIRE_FAULT_ACTIONS = wire_names(FaultAction, "FAULT_ACTION_")
WIRE_TARGETED_FAULTS = wire_names(FaultAction, "FAULT_ACTION_", below=50)
WIRE_FAULT_PHASES = wire_names(FaultPhase, "FAULT_PHASE_")


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
    return RUN_ID_RE.fullmatch(run) is not None


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
    if not (math.isfinite(m.recorder_waited_s) and m.recorder_waited_s >= 0.0):
        raise MessageError(f"recorder_waited_s: {m.recorder_waited_s} is not a finite number of seconds >= 0")


def _recorded(m: Recorded, top: int) -> None:
    pass  # the header only (its k checked like every message's)


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
    _choice("action", m.action, WIRE_FAULT_ACTIONS)
    _choice("phase", m.phase, WIRE_FAULT_PHASES)
    if m.HasField("target"):
        _id(top, "target", m.target)
    elif m.action in WIRE_TARGETED_FAULTS:
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
    "recorded": _recorded,
}
_SHALLOW: dict[str, Callable[[Any, int], None]] = {"est": _est_shallow, "batches": _step_batches_shallow}
SHALLOW_KINDS = tuple(_SHALLOW)
_KIND_OF = {cls: kind for kind, cls in MODELS.items()}
