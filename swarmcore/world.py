"""Truth and sensors of the swarm: what ``world_sim`` owns, as pure functions (the truth
side: nothing here is flight software; the filter's set-up is :mod:`swarmcore.agent`).

Every random draw comes from :func:`swarmcore.streams.stream` keyed by (seed, purpose,
step[, satellite]); noise for all n×n relative pairs is drawn every step, so which pairs
are taken never changes the numbers of the others.

Gyro model: a rate-integrating (delta-angle) gyro. The sample for step k→k+1 is the
constant rate that carries the true attitude from ``q_k`` to ``q_{k+1}`` (coning
compensated), plus the bias at ``t_k`` and the exactly discretised noise of the
continuous model ``ω̃ = ω + β + η_v``, ``β̇ = η_u``: the attitude noise ``e`` (rad) and
bias increment ``w`` are drawn jointly with covariance
``[[σ_v² Δt + σ_u² Δt³/3, σ_u² Δt²/2], [σ_u² Δt²/2, σ_u² Δt]]`` per axis, which is what
the filter's Van Loan block for the own satellite assumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels, quat
from .agent import Detections
from .cameras import best_camera
from .dynamics import T_IH as hcw_T_IH
from .dynamics import hcw_noise_cov, hcw_phi, rk4_attitude
from .mekf import AbsoluteMeasurement, SwarmEstimate, init_estimate
from .reference import Chief, chief_of, force_model_of
from .scenario import Scenario
from .sensors import relative_noise_cov, relative_pose_T
from .streams import stream

__all__ = [
    "TruthState",
    "WorldParams",
    "world_params",
    "initial_truth",
    "step_truth",
    "absolute_measurements",
    "SyntheticCameras",
    "initial_estimate",
]


@dataclass(frozen=True)
class TruthState:
    step: int
    t: float
    q_BI: np.ndarray  # (n, 4)
    omega_BI_B: np.ndarray  # (n, 3)
    r_H: np.ndarray  # (n, 3)
    v_H: np.ndarray  # (n, 3)
    bias_B: np.ndarray  # (n, 3) gyro biases
    r_I: np.ndarray | None = None  # (n, 3) ECI positions (orbit.model j2 only; r_H, v_H derive from them)
    v_I: np.ndarray | None = None  # (n, 3) ECI velocities


@dataclass(frozen=True)
class WorldParams:
    seed: int
    n: int
    dt: float
    mean_motion: float
    J: np.ndarray
    truth_substeps: int
    torque_sigma: float  # 0 when the disturbance is off
    accel_sigma: float
    arw: float
    rrw: float  # 0 when the bias walk is off
    star_sigma: float
    gps_sigma: float
    star_enabled: bool
    gps_enabled: bool
    rel: object  # scenario.Relative (frozen-by-convention)
    phi_trans: np.ndarray
    chol_trans: np.ndarray
    chief: Chief | None = None  # the reference orbit (its Hill frame is H)
    orbit_model: str = "hcw"
    force: object = None  # orbit.ForceModel (j2)
    orbit_step_s: float = 10.0
    ballistic: np.ndarray | None = None  # (n,) C_D A / m (j2 with drag)
    gps_sats: tuple[int, ...] | None = None  # only these have a GPS receiver (None: all)


def world_params(sc: Scenario) -> WorldParams:
    d = sc.disturbances
    g = sc.sensors.gyro
    n_e = sc.orbit.mean_motion()
    accel = d.accel_sigma_m_s15 if d.force else 0.0
    Qt = hcw_noise_cov(n_e, sc.dt_s, accel)
    return WorldParams(
        seed=sc.seed,
        n=sc.n_sats,
        dt=sc.dt_s,
        mean_motion=n_e,
        J=sc.spacecraft.J(),
        truth_substeps=sc.truth_substeps,
        torque_sigma=d.torque_sigma_Nm_sqrt_s if d.torque else 0.0,
        accel_sigma=accel,
        arw=g.arw_rad_sqrt_s,
        rrw=g.rrw_rad_s15 if g.bias_walk else 0.0,
        star_sigma=sc.sensors.star_tracker.sigma_rad,
        gps_sigma=sc.sensors.gps.sigma_m,
        star_enabled=sc.sensors.star_tracker.enabled,
        gps_enabled=sc.sensors.gps.enabled,
        rel=sc.sensors.relative,
        phi_trans=hcw_phi(n_e, sc.dt_s),
        chol_trans=_psd_chol(Qt),
        chief=chief_of(sc),
        orbit_model=sc.orbit.model,
        force=force_model_of(sc.orbit) if sc.orbit.model == "j2" else None,
        orbit_step_s=sc.orbit.step_s,
        ballistic=sc.ballistic() if sc.orbit.drag.enabled else None,
        gps_sats=None if sc.sensors.gps.satellites is None else tuple(sc.sensors.gps.satellites),
    )


def frame_T_IH(wp: WorldParams, s: TruthState) -> np.ndarray:
    """Hill → inertial at the truth's time (the chief's frame)."""
    return wp.chief.T_IH(s.t) if wp.chief is not None else hcw_T_IH(wp.mean_motion, s.t)


def _psd_chol(Q: np.ndarray) -> np.ndarray:
    """Cholesky factor of a PSD matrix that may be singular (zero noise)."""
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def initial_truth(sc: Scenario) -> TruthState:
    """Random initial conditions within the scenario's ranges (stream 'init_truth')."""
    rng = stream(sc.seed, "init_truth")
    n = sc.n_sats
    ini = sc.initial
    r = np.zeros((n, 3))
    if ini.layout == "lattice":
        from .graphs import lattice_positions

        r = lattice_positions(n, ini.spacing_m) + rng.uniform(-ini.position_max_m, ini.position_max_m, (n, 3))
    elif ini.layout == "train":
        nominal = np.zeros((n, 3))
        nominal[:, 1] = -ini.spacing_m * np.arange(n)
        r = nominal + rng.uniform(-ini.position_max_m, ini.position_max_m, (n, 3))
    for i in range(n if ini.layout == "random" else 0):
        for _attempt in range(1000):
            cand = rng.uniform(-ini.position_max_m, ini.position_max_m, 3)
            if i == 0 or np.min(np.linalg.norm(r[:i] - cand, axis=1)) >= ini.min_separation_m:
                break
        else:
            raise ValueError(
                f"initial.min_separation_m: cannot place {n} satellites {ini.min_separation_m} m apart "
                f"within ±{ini.position_max_m} m"
            )
        r[i] = cand
    v = rng.uniform(-ini.velocity_max_m_s, ini.velocity_max_m_s, (n, 3))
    if ini.drift_free:
        v[:, 1] = -2.0 * sc.orbit.mean_motion() * r[:, 0]
    w = rng.uniform(-ini.rate_max_rad_s, ini.rate_max_rad_s, (n, 3))
    q = quat.random_quaternion(rng, n) if ini.attitude == "random" else np.tile(quat.IDENTITY, (n, 1))
    bias = rng.normal(0.0, sc.sensors.gyro.bias_initial_sigma_rad_s, (n, 3))
    if sc.orbit.model == "j2":
        # Each satellite's ECI state from the drawn Hill state about the chief; the Hill
        # state the recorder sees is then always the one derived from ECI (round trip ~1e-9 m).
        chief = chief_of(sc)
        r_I, v_I = chief.hill_to_eci(0, r, v)
        r, v = chief.eci_to_hill(0, r_I, v_I)
        return TruthState(0, 0.0, q, w, r, v, bias, r_I, v_I)
    return TruthState(0, 0.0, q, w, r, v, bias)


