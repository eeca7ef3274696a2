"""Core values ⇄ bus messages (exact: float64 travels as float64, bit for bit).

Arrays go in as ``ndarray.ravel().tolist()`` (the fast way into a packed field) and come
out as ``np.asarray(field)`` (a copy at memory speed). Every function here counts its CPU
time as message handling (:func:`swarmrt.bus.messages.codec_cpu_ms`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from swarmcore.agent import Detections
from swarmcore.estimators import EstimateView, Received, StepReport
from swarmcore.estimators.ci import CiState
from swarmcore.estimators.pairwise import PairwiseState
from swarmcore.mekf import AbsoluteMeasurement, RelativeMeasurements, SwarmEstimate, UpdateReport
from swarmrt.bus.messages import (
    CameraOutput,
    CameraView,
    Detection,
    Estimate,
    EstimatorMessage,
    FullEstimate,
    Images,
    Matrix,
    MeasBatch,
    MessageError,
    Select,
    Sensors,
    StepBatches,
    Truth,
    batch_arrays,
    counted,
    detection_arrays,
    encode,
    forget_arrays,
    pixels,
    replace,
    step_batch_arrays,
)
from swarmrt.bus.messages import (
    CiState as CiStateMsg,
)
from swarmrt.bus.messages import (
    PairwiseState as PairwiseStateMsg,
)

__all__ = [
    "view_msg",
    "ci_state_msg",
    "ci_state",
    "pairwise_state_msg",
    "pairwise_state",
    "received_from_step",
    "received_from_batches",
    "matrix",
    "batch_wire_size",
    "array",
    "estimate_msg",
    "full_estimate_msg",
    "estimate_from_full",
    "estimate_arrays",
    "sensors_msg",
    "absolute_from_sensors",
    "gyro_from_sensors",
    "batch_msg",
    "radio_bytes",
    "relative_from_batches",
    "step_batches_msg",
    "relative_from_step",
    "detections",
    "detections_from_msg",
    "truth_msg",
    "select_msg",
    "pairs_from_select",
    "images_msg",
    "observation_from_images",
]


def _l(a) -> list:
    """A flat list of Python floats (row-major)."""
    return np.asarray(a, dtype=float).ravel().tolist()


def matrix(a) -> Matrix:
    a = np.asarray(a, dtype=float)
    return Matrix(shape=list(a.shape), data=a.ravel().tolist())


_MAX_EXTENT = 2**31 - 1  # no message here holds more; numpy's limits are higher but vary


def array(m: Matrix) -> np.ndarray:
    """A Matrix as an array of its shape (:class:`MessageError` if its length disagrees)."""
    shape = tuple(m.shape)
    need = math.prod(shape)  # exact (numpy's int64 product wraps: a huge shape could "need" 0 numbers)
    if len(m.data) != need:
        raise MessageError(f"array of shape {list(shape)} needs {need} numbers, got {len(m.data)}")
    # An empty array may still name an impossible shape ([2^32, 2^32, 0]): numpy refuses it with
    # one of several messages, so the bound is checked here, once, in its own words.
    if math.prod(d for d in shape if d) > _MAX_EXTENT:
        raise MessageError(f"array of shape {list(shape)} is too big (its non-zero extents "
                           f"multiply past {_MAX_EXTENT})")
    try:
        return np.asarray(m.data, dtype=float).reshape(shape)
    except ValueError as exc:  # anything else numpy refuses, named
        raise MessageError(f"array of shape {list(shape)} is too big or malformed: {exc}") from None


_POSE = np.r_[0:3, 6:9]  # [a, Δr] within a satellite's 12-state block (swarmcore.mekf.observed_indices)


def pose_blocks(P: np.ndarray, n: int) -> np.ndarray:
    """(n, 6, 6) covariance of each satellite's [a, Δr]: the same numbers as
    :func:`swarmcore.sim.pose_cov_blocks` (copies), taken from the diagonal 12×12 blocks
    without gathering the 6n×6n observed submatrix first."""
    d = np.arange(n)
    B = np.asarray(P).reshape(n, 12, n, 12)[d, :, d, :]  # (n, 12, 12) diagonal blocks
    return B[:, _POSE][:, :, _POSE]


def _rows(field, width: int) -> np.ndarray:
    return np.asarray(field, dtype=float).reshape(-1, width)


@counted
def estimate_msg(est: SwarmEstimate, *, run: str, sender: str, own: int, phase: str = "posterior", report: UpdateReport | None = None, **extra) -> Estimate:
    fields: dict[str, Any] = dict(
        run=run,
        sender=sender,
        k=est.step,
        t_s=est.t,
        own=own,
        phase=phase,
        q_BI=_l(est.q_BI),
        omega_BI_B_rad_s=_l(est.omega_BI_B),
        r_H_m=_l(est.r_H),
        v_H_m_s=_l(est.v_H),
        bias_B_rad_s=_l(est.bias_B),
        P_pose=matrix(pose_blocks(est.P, est.n)),
        P_diag=matrix(np.diag(est.P)),
    )
    if report is not None:
        fields.update(
            gate_accepted=report.n_accepted,
            gate_rejected=report.n_rejected,
            nis=report.nis,
            nis_dof=report.nis_dof,
            iterations=report.iterations,
        )
    fields.update(extra)
    return Estimate(**fields)


def estimate_arrays(msg) -> dict:
    """Per-satellite arrays of an Estimate, FullEstimate or Truth message, shaped (n, 4 | 3)."""
    out = {"q_BI": _rows(msg.q_BI, 4)}
    for f in ("omega_BI_B_rad_s", "r_H_m", "v_H_m_s"):
        out[f] = _rows(getattr(msg, f), 3)
    return out


@counted
def view_msg(view: EstimateView, *, run: str, sender: str, phase: str = "posterior", report: StepReport | None = None,
             estimator: str = "full", **extra) -> Estimate:
    """An estimator's claim (:class:`swarmcore.estimators.EstimateView`) as an Estimate. A
    view of every satellite travels as a whole-swarm estimate (no ``ids``), whose numbers
    equal :func:`estimate_msg`'s of the same estimate; any other lists its rows in ``ids``."""
    n_rows = view.ids.size
    whole = view.full is not None and n_rows == view.full.n
    fields: dict[str, Any] = dict(
        run=run,
        sender=sender,
        k=view.step,
        t_s=view.t,
        own=view.own,
        phase=phase,
        q_BI=_l(view.q_BI),
        omega_BI_B_rad_s=_l(view.omega_BI_B),
        r_H_m=_l(view.r_H),
        v_H_m_s=_l(view.v_H),
        bias_B_rad_s=_l(view.bias_B),
        P_pose=matrix(view.P_pose),
        P_diag=matrix(view.P_diag),
        P_rel_pose=matrix(view.P_rel_pose),
        estimator="" if estimator == "full" else estimator,
    )
    if not whole:
        fields["ids"] = np.asarray(view.ids, dtype=np.int64).tolist()
    if report is not None:
        fields.update(
            gate_accepted=report.gate_accepted,
            gate_rejected=report.gate_rejected,
            nis=report.nis if np.isfinite(report.nis) else 0.0,
            nis_dof=report.nis_dof,
            iterations=report.iterations,
            late_used=report.late_used,
            late_dropped=report.late_dropped,
            replayed_steps=report.replayed_steps,
        )
    fields.update(extra)
    return Estimate(**fields)


