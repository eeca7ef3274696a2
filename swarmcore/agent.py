"""Flight software of one satellite: its filter's set-up, its step, and late measurements.

What a ``sat_agent`` runs and what the in-process simulator runs for every satellite,
with the same calls in the same order (that is what makes their numbers equal). Nothing
here reads truth: inputs are the satellite's own sensor readings, its own camera
outputs and the relative measurement batches its radio delivered.

One step k of satellite ``own`` (t_k = k dt):

1. predict from k−1 to k with its own gyro sample of that interval (none at k = 0);
2. update with its own absolute reading (star tracker, GPS) and every relative
   measurement of step k it holds, in canonical order (by observer, then target).

Late (out-of-sequence) measurements: a batch taken at step s < k that arrives at k.
``late: replay`` keeps a bounded history (``history_steps``) of each step's prior, gyro
input and applied measurements, inserts the late ones at their own step and re-runs the
filter forward from there (reprocessing: exact for the filter's linearisation schedule,
so delivering a batch late gives the posterior of delivering it on time, to round-off).
Older than the history, or ``late: drop``: dropped and counted. The centralized
reference's late peer absolute readings (star tracker, GPS that came over the radio) are
inserted and replayed the same way (``late_absolute``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .cameras import best_camera
from .mekf import (
    Absolute,
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    UpdateReport,
    predict,
    update,
)
from .reference import chief_of, force_model_of
from .scenario import Scenario
from .sensors import relative_noise_cov

__all__ = [
    "filter_params",
    "usable",
    "filter_step",
    "Detections",
    "SyntheticPoseEstimator",
    "AgentFilter",
    "LateReport",
]


def filter_params(sc: Scenario, own: int) -> FilterParams:
    """The filter of satellite ``own`` as the scenario configures it."""
    f = sc.filter
    j2_frame = sc.orbit.model == "j2"
    bearing = sc.sensors.relative.model == "bearing"
    j2 = sc.filter_dynamics() == "j2"
    drag = j2 and sc.orbit.drag.enabled
    return FilterParams(
        n=sc.n_sats,
        own=own,
        dt=sc.dt_s,
        mean_motion=sc.orbit.mean_motion(),
        chief=chief_of(sc) if j2_frame else None,
        dynamics="j2" if j2 else "hcw",
        force=force_model_of(sc.orbit) if j2 else None,
        orbit_step_s=sc.orbit.step_s,
        ballistic=sc.ballistic() if drag else None,
        chief_ballistic=sc.orbit.drag.chief_ballistic_m2_kg if drag else None,
        relative_kind="bearing" if bearing else "pose",
        J=sc.spacecraft.J(),
        arw=sc.sensors.gyro.arw_rad_sqrt_s,
        rrw=sc.sensors.gyro.rrw_rad_s15,
        torque=sc.disturbances.torque_sigma_Nm_sqrt_s,
        accel=sc.disturbances.accel_sigma_m_s15,
        att_rw_other=f.att_rw_other_rad_sqrt_s,
        pos_rw=f.pos_rw_m_sqrt_s,
        gate_threshold=f.gate.threshold(dof=2 if bearing else 6),
        update_method=f.update,
        rk4_substeps=f.rk4_substeps,
        max_iterations=f.max_iterations,
        iterate_above_rad=f.iterate_above_rad,
        missing_gyro_rate_sigma=f.initial_sigma.rate_rad_s,
    )


def filter_step(
    est: SwarmEstimate,
    params: FilterParams,
    gyro_rate_B: np.ndarray | None,
    absolute: AbsoluteMeasurement | None,
    relative: RelativeMeasurements,
    mode: str = "cooperative",
    propagate: bool = True,
) -> tuple[SwarmEstimate, UpdateReport]:
    """One step of one filter: predict (unless ``propagate`` is False), then update with
    the measurements this filter uses (``isolated``: only its own) in canonical order."""
    if propagate:
        est = predict(est, params, gyro_rate_B)
    return update(est, params, absolute, usable(relative, params.own, mode))


def usable(relative: RelativeMeasurements, own: int, mode: str) -> RelativeMeasurements:
    """The relative measurements a filter in ``mode`` applies, in canonical order."""
    if mode == "isolated":
        relative = relative.subset(relative.observer == own)
    return relative.canonical()


# --------------------------------------------------------------------- camera outputs
@dataclass(frozen=True)
class Detections:
    """What an observer's face cameras report at one step (synthetic camera model):
    relative poses of targets, with the camera that saw each. No covariance: the agent's
    pose estimator attaches the one it believes (:class:`SyntheticPoseEstimator`)."""

    observer: int
    target: np.ndarray  # (m,) int
    camera: np.ndarray  # (m,) int, 0..5
    q_BjBi: np.ndarray  # (m, 4)
    r_ij_Bi: np.ndarray  # (m, 3) m

    def __len__(self) -> int:
        return int(self.target.shape[0])

    def subset(self, idx) -> Detections:
        return Detections(self.observer, self.target[idx], self.camera[idx], self.q_BjBi[idx], self.r_ij_Bi[idx])


class SyntheticPoseEstimator:
    """Agent side of the synthetic camera model: a detection becomes a relative
    measurement with the noise covariance the sensor model gives for the MEASURED
    position (what a camera pipeline knows), :func:`swarmcore.sensors.relative_noise_cov`."""

    needs_prediction = False

    def __init__(self, sc: Scenario):
        self.rel = sc.sensors.relative
        # Bearings are shared in I, turned with the observer's own predicted attitude: both
        # the simulator and sat_agent predict before they measure and always hand the
        # prediction over, so no image-pipeline path (``needs_prediction``) is needed.

    @classmethod
    def from_relative(cls, rel) -> SyntheticPoseEstimator:
        """From the ``sensors.relative`` section alone."""
        self = cls.__new__(cls)
        self.rel = rel
        return self

    def measure(self, observer: int, dets: Detections | None, predicted: SwarmEstimate | None = None, step: int | None = None):
        """``(RelativeMeasurements, camera ids)`` of this observer's detections."""
        if dets is None or not len(dets):
            return RelativeMeasurements.empty(), np.zeros(0, dtype=int)
        m = len(dets)
        if self.rel.model == "bearing":
            return self._bearings(observer, dets, predicted)
        rel = RelativeMeasurements(
            np.full(m, observer, dtype=int),
            np.asarray(dets.target, dtype=int),
            np.asarray(dets.q_BjBi, dtype=float),
            np.asarray(dets.r_ij_Bi, dtype=float),
            relative_noise_cov(self.rel, dets.r_ij_Bi),
        )
        return rel, np.asarray(dets.camera, dtype=int)

    def _bearings(self, observer: int, dets: Detections, predicted: SwarmEstimate | None):
        return inertial_bearings(observer, dets, predicted, self.rel.bearing.sigma_rad)