def _gyro_noise_chol(arw: float, rrw: float, dt: float) -> np.ndarray:
    Q = np.array(
        [
            [arw**2 * dt + rrw**2 * dt**3 / 3.0, rrw**2 * dt**2 / 2.0],
            [rrw**2 * dt**2 / 2.0, rrw**2 * dt],
        ]
    )
    return _psd_chol(Q)


def step_truth(wp: WorldParams, s: TruthState) -> tuple[TruthState, np.ndarray]:
    """Advance the truth by ``dt``; return the new state and the gyro samples (n, 3) of the step."""
    n, k, dt = wp.n, s.step, wp.dt
    torques = None
    if wp.torque_sigma > 0:
        h = dt / wp.truth_substeps
        torques = stream(wp.seed, "torque", k).standard_normal((wp.truth_substeps, n, 3)) * (wp.torque_sigma / np.sqrt(h))
    out = kernels.rk4(s.q_BI, s.omega_BI_B, wp.J, np.linalg.inv(wp.J), dt, wp.truth_substeps, torques)  # compiled (numpy twin: rk4_attitude)
    q1, w1 = rk4_attitude(s.q_BI, s.omega_BI_B, wp.J, dt, wp.truth_substeps, torques) if out is None else out
    r_I = v_I = None
    if wp.orbit_model == "j2":
        assert wp.chief is not None and s.r_I is not None and s.v_I is not None
        from .orbit import propagate

        r_I, v_I = propagate(s.r_I, s.v_I, dt, wp.force, step_s=wp.orbit_step_s, ballistic_m2_kg=wp.ballistic)  # type: ignore[arg-type]
        if wp.accel_sigma > 0:
            # The same white-acceleration increments as the HCW truth (Van Loan over dt in H),
            # turned into I with the chief's frame at t_{k+1}.
            d = stream(wp.seed, "force", k).standard_normal((n, 6)) @ wp.chol_trans.T
            T = wp.chief.T_IH((k + 1) * dt)
            r_I = r_I + d[:, 0:3] @ T.T
            v_I = v_I + d[:, 3:6] @ T.T
        r_H, v_H = wp.chief.eci_to_hill(k + 1, r_I, v_I)
        rv = np.concatenate([r_H, v_H], axis=1)
    else:
        rv = np.concatenate([s.r_H, s.v_H], axis=1) @ wp.phi_trans.T
        if wp.accel_sigma > 0:
            rv = rv + stream(wp.seed, "force", k).standard_normal((n, 6)) @ wp.chol_trans.T
    # Gyro: coning-compensated mean rate + bias at t_k + exact discrete noise.
    rate_mean = quat.quat_to_rotvec(quat.qmul(q1, quat.qconj(s.q_BI))) / dt
    z = stream(wp.seed, "gyro", k).standard_normal((n, 3, 2))
    noise = z @ _gyro_noise_chol(wp.arw, wp.rrw, dt).T  # (n, 3, 2): [attitude noise e, bias step]
    gyro = rate_mean + s.bias_B + noise[..., 0] / dt
    bias1 = s.bias_B + noise[..., 1]
    return TruthState(k + 1, s.t + dt, q1, w1, rv[:, 0:3], rv[:, 3:6], bias1, r_I, v_I), gyro