@counted
def full_estimate_msg(est: SwarmEstimate, *, run: str, sender: str, own: int, ids=None) -> FullEstimate:
    """A complete estimate (``ids``: the satellites of its rows, when not the whole swarm)."""
    return FullEstimate(
        run=run,
        sender=sender,
        k=est.step,
        t_s=est.t,
        own=own,
        q_BI=_l(est.q_BI),
        omega_BI_B_rad_s=_l(est.omega_BI_B),
        r_H_m=_l(est.r_H),
        v_H_m_s=_l(est.v_H),
        bias_B_rad_s=_l(est.bias_B),
        P=matrix(est.P),
        ids=[] if ids is None else np.asarray(ids, dtype=np.int64).tolist(),
    )


@counted
def estimate_from_full(msg: FullEstimate, n: int) -> SwarmEstimate:
    """The estimate a FullEstimate carries: of the whole swarm of ``n``, or of the rows its
    ``ids`` list (a prior of one satellite, for an estimator that keeps only its own)."""
    a = estimate_arrays(msg)
    P = array(msg.P)
    rows = len(msg.ids) or n
    if msg.ids and max(msg.ids) >= n:
        raise ValueError(f"estimate of satellites {list(msg.ids)[:8]}; this swarm has {n}")
    if a["q_BI"].shape != (rows, 4) or P.shape != (12 * rows, 12 * rows):
        raise ValueError(f"estimate is for {a['q_BI'].shape[0]} satellites with P {P.shape}; expected {rows} of this swarm of {n}")
    return SwarmEstimate(
        step=msg.k,
        t=msg.t_s,
        q_BI=a["q_BI"],
        omega_BI_B=a["omega_BI_B_rad_s"],
        r_H=a["r_H_m"],
        v_H=a["v_H_m_s"],
        bias_B=np.asarray(msg.bias_B_rad_s, dtype=float),
        P=P,
    )


