"""Core values ⇄ bus messages (exact: floats round-trip bit for bit)."""

from __future__ import annotations

import numpy as np

from swarmcore.agent import Detections
from swarmcore.mekf import AbsoluteMeasurement, RelativeMeasurements, SwarmEstimate, UpdateReport
from swarmcore.metrics import pose_cov_blocks

from .messages import B64Array, CameraOutput, Detection, Estimate, FullEstimate, Images, MeasBatch, RelMeas, Sensors, ViewMeta

__all__ = [
    "estimate_msg",
    "full_estimate_msg",
    "estimate_from_full",
    "sensors_msg",
    "absolute_from_sensors",
    "batch_msg",
    "relative_from_batches",
    "detections",
    "detections_from_msg",
    "images_msg",
    "observation_from_images",
]


def _l(a) -> list:
    return np.asarray(a, dtype=float).tolist()


def estimate_msg(est: SwarmEstimate, *, run: str, sender: str, own: int, phase: str = "posterior", report: UpdateReport | None = None, **extra) -> Estimate:
    fields = dict(
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
        P_pose=B64Array.of(pose_cov_blocks(est.P, est.n)),
        P_diag=B64Array.of(np.diag(est.P)),
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
        P=B64Array.of(est.P),
    )


def estimate_from_full(msg: FullEstimate, n: int) -> SwarmEstimate:
    P = msg.P.array()
    q = np.asarray(msg.q_BI, dtype=float)
    if q.shape != (n, 4) or P.shape != (12 * n, 12 * n):
        raise ValueError(f"estimate is for {q.shape[0]} satellites with P {P.shape}; this swarm has {n}")
    return SwarmEstimate(
        step=msg.k,
        t=msg.t_s,
        q_BI=q,
        omega_BI_B=np.asarray(msg.omega_BI_B_rad_s, dtype=float),
        r_H=np.asarray(msg.r_H_m, dtype=float),
        v_H=np.asarray(msg.v_H_m_s, dtype=float),
        bias_B=np.asarray(msg.bias_B_rad_s, dtype=float),
        P=P,
    )


def sensors_msg(*, run: str, k: int, t_s: float, sat: int, gyro, absm: AbsoluteMeasurement | None, sigma_star: float, sigma_gps: float) -> Sensors:
    return Sensors(
        run=run,
        sender="world",
        k=k,
        t_s=t_s,
        sat=sat,
        gyro_rate_B_rad_s=None if gyro is None else _l(gyro),
        q_BI_star=None if absm is None or absm.q_BI is None else _l(absm.q_BI),
        r_H_gps_m=None if absm is None or absm.r_H is None else _l(absm.r_H),
        sigma_star_rad=sigma_star,
        sigma_gps_m=sigma_gps,
    )


def absolute_from_sensors(msg: Sensors) -> AbsoluteMeasurement | None:
    if msg.q_BI_star is None and msg.r_H_gps_m is None:
        return None
    return AbsoluteMeasurement(
        q_BI=None if msg.q_BI_star is None else np.asarray(msg.q_BI_star, dtype=float),
        r_H=None if msg.r_H_gps_m is None else np.asarray(msg.r_H_gps_m, dtype=float),
        sigma_att_rad=msg.sigma_star_rad,
        sigma_pos_m=msg.sigma_gps_m,
    )


def detections(d: Detections) -> list[Detection]:
    """An observer's synthetic camera detections as message rows."""
    return [
        Detection(target=int(d.target[m]), camera=int(d.camera[m]), q_BjBi=_l(d.q_BjBi[m]), r_ij_Bi_m=_l(d.r_ij_Bi[m]))
        for m in range(len(d))
    ]


def detections_from_msg(msg: CameraOutput, camera_ok=None) -> Detections:
    """The detections of a camera-output message, keeping those of cameras ``camera_ok``
    says work (the agent's own belief of its camera health)."""
    rows = [d for d in msg.detections if camera_ok is None or camera_ok[d.camera]]
    return Detections(
        observer=msg.sat,
        target=np.array([d.target for d in rows], dtype=int),
        camera=np.array([d.camera for d in rows], dtype=int),
        q_BjBi=np.array([d.q_BjBi for d in rows], dtype=float).reshape(-1, 4),
        r_ij_Bi=np.array([d.r_ij_Bi_m for d in rows], dtype=float).reshape(-1, 3),
    )


def batch_msg(rel: RelativeMeasurements, cameras: np.ndarray, *, run: str, sender: str, k: int, t_s: float, observer: int) -> MeasBatch:
    return MeasBatch(
        run=run,
        sender=sender,
        k=k,
        t_s=t_s,
        observer=observer,
        meas=[
            RelMeas(
                observer=int(rel.observer[m]),
                target=int(rel.target[m]),
                camera=int(cameras[m]),
                q_BjBi=_l(rel.q_BjBi[m]),
                r_ij_Bi_m=_l(rel.r_ij_Bi[m]),
                R_Bi=_l(rel.R_Bi[m].ravel()),
            )
            for m in range(len(rel))
        ],
    )


def relative_from_batches(batches: list[MeasBatch]) -> RelativeMeasurements:
    rows = [m for b in batches for m in b.meas]
    if not rows:
        return RelativeMeasurements.empty()
    return RelativeMeasurements(
        observer=np.array([m.observer for m in rows], dtype=int),
        target=np.array([m.target for m in rows], dtype=int),
        q_BjBi=np.array([m.q_BjBi for m in rows], dtype=float),
        r_ij_Bi=np.array([m.r_ij_Bi_m for m in rows], dtype=float),
        R_Bi=np.array([m.R_Bi for m in rows], dtype=float).reshape(-1, 6, 6),
    )


def images_msg(views, *, run: str, k: int, t_s: float, sat: int, targets) -> Images:
    """One observer's rendered views (:class:`swarmvision.views.View`) as an Images message."""
    metas, pixels = [], []
    for v in views:
        it = v.intrinsics
        metas.append(
            ViewMeta(
                camera=int(v.camera),
                T_CB=_l(np.asarray(v.T_CB, dtype=float).ravel()),
                r_C_B_m=_l(v.r_C_B),
                width_px=int(it.width),
                height_px=int(it.height),
                fx_px=float(it.fx),
                fy_px=float(it.fy),
                cx_px=float(it.cx),
                cy_px=float(it.cy),
                target=int(v.target),
                baseline_m=float(v.baseline_m),
                n_images=len(v.images),
            )
        )
        pixels.extend(v.images)
    msg = Images(run=run, sender="world", k=k, t_s=t_s, sat=sat, targets=sorted(int(j) for j in targets), views=metas)
    return msg.with_pixels(pixels)


def observation_from_images(msg: Images):
    """An Images message as the pose pipelines take it (:class:`swarmvision.views.Observation`)."""
    from swarmcore.cameras import Intrinsics
    from swarmvision.views import Observation, View

    out, pix = [], iter(msg.pixels)
    for m in msg.views:
        ims = tuple(next(pix) for _ in range(m.n_images))
        intr = Intrinsics(m.width_px, m.height_px, m.fx_px, m.fy_px, m.cx_px, m.cy_px)
        out.append(
            View(msg.sat, m.camera, msg.k, msg.t_s, ims, np.array(m.T_CB, dtype=float).reshape(3, 3), np.array(m.r_C_B_m, dtype=float),
                 intr, target=m.target, baseline_m=m.baseline_m)
        )
    return Observation(out, np.asarray(msg.targets, dtype=int))