def absolute_measurements(wp: WorldParams, s: TruthState) -> list[AbsoluteMeasurement]:
    """Every satellite's star tracker and GPS reading at ``s`` (streams 'star', 'gps')."""
    nu_q = stream(wp.seed, "star", s.step).standard_normal((wp.n, 3)) * wp.star_sigma
    nu_r = stream(wp.seed, "gps", s.step).standard_normal((wp.n, 3)) * wp.gps_sigma
    q_meas = quat.normalize(quat.qmul(quat.dq_from_err(nu_q), s.q_BI))
    r_meas = s.r_H + nu_r
    return [
        AbsoluteMeasurement(
            q_BI=q_meas[i] if wp.star_enabled else None,
            r_H=r_meas[i] if wp.gps_enabled and (wp.gps_sats is None or i in wp.gps_sats) else None,
            sigma_att_rad=wp.star_sigma,
            sigma_pos_m=wp.gps_sigma,
        )
        for i in range(wp.n)
    ]


class SyntheticCameras:
    """World side of the synthetic camera model (chapters 4 and 6): what each observer's
    face cameras report of the pairs scheduled for a step, with noise drawn from the
    sensor model at the TRUE position (stream 'rel'; all n×n pairs are drawn every step,
    so which pairs are taken never changes the numbers of the others)."""

    def __init__(self, wp: WorldParams):
        self.wp = wp

    def close(self) -> None:
        pass

    def observe(self, s: TruthState, observer, target, camera_ok: np.ndarray | None = None, predicted=None) -> dict[int, Detections]:
        """``observer → Detections`` for the scheduled pairs; a pair whose face camera is
        off (``camera_ok[i, c]`` False) produces nothing."""
        wp = self.wp
        observer = np.asarray(observer, dtype=int)
        target = np.asarray(target, dtype=int)
        if observer.size == 0:
            return {}
        if wp.rel.model == "bearing":  # type: ignore[attr-defined]
            return self._bearings(s, observer, target, camera_ok)
        q_true, r_true = relative_pose_T(frame_T_IH(wp, s), s.q_BI, s.r_H, observer, target)
        z_all = stream(wp.seed, "rel", s.step).standard_normal((wp.n, wp.n, 6))
        z = z_all[observer, target]
        L = np.linalg.cholesky(relative_noise_cov(wp.rel, r_true))
        nu = np.einsum("mab,mb->ma", L, z)
        q_meas = quat.normalize(quat.qmul(q_true, quat.dq_from_err(nu[:, 0:3])))
        r_meas = r_true + nu[:, 3:6]
        cams = best_camera(r_true)
        keep = np.ones(observer.size, dtype=bool) if camera_ok is None else camera_ok[observer, cams]
        out = {}
        for i in np.unique(observer[keep]):
            rows = np.flatnonzero((observer == i) & keep)
            out[int(i)] = Detections(int(i), target[rows], cams[rows], q_meas[rows], r_meas[rows])
        return out


    def _bearings(self, s: TruthState, observer: np.ndarray, target: np.ndarray, camera_ok: np.ndarray | None) -> dict[int, Detections]:
        """Angles-only camera (``sensors.relative.model: bearing``): the unit line of sight
        in B_i, taken by the face camera nearest it, if :func:`swarmcore.bearing.visibility`
        detects the target (field of view, size / brightness, Earth occultation, Sun
        exclusion; ECI positions from the chief), with isotropic tangent-plane noise σ_px/f_px
        (stream 'rel', its first two components; a detection's ``q_BjBi`` is the identity)."""
        from .bearing import BearingCamera, tangent_basis, visibility
        from .cameras import T_CB

        wp = self.wp
        b = wp.rel.bearing  # type: ignore[attr-defined]
        _q, rho_B = relative_pose_T(frame_T_IH(wp, s), s.q_BI, s.r_H, observer, target)
        u = rho_B / np.linalg.norm(rho_B, axis=1, keepdims=True)
        cams = best_camera(rho_B)
        if s.r_I is not None:
            r_I = s.r_I
        else:
            assert wp.chief is not None
            r_I = wp.chief.hill_to_eci(s.step, s.r_H)[0]
        sun = np.asarray(b.sun_direction_I, dtype=float)
        sun = sun / np.linalg.norm(sun)
        detected = np.zeros(observer.size, dtype=bool)
        for c in np.unique(cams):
            rows = np.flatnonzero(cams == c)
            cam = BearingCamera(f_px=b.f_px, sigma_px=b.sigma_px, half_fov_rad=np.radians(b.half_fov_deg), T_CB=T_CB[c],
                                min_size_px=b.min_size_px, limiting_magnitude=b.limiting_magnitude,
                                sun_exclusion_rad=np.radians(b.sun_exclusion_deg))
            vis = visibility(cam, s.q_BI[observer[rows]], r_I[observer[rows]], r_I[target[rows]], sun,
                             b.target_size_m, b.target_area_m2, b.target_albedo)
            detected[rows] = vis.detected
        z = stream(wp.seed, "rel", s.step).standard_normal((wp.n, wp.n, 6))[observer, target, 0:2]
        E = tangent_basis(u)
        noisy = u + b.sigma_rad * np.einsum("mab,mb->ma", E, z)
        u_meas = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
        keep = detected if camera_ok is None else detected & camera_ok[observer, cams]
        out = {}
        ident = np.tile(quat.IDENTITY, (observer.size, 1))
        for i in np.unique(observer[keep]):
            rows = np.flatnonzero((observer == i) & keep)
            out[int(i)] = Detections(int(i), target[rows], cams[rows], ident[rows], u_meas[rows])
        return out