@counted
def sensors_msg(*, run: str, k: int, t_s: float, sat: int, gyro, absm: AbsoluteMeasurement | None, sigma_star: float, sigma_gps: float) -> Sensors:
    return Sensors(
        run=run,
        sender="world",
        k=k,
        t_s=t_s,
        sat=sat,
        gyro_rate_B_rad_s=[] if gyro is None else _l(gyro),
        q_BI_star=[] if absm is None or absm.q_BI is None else _l(absm.q_BI),
        r_H_gps_m=[] if absm is None or absm.r_H is None else _l(absm.r_H),
        sigma_star_rad=sigma_star,
        sigma_gps_m=sigma_gps,
    )


@counted
def absolute_from_sensors(msg: Sensors) -> AbsoluteMeasurement | None:
    if not msg.q_BI_star and not msg.r_H_gps_m:
        return None
    return AbsoluteMeasurement(
        q_BI=np.asarray(msg.q_BI_star, dtype=float) if msg.q_BI_star else None,
        r_H=np.asarray(msg.r_H_gps_m, dtype=float) if msg.r_H_gps_m else None,
        sigma_att_rad=msg.sigma_star_rad,
        sigma_pos_m=msg.sigma_gps_m,
    )


def gyro_from_sensors(msg: Sensors) -> np.ndarray | None:
    """The gyro's rate (3,), or None when the message carries none (step 0)."""
    return np.asarray(msg.gyro_rate_B_rad_s, dtype=float) if msg.gyro_rate_B_rad_s else None


@counted
def detections(d: Detections) -> list[Detection]:
    """An observer's synthetic camera detections as message rows."""
    cols = (np.asarray(d.target).tolist(), np.asarray(d.camera).tolist(), np.asarray(d.q_BjBi).tolist(), np.asarray(d.r_ij_Bi).tolist())
    return [Detection(target=t, camera=c, q_BjBi=q, r_ij_Bi_m=r) for t, c, q, r in zip(*cols, strict=True)]


@counted
def detections_from_msg(msg: CameraOutput, camera_ok=None) -> Detections:
    """The detections of a camera-output message, keeping those of cameras ``camera_ok``
    says work (the agent's own belief of its camera health)."""
    target, camera, q, r = detection_arrays(msg)
    d = Detections(observer=msg.sat, target=target, camera=camera, q_BjBi=q, r_ij_Bi=r)
    if camera_ok is not None and len(d) and not np.asarray(camera_ok)[camera].all():
        d = d.subset(np.asarray(camera_ok)[camera])
    return d