def _bearing_row(predicted: SwarmEstimate, observer: int) -> int | None:
    """The observer's row in a prediction (a full-swarm one holds every id in order; an
    own-state estimator's, its own satellite alone, row 0)."""
    if predicted.n == 1:
        return 0
    return observer if predicted.n > observer else None


def bearing_noise_layout(sigma_rad: float, m: int) -> np.ndarray:
    """(m, 6, 6) covariance of m bearings in the 6-row layout of a pose measurement
    (:func:`swarmcore.mekf.bearing_residuals_padded`): σ² I₂ on the tangent-plane residual,
    identity on the four unused rows."""
    R = np.broadcast_to(np.eye(6), (m, 6, 6)).copy()
    R[:, 0:2, 0:2] = sigma_rad**2 * np.eye(2)
    return R


def inertial_bearings(observer: int, dets: Detections, predicted: SwarmEstimate | None, sigma_rad: float):
    """A camera's lines of sight (unit, B_i) → the inertial unit vectors an observer shares:
    ``ũ_I = T(q̂_i)ᵀ ũ_B`` with its own predicted attitude, and R = (σ² + σ_a²) I₂ with σ_a²
    the mean variance of that attitude (isotropic attitude error seen in the tangent
    plane). Without a prediction (a restarted agent's first step) nothing is shared."""
    from .quat import attitude_matrix

    m = len(dets)
    row = None if predicted is None else _bearing_row(predicted, observer)
    if predicted is None or row is None or m == 0:
        return RelativeMeasurements.empty(), np.zeros(0, dtype=int)
    T = attitude_matrix(predicted.q_BI[row])
    u_I = np.asarray(dets.r_ij_Bi, dtype=float) @ T
    a = 12 * row
    var_att = float(np.mean(np.diag(predicted.P[a : a + 3, a : a + 3])))
    ident = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (m, 1))
    rel = RelativeMeasurements(np.full(m, observer, dtype=int), np.asarray(dets.target, dtype=int), ident, u_I,
                               bearing_noise_layout(float(np.sqrt(sigma_rad**2 + var_att)), m))
    return rel, np.asarray(dets.camera, dtype=int)


