"""Core values ⇄ bus messages (exact: float64 travels as float64, bit for bit).

Arrays go in as ``ndarray.ravel().tolist()`` (the fast way into a packed field) and come
out as ``np.asarray(field)`` (a copy at memory speed). Every function here counts its CPU
time as message handling (:func:`swarm.bus.messages.codec_cpu_ms`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from swarmcore.agent import Detections
from swarmcore.mekf import AbsoluteMeasurement, RelativeMeasurements, SwarmEstimate, UpdateReport

from .messages import (
    CameraOutput,
    CameraView,
    Detection,
    Estimate,
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

__all__ = [
    "matrix",
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


def array(m: Matrix) -> np.ndarray:
    """A Matrix as an array of its shape (:class:`MessageError` if its length disagrees)."""
    shape = tuple(m.shape)
    need = int(np.prod(shape, dtype=np.int64))
    if len(m.data) != need:
        raise MessageError(f"array of shape {list(shape)} needs {need} numbers, got {len(m.data)}")
    return np.asarray(m.data, dtype=float).reshape(shape)


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
def full_estimate_msg(est: SwarmEstimate, *, run: str, sender: str, own: int) -> FullEstimate:
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
    )


@counted
def estimate_from_full(msg: FullEstimate, n: int) -> SwarmEstimate:
    a = estimate_arrays(msg)
    P = array(msg.P)
    if a["q_BI"].shape != (n, 4) or P.shape != (12 * n, 12 * n):
        raise ValueError(f"estimate is for {a['q_BI'].shape[0]} satellites with P {P.shape}; this swarm has {n}")
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
def batch_msg(rel: RelativeMeasurements, cameras: np.ndarray, *, run: str, sender: str, k: int, t_s: float, observer: int) -> MeasBatch:
    if len(rel) and not (np.asarray(rel.observer) == observer).all():
        raise ValueError(f"a measurement by {sorted(set(np.asarray(rel.observer).tolist()) - {observer})} in the batch of observer {observer}")
    return MeasBatch(
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
    for b in sorted(batches, key=lambda b: b.observer):
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