@counted
def batch_msg(rel: RelativeMeasurements, cameras: np.ndarray, *, run: str, sender: str, k: int, t_s: float, observer: int,
              estimator: EstimatorMessage | None = None) -> MeasBatch:
    """Observer's batch of step k, with its estimator's message (None: it sends none)."""
    if len(rel) and not (np.asarray(rel.observer) == observer).all():
        raise ValueError(f"a measurement by {sorted(set(np.asarray(rel.observer).tolist()) - {observer})} in the batch of observer {observer}")
    return MeasBatch(
        estimator=estimator,
        run=run,
        sender=sender,
        k=k,
        t_s=t_s,
        observer=observer,
        target=np.asarray(rel.target, dtype=np.int64).tolist(),
        camera=np.asarray(cameras, dtype=np.int64).tolist(),
        q_BjBi=_l(rel.q_BjBi),
        r_ij_Bi_m=_l(rel.r_ij_Bi),
        R_Bi=Matrix(shape=[len(rel), 6, 6], data=_l(rel.R_Bi)),
    )


def radio_bytes(msg: MeasBatch) -> int:
    """The bytes a measurement batch takes on the radio (the link model's size): the
    message as encoded on the bus, less the run id, which the bus key carries and a
    satellite's radio frame would not. The same number in every run of a scenario
    (``swarm sim``, ``swarm run``, compose), whatever the run is called."""
    return len(encode(replace(msg, run="")))


@counted
def relative_from_batches(batches: list[MeasBatch]) -> RelativeMeasurements:
    cols = [(b.observer, batch_arrays(b)) for b in batches if len(b.target)]
    if not cols:
        return RelativeMeasurements.empty()
    return RelativeMeasurements(
        observer=np.concatenate([np.full(len(a[0]), obs, dtype=int) for obs, a in cols]),
        target=np.concatenate([a[0] for _o, a in cols]),
        q_BjBi=np.concatenate([a[1] for _o, a in cols]),
        r_ij_Bi=np.concatenate([a[2] for _o, a in cols]),
        R_Bi=np.concatenate([a[3] for _o, a in cols]),
    )


@counted
def step_batches_msg(batches: list[MeasBatch], *, run: str, k: int, t_s: float) -> StepBatches:
    """The ideal radio's message of step k: ``batches`` (one per observer) laid end to end
    in observer order. Each column is extended from the batch's own (protobuf copies packed
    numbers container to container: at n = 40, 0.2 ms where going through Python floats
    took 3.3 ms, on the world's path every step waits on)."""
    msg = StepBatches(run=run, sender="world", k=k, t_s=t_s)
    ordered = sorted(batches, key=lambda b: b.observer)
    if any(b.HasField("estimator") for b in ordered):
        for b in ordered:
            msg.estimators.append(b.estimator)
    for b in ordered:
        msg.observers.append(b.observer)
        msg.counts.append(len(b.target))
        msg.target.extend(b.target)
        msg.camera.extend(b.camera)
        msg.q_BjBi.extend(b.q_BjBi)
        msg.r_ij_Bi_m.extend(b.r_ij_Bi_m)
        msg.R_Bi.data.extend(b.R_Bi.data)
        forget_arrays(b)  # its decoder kept its columns for a conversion that will not come
    msg.R_Bi.shape.extend([len(msg.target), 6, 6])
    return msg


@counted
def relative_from_step(msg: StepBatches, skip: int | None = None) -> RelativeMeasurements:
    """The measurements of a StepBatches (observer order, as they came), without those of
    observer ``skip`` (the receiver's own, which it already holds)."""
    obs, tgt, q, r, R = step_batch_arrays(msg)
    if skip is not None:
        keep = obs != skip
        if not keep.all():
            obs, tgt, q, r, R = obs[keep], tgt[keep], q[keep], r[keep], R[keep]
    if not len(obs):
        return RelativeMeasurements.empty()
    return RelativeMeasurements(observer=obs, target=tgt, q_BjBi=q, r_ij_Bi=r, R_Bi=R)