def face_cameras_of(r_ij_Bi: np.ndarray) -> np.ndarray:
    """The face camera that sees each line of sight (the one nearest its boresight)."""
    return best_camera(r_ij_Bi) if len(r_ij_Bi) else np.zeros(0, dtype=int)


# --------------------------------------------------------------------- the agent's filter
@dataclass
class _Record:
    """What the filter did at one step: enough to do it again with more measurements."""

    step: int
    prior: SwarmEstimate  # after predicting to this step, before its update
    absolute: Absolute  # the own reading, or {sat: reading} (the centralized reference)
    relative: RelativeMeasurements  # applied, canonical
    updated: bool = True  # False: a coasted step (posterior = prior) until measurements come
    gyro_next: np.ndarray | None = None  # the gyro sample used to predict to step + 1


@dataclass
class LateReport:
    """What became of the late measurements handed to one :meth:`AgentFilter.step`."""

    used: int = 0  # measurements inserted at their own step (replay)
    dropped: int = 0  # older than the history, or ``late: drop``
    replayed_steps: int = 0  # filter steps re-run
    oldest_step: int | None = None  # the earliest step replayed from


@dataclass
class AgentFilter:
    """One satellite's full-swarm filter with its history (see the module docstring).

    ``est`` is either the posterior of step ``est.step`` or, while ``prior_pending``, its
    prior (just predicted, or the initial estimate), whose update :meth:`step` applies.
    """

    params: FilterParams
    est: SwarmEstimate
    mode: str = "cooperative"
    late: Literal["replay", "drop"] = "drop"
    history_steps: int = 0
    prior_pending: bool = True
    _hist: dict[int, _Record] = field(default_factory=dict, repr=False)

    def predict_to(self, k: int, gyro: np.ndarray | None) -> SwarmEstimate:
        """Predict the current posterior to step ``k = est.step + 1`` with the gyro sample
        of that interval; the update of step ``k`` follows in :meth:`step`."""
        if k != self.est.step + 1 or self.prior_pending:
            raise ValueError(f"predict_to({k}) from step {self.est.step} (prior pending: {self.prior_pending})")
        rec = self._hist.get(self.est.step)
        if rec is not None:
            rec.gyro_next = None if gyro is None else np.array(gyro, dtype=float)
        self.est = predict(self.est, self.params, gyro)
        self.prior_pending = True
        return self.est

    def coast_to(self, k: int, gyro_of) -> None:
        """Bring the filter to a posterior at step ``k − 1`` across steps it missed:
        predictions only (no measurements). ``gyro_of(s)`` gives the gyro sample for the
        interval s−1 → s (or None)."""
        if self.prior_pending and self.est.step < k:
            self._close_pending()
        while self.est.step < k - 1:
            self.predict_to(self.est.step + 1, gyro_of(self.est.step + 1))
            self._close_pending()

    def _close_pending(self) -> None:
        """A step without measurements: its posterior is its prior."""
        self._record(self.est.step, self.est, None, RelativeMeasurements.empty(), updated=False)
        self.prior_pending = False

    def step(
        self,
        k: int,
        gyro: np.ndarray | None,
        absolute: Absolute,
        relative: RelativeMeasurements,
        late: dict[int, RelativeMeasurements] | None = None,
        late_absolute: dict[int, dict[int, AbsoluteMeasurement]] | None = None,
    ) -> tuple[UpdateReport, LateReport]:
        """Step ``k``: insert ``late`` measurements (taken at earlier steps) and replay,
        then predict to k (unless :meth:`predict_to` already did) and update.
        ``late_absolute`` ``{step: {sat: reading}}``: peers' absolute readings of earlier
        steps that came late (the centralized reference), inserted and replayed alike."""
        lrep = self._insert_late(late or {}, late_absolute or {})
        if not self.prior_pending:
            self.predict_to(k, gyro)
        if self.est.step != k:
            raise ValueError(f"step({k}) with the filter at step {self.est.step}")
        prior = self.est
        rel = usable(relative, self.params.own, self.mode)
        self.est, rep = update(prior, self.params, absolute, rel)
        self.prior_pending = False
        self._record(k, prior, absolute, rel)
        return rep, lrep

    # -- history ------------------------------------------------------------------
    def _record(self, k: int, prior: SwarmEstimate, absolute, rel: RelativeMeasurements, updated: bool = True) -> None:
        if self.late != "replay" or self.history_steps <= 0:
            return
        self._hist[k] = _Record(k, prior, absolute, rel, updated)
        for s in [s for s in self._hist if s < k - self.history_steps]:
            del self._hist[s]

    def _insert_late(self, late: dict[int, RelativeMeasurements],
                     late_absolute: dict[int, dict[int, AbsoluteMeasurement]] | None = None) -> LateReport:
        rep = LateReport()
        last = self.est.step - 1 if self.prior_pending else self.est.step  # the last updated step
        first = None
        late_absolute = late_absolute or {}
        for s in sorted(set(late) | set(late_absolute)):
            m = usable(late[s], self.params.own, self.mode) if s in late else RelativeMeasurements.empty()
            # Peers' absolute readings (one each; the own one is never late).
            a = {i: r for i, r in late_absolute.get(s, {}).items() if i != self.params.own}
            if not len(m) and not a:
                continue
            if s > last:
                raise ValueError(f"measurements of step {s} are not late: the filter has updated up to step {last}")
            rec = self._hist.get(s)
            if self.late != "replay" or rec is None:
                rep.dropped += len(m) + len(a)
                continue
            if len(m):
                rec.relative = RelativeMeasurements.concat([rec.relative, m]).canonical()
            if a:
                # The step's readings as {sat: reading} (absolute_rows sorts them: the order
                # they came in changes nothing).
                held = rec.absolute
                if not isinstance(held, Mapping):
                    held = {} if held is None else {self.params.own: held}
                rec.absolute = {**held, **a}
            rec.updated = True
            rep.used += len(m) + len(a)
            first = s if first is None else first
        if first is None:
            return rep
        rep.oldest_step = first
        # Re-run from the first changed step to the last updated one, with the same inputs.
        est = self._hist[first].prior
        for s in range(first, last + 1):
            rec = self._hist[s]
            if s > first:
                rec.prior = predict(est, self.params, self._hist[s - 1].gyro_next)
            est = rec.prior
            if rec.updated:
                est, _ = update(rec.prior, self.params, rec.absolute, rec.relative)
            rep.replayed_steps += 1
        if self.prior_pending:
            est = predict(est, self.params, self._hist[last].gyro_next)
        self.est = est
        return rep
