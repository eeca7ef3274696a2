"""The reference orbit (the *chief*) every satellite's relative state is counted from.

The chief is not a satellite: it is a point on a known orbit, uploaded to every agent (an
ephemeris), whose Hill frame H is the frame of every ``r_H``, ``v_H`` of the truth and the
filters. Both sides compute it with the same call, so the world's and the agents' frames
are the same bits.

* ``orbit.model: hcw`` — a circular equatorial orbit of radius ``(μ/n²)^⅓`` turning at the
  mean motion n: ``T_IH(t)`` is :func:`swarmcore.dynamics.T_IH` (every earlier result), the
  chief's ECI position ``a [cos nt, sin nt, 0]`` (needed only by the angles-only camera's
  detection: Earth occultation, shadow, Sun).
* ``orbit.model: j2`` — the chief's elements (``orbit.altitude_m`` …) to an ECI state at
  t = 0, propagated step by step over ``dt_s`` with :func:`swarmcore.orbit.propagate`
  (two-body + J2 (+ drag with the chief's ballistic coefficient), RK8 in equal steps of at
  most ``orbit.step_s``). State k is state k−1 propagated by ``dt_s``: exactly what
  :func:`swarmcore.relmotion.propagate_relative` returns as the chief from state k−1.

Times are steps (``t_k = k dt``): the emulator only ever asks for grid times.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from . import orbit
from .dynamics import T_IH as hcw_T_IH

__all__ = ["Chief", "chief_of", "force_model_of"]


def force_model_of(o) -> orbit.ForceModel:
    """The truth's (and a j2 filter's) force model of a scenario's ``orbit`` section."""
    d = o.drag
    atm = orbit.ExponentialAtmosphere(d.rho0_kg_m3, d.h0_m, d.scale_height_m, d.co_rotating) if d.enabled else None
    return orbit.ForceModel(j2=o.j2, atmosphere=atm)


class Chief:
    """The chief's ECI state, Hill frame and acceleration at every step (cached, extended
    on demand)."""

    def __init__(self, model: str, dt: float, mean_motion: float, coe: np.ndarray | None = None,
                 force: orbit.ForceModel | None = None, step_s: float = 10.0, chief_ballistic: float = 0.0):
        self.model = model
        self.dt = float(dt)
        self.n = float(mean_motion)
        self.force = force if force is not None else orbit.J2_ONLY
        self.step_s = float(step_s)
        self.chief_ballistic = float(chief_ballistic) if self.force.atmosphere is not None else None
        self._r: list[np.ndarray] = []
        self._v: list[np.ndarray] = []
        if model == "j2":
            assert coe is not None
            r0, v0 = orbit.coe_to_rv(np.asarray(coe, dtype=float))
            self._r.append(np.asarray(r0, dtype=float))
            self._v.append(np.asarray(v0, dtype=float))
        else:
            self.a_m = (orbit.MU_EARTH_M3_S2 / self.n**2) ** (1.0 / 3.0)

    def step_of(self, t: float) -> int:
        return round(t / self.dt)

    def state(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The chief's ECI position and velocity at step k."""
        if self.model != "j2":
            th = self.n * k * self.dt
            c, s = math.cos(th), math.sin(th)
            return self.a_m * np.array([c, s, 0.0]), self.a_m * self.n * np.array([-s, c, 0.0])
        while len(self._r) <= k:
            r, v = orbit.propagate(self._r[-1], self._v[-1], self.dt, self.force, step_s=self.step_s,
                                   ballistic_m2_kg=self.chief_ballistic)
            self._r.append(r)
            self._v.append(v)
        return self._r[k], self._v[k]

    def accel(self, k: int) -> np.ndarray | None:
        """The chief's acceleration at step k (None for hcw: the frame turns uniformly)."""
        if self.model != "j2":
            return None
        r, v = self.state(k)
        return orbit.acceleration(r, v, self.force, self.chief_ballistic)

    def T_IH(self, t: float) -> np.ndarray:
        """Hill → inertial at time t (a grid time for j2)."""
        if self.model != "j2":
            return hcw_T_IH(self.n, t)
        r, v = self.state(self.step_of(t))
        return orbit.hill_T_IH(r, v)

    def hill_to_eci(self, k: int, r_H: np.ndarray, v_H: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Satellites' Hill states at step k → ECI (j2: :func:`orbit.hill_to_eci`; hcw: the
        uniformly turning frame)."""
        r_c, v_c = self.state(k)
        v_H = np.zeros_like(r_H) if v_H is None else v_H
        if self.model == "j2":
            return orbit.hill_to_eci(r_c, v_c, r_H, v_H, self.accel(k))
        T = self.T_IH(k * self.dt)
        w = np.array([0.0, 0.0, self.n])
        return r_c + r_H @ T.T, v_c + (v_H + np.cross(w, r_H)) @ T.T

    def eci_to_hill(self, k: int, r_I: np.ndarray, v_I: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r_c, v_c = self.state(k)
        return orbit.eci_to_hill(r_c, v_c, r_I, v_I, self.accel(k))


@lru_cache(maxsize=16)
def _chief(model: str, dt: float, n: float, coe: tuple, force: orbit.ForceModel, step_s: float, bc: float) -> Chief:
    return Chief(model, dt, n, np.array(coe) if coe else None, force, step_s, bc)


def chief_of(sc) -> Chief:
    """The scenario's chief (one object per distinct orbit and ``dt`` in a process: every
    filter and the world of an in-process run share its cache)."""
    o = sc.orbit
    if o.model != "j2":
        return _chief("hcw", float(sc.dt_s), float(o.mean_motion_rad_s), (), orbit.J2_ONLY, 10.0, 0.0)
    coe = (o.semi_major_axis(), o.eccentricity, math.radians(o.inclination_deg), math.radians(o.raan_deg),
           math.radians(o.argp_deg), math.radians(o.true_anomaly_deg))
    return _chief("j2", float(sc.dt_s), o.mean_motion(), coe, force_model_of(o), float(o.step_s),
                  float(o.drag.chief_ballistic_m2_kg))