@counted
def truth_msg(tr, *, run: str, k: int) -> Truth:
    """The world's true state (:class:`swarmcore.world.TruthState`) at step k."""
    return Truth(
        run=run,
        sender="world",
        k=k,
        t_s=tr.t,
        q_BI=_l(tr.q_BI),
        omega_BI_B_rad_s=_l(tr.omega_BI_B),
        r_H_m=_l(tr.r_H),
        v_H_m_s=_l(tr.v_H),
        gyro_bias_B_rad_s=_l(tr.bias_B),
    )


@counted
def select_msg(observer, target, **fields) -> Select:
    """A Select of the pairs (observer[r], target[r])."""
    return Select(observer=np.asarray(observer, dtype=np.int64).tolist(), target=np.asarray(target, dtype=np.int64).tolist(), **fields)


def pairs_from_select(msg: Select) -> tuple[np.ndarray, np.ndarray]:
    """(observers, targets) of a Select message, as int arrays."""
    return np.asarray(msg.observer, dtype=int), np.asarray(msg.target, dtype=int)


@counted
def images_msg(views, *, run: str, k: int, t_s: float, sat: int, targets) -> Images:
    """One observer's rendered views (:class:`swarmvision.views.View`) as an Images message."""
    out = []
    for v in views:
        it = v.intrinsics
        ims = [np.ascontiguousarray(im, dtype=np.uint8) for im in v.images]
        if any(im.shape != (int(it.height), int(it.width)) for im in ims):
            raise ValueError(f"camera {v.camera}: images of shapes {[im.shape for im in ims]} for a {it.height}×{it.width} camera")
        out.append(
            CameraView(
                camera=int(v.camera),
                T_CB=_l(v.T_CB),
                r_C_B_m=_l(v.r_C_B),
                width_px=int(it.width),
                height_px=int(it.height),
                fx_px=float(it.fx),
                fy_px=float(it.fy),
                cx_px=float(it.cx),
                cy_px=float(it.cy),
                target=int(v.target),
                baseline_m=float(v.baseline_m),
                images_mono8=[im.tobytes() for im in ims],
            )
        )
    return Images(run=run, sender="world", k=k, t_s=t_s, sat=sat, targets=sorted(int(j) for j in targets), views=out)


@counted
def observation_from_images(msg: Images):
    """An Images message as the pose pipelines take it (:class:`swarmvision.views.Observation`)."""
    from swarmcore.cameras import Intrinsics
    from swarmvision.views import Observation, View

    out, pix = [], iter(pixels(msg))
    for m in msg.views:
        ims = tuple(next(pix) for _ in m.images_mono8)
        intr = Intrinsics(m.width_px, m.height_px, m.fx_px, m.fy_px, m.cx_px, m.cy_px)
        out.append(
            View(msg.sat, m.camera, msg.k, msg.t_s, ims, np.array(m.T_CB, dtype=float).reshape(3, 3), np.array(m.r_C_B_m, dtype=float),
                 intr, target=m.target, baseline_m=m.baseline_m)
        )
    return Observation(out, np.asarray(msg.targets, dtype=int))


def batch_wire_size(run: str = "sim", to_msg=None):
    """``wire_size(observer, k, t, rel, cameras, message)``: the bytes of an observer's
    measurement batch and its estimator's message on the radio (:func:`radio_bytes`: as its
    agent publishes them, less the run id; so ``run`` does not change it). ``to_msg``: the
    estimator's message → EstimatorMessage (:class:`swarmrt.estimators.EstimatorCodec`;
    None: none is sent). The link model of the in-process simulator needs it."""

    def size(observer: int, k: int, t: float, rel, cameras, message=None) -> int:
        est = None if to_msg is None or message is None else to_msg(message)
        return radio_bytes(batch_msg(rel, cameras, run=run, sender=f"agent-{observer}", k=k, t_s=t, observer=observer, estimator=est))

    return size


