"""``solo``: every satellite on its own sensors (an example estimator plug-in).

Each agent runs the own-satellite part of the cooperative MEKF (gyro in dynamic-model
replacement mode, star tracker, GPS: :mod:`swarmcore.mekf` with one satellite) and uses
no relative measurement: the non-cooperative baseline. Each step it broadcasts its prior
position and its 3×3 covariance in a message of its own encoding (:meth:`encode`: 12
little-endian float64, 96 bytes), which the swarm carries through the radio like any
estimator's, and it keeps the latest it heard of each peer (``StepReport.extra``
counts them; a cooperative estimator would fuse them). It claims only its own state.

Written against the public interface only (:mod:`swarmcore.estimators.base`), as a
package of one's own would be.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from swarmcore.estimators.base import EstimateView, EstimatorParams, StepInputs, StepReport
from swarmcore.estimators.own import OwnStateEstimator
from swarmcore.estimators.views import pose_block

__all__ = ["SoloEstimator", "SoloParams", "Where"]

class SoloParams(EstimatorParams):
    process_noise_scale: float = Field(1.0, gt=0, description="multiply the acceleration noise density by this")


@dataclass(frozen=True)
class Where:
    """Its message: where a satellite believes it is (H frame) and how well."""

    r_H: np.ndarray  # (3,) m
    P_r: np.ndarray  # (3, 3) m²


class SoloEstimator(OwnStateEstimator):
    """Its state, prediction and own-sensor update come from :class:`OwnStateEstimator`
    (the own block of the cooperative MEKF); what it adds is its message and its step."""

    kind = "solo"
    Params = SoloParams

    def __init__(self, sc, own: int, params: SoloParams | None = None):
        super().__init__(sc, own, params)
        self.fp = dataclasses.replace(self.fp, accel=self.fp.accel * self.params.process_noise_scale)  # type: ignore[attr-defined]
        self._heard: dict[int, Where] = {}

    def transmit(self, k: int) -> Where:
        e = self.e
        return Where(e.r_H[0].copy(), e.P[6:9, 6:9].copy())

    def step(self, inputs: StepInputs) -> StepReport:
        self.begin_step(inputs.step, inputs.gyro_rate_B)
        rep = StepReport(late_dropped=sum(len(r.measurements) for r in inputs.late()))
        rep.nis, rep.nis_dof = self.update_absolute(inputs.absolute)
        self._heard.update({r.sender: r.payload for r in inputs.on_time() if isinstance(r.payload, Where)})
        rep.extra["peers_heard"] = len(self._heard)
        self._pending = False
        return rep

    def view(self) -> EstimateView:
        """Its own state only: it has no estimate of a peer's attitude to claim."""
        e = self.e
        P = pose_block(e.P)[None]
        return EstimateView(step=e.step, t=e.t, own=self.own, ids=np.array([self.own]), q_BI=e.q_BI, omega_BI_B=e.omega_BI_B,
                            r_H=e.r_H, v_H=e.v_H, bias_B=e.bias_B, P_pose=P, P_rel_pose=np.zeros((1, 6, 6)), P_diag=np.diag(e.P))

    # -- its message on the wire: 12 float64, little-endian ---------------------------------
    _FMT = struct.Struct("<12d")

    @classmethod
    def encode(cls, message: Where) -> bytes:
        return cls._FMT.pack(*np.asarray(message.r_H, float), *np.asarray(message.P_r, float).ravel())

    @classmethod
    def decode(cls, data: bytes) -> Where:
        if len(data) != cls._FMT.size:
            raise ValueError(f"solo message: {len(data)} bytes, expected {cls._FMT.size}")
        x = np.array(cls._FMT.unpack(data))
        P = x[3:].reshape(3, 3)
        if not np.isfinite(x).all() or not np.allclose(P, P.T) or np.linalg.eigvalsh(P).min() <= 0:
            raise ValueError("solo message: not a finite position with a symmetric positive-definite covariance")
        return Where(x[:3], P)