def initial_estimate(sc: Scenario, truth0: TruthState, own: int, ids: list[int] | None = None) -> SwarmEstimate:
    """Filter ``own``'s prior from ground operations: truth minus an error drawn from its
    initial covariance (stream 'init_est'). ``ids``: only these satellites' rows (ascending,
    ``own`` among them; None: the whole swarm) — the same draws, so a filter of its own
    satellite alone starts from the own row of the whole-swarm prior.

    In the distributed emulator the world hands this to the agent (a prior from ground
    operations); agents never see the truth itself.
    """
    s = sc.filter.initial_sigma
    n = sc.n_sats
    rng = stream(sc.seed, "init_est", own)
    a = rng.standard_normal((n, 3)) * s.att_rad
    dw = rng.standard_normal((n, 3)) * s.rate_rad_s
    dr = rng.standard_normal((n, 3)) * s.pos_m
    dv = rng.standard_normal((n, 3)) * s.vel_m_s
    db = rng.standard_normal(3) * s.bias_rad_s
    q_hat = quat.retract(truth0.q_BI, -a)
    w_hat = truth0.omega_BI_B - dw
    w_hat[own] = truth0.omega_BI_B[own]
    rows = np.arange(n) if ids is None else np.asarray(ids, dtype=int)
    if ids is not None and (own not in rows or np.any(np.diff(rows) <= 0) or rows.min() < 0 or rows.max() >= n):
        raise ValueError(f"initial_estimate: ids {list(rows)} must be ascending satellite ids including {own}")
    return init_estimate(
        step=truth0.step,
        t=truth0.t,
        q_BI=q_hat[rows],
        omega_BI_B=w_hat[rows],
        r_H=(truth0.r_H - dr)[rows],
        v_H=(truth0.v_H - dv)[rows],
        bias_B=truth0.bias_B[own] - db,
        sigmas=s.model_dump(),
        own=int(np.nonzero(rows == own)[0][0]),
    )