# ------------------------------------------------------------------ estimator messages
@counted
def ci_state_msg(s: CiState) -> CiStateMsg:
    return CiStateMsg(q_BI=_l(s.q_BI), omega_BI_B_rad_s=_l(s.omega_BI_B), r_H_m=_l(s.r_H), v_H_m_s=_l(s.v_H), P_pose=matrix(s.P_pose))


@counted
def ci_state(m: CiStateMsg, sat: int, step: int) -> CiState:
    return CiState(sat, step, np.asarray(m.q_BI, dtype=float), np.asarray(m.omega_BI_B_rad_s, dtype=float),
                   np.asarray(m.r_H_m, dtype=float), np.asarray(m.v_H_m_s, dtype=float), array(m.P_pose))


@counted
def pairwise_state_msg(s: PairwiseState) -> PairwiseStateMsg:
    return PairwiseStateMsg(q_BI=_l(s.q_BI), omega_BI_B_rad_s=_l(s.omega_BI_B), r_H_m=_l(s.r_H), v_H_m_s=_l(s.v_H),
                            bias_B_rad_s=_l(s.bias_B), P=matrix(s.P), partners=np.asarray(s.partners, dtype=np.int64).tolist(),
                            sigma=Matrix(shape=[len(s.partners), 12, 12], data=_l(s.sigma)))


@counted
def pairwise_state(m: PairwiseStateMsg, sat: int, step: int) -> PairwiseState:
    return PairwiseState(sat, step, np.asarray(m.q_BI, dtype=float), np.asarray(m.omega_BI_B_rad_s, dtype=float),
                         np.asarray(m.r_H_m, dtype=float), np.asarray(m.v_H_m_s, dtype=float), np.asarray(m.bias_B_rad_s, dtype=float),
                         array(m.P), np.asarray(m.partners, dtype=int), array(m.sigma).reshape(-1, 12, 12))


@counted
def received_from_step(msg: StepBatches, skip: int | None, payload_of) -> list[Received]:
    """A StepBatches as what the radio delivered of each observer (but ``skip``, the
    receiver's own): its batch and its estimator's message (``payload_of(EstimatorMessage,
    sender, k)`` → the estimator's value, or None). Both are made when the estimator first
    reads them (an agent hears every peer; an estimator may read a few)."""
    obs, tgt, q, r, R = step_batch_arrays(msg)
    out = []
    start = 0
    ests = list(msg.estimators)
    k = int(msg.k)
    for idx, (o, c) in enumerate(zip(msg.observers, msg.counts)):
        sl = slice(start, start + c)
        start += c
        if o == skip:
            continue

        def rel(sl=sl, c=c) -> RelativeMeasurements:
            if not c:
                return RelativeMeasurements.empty()
            return RelativeMeasurements(observer=obs[sl], target=tgt[sl], q_BjBi=q[sl], r_ij_Bi=r[sl], R_Bi=R[sl])

        pay = None
        if ests and ests[idx].kind:
            e, sender = ests[idx], int(o)
            pay = lambda e=e, sender=sender: payload_of(e, sender, k)  # noqa: E731  (made when read)
        out.append(Received(int(o), k, rel, pay))
    return out


@counted
def received_from_batches(batches: list[MeasBatch], payload_of) -> list[Received]:
    """Batches the radio delivered (links on), each with its estimator's message."""
    out = []
    for b in batches:
        rel = relative_from_batches([b])
        pay = payload_of(b.estimator, int(b.observer), int(b.k)) if b.HasField("estimator") and b.estimator.kind else None
        out.append(Received(int(b.observer), int(b.k), rel, pay))
    return out
