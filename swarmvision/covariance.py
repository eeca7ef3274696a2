"""Measurement noise R of a vision measurement, in the camera frame then in B_i.

The camera-frame law and the rotation into B_i are the core's
(:mod:`swarmcore.sensors`); this module adds the vision-specific sources.

Camera-frame error vector ``[a_C, e_C]``: ``R̃_CBj = exp([a_C×]) R_CBj`` (rad) and
``p̃_C = p_C + e_C`` (m). The filter's measurement noise (``q̃_BjBi = q_BjBi ⊗ δq(a)``,
``r̃_ij_Bi = r_ij_Bi + e``, both in B_i) is the same error rotated by ``T_BC``:
``R_Bi = diag(T_BC, T_BC) Σ_C diag(T_BC, T_BC)ᵀ``.

Sources (``CovarianceConfig.source``):

* ``fixed`` — per-axis σ at a reference range, ∝ ``(range / ref) ** exponent``;
* ``pnp`` — the PnP solution's own first-order covariance (mono only);
* ``characterized`` — variance per camera axis versus range (interpolated) times a
  Sun-angle factor, from a ``swarm characterize`` JSON;
* ``fitted`` — the log-linear error model of :mod:`swarmvision.error_model` (range, Sun
  angle, apparent attitude, pipeline quality numbers; times the autocorrelation time).
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from swarmcore.sensors import camera_axis_variances, camera_to_body
from swarmcore.vision_config import CovarianceConfig

from .catalogue import DATA, default_table_path, model_name

__all__ = ["resolve_model_path", "camera_to_body", "floor_cov", "fixed_cov_C", "CharacterizedNoise", "load_table", "default_table_path", "sun_angle_deg"]

def resolve_model_path(model: str | None, pipeline: str, camera: dict) -> Path:
    """The fitted error model a scenario names (``vision.covariance.model``): a path, a bare
    file name in ``swarmvision/data``, or (None) the one shipped for this pipeline and camera."""
    if model is None:
        p = DATA / model_name(pipeline, camera)
    else:
        p = Path(model)
        if not p.is_file() and (DATA / p.name).is_file() and p.name == str(model):
            p = DATA / p.name
    if not p.is_file():
        raise ValueError(
            f"vision.covariance.model: no error model {p} for this camera {camera}. Run `swarm characterize "
            f"--pipeline {pipeline} --scenario <file> --out DIR` (it fits one) or `swarm fit-noise`, or use "
            "covariance.source characterized|fixed|pnp"
        )
    return p


def sun_angle_deg(los_I: np.ndarray, sun_I: np.ndarray) -> float:
    """Angle between the observer→target line of sight and the direction to the Sun.

    0°: the target sits in front of the Sun (the observer sees its unlit side);
    180°: the Sun is behind the observer (fully lit target)."""
    a = np.asarray(los_I, float)
    b = np.asarray(sun_I, float)
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def floor_cov(cov: np.ndarray, cfg: CovarianceConfig) -> np.ndarray:
    d = np.diag(cov).copy()
    d[:3] = np.maximum(d[:3], cfg.min_sigma_att_rad**2)
    d[3:] = np.maximum(d[3:], cfg.min_sigma_pos_m**2)
    out = cov.copy()
    out[np.diag_indices(6)] = d
    return out * cfg.inflation


def fixed_cov_C(cfg: CovarianceConfig, range_m: float) -> np.ndarray:
    """The chapter-6 camera noise law (:func:`swarmcore.sensors.camera_axis_variances`)
    with this configuration's σ, floored and inflated."""
    var = camera_axis_variances(cfg.sigma_att_camera_rad, cfg.sigma_pos_camera_m, range_m, cfg.reference_range_m, cfg.range_exponent)
    return floor_cov(np.diag(var), cfg)


@lru_cache(maxsize=8)
def load_table(path: str) -> dict:
    return json.loads(Path(path).read_text())


class CharacterizedNoise:
    """R as a function of range and Sun angle from a characterization table.

    ``var(range, sun) = var_range(range) · f(sun)`` per camera axis: ``var_range`` is the
    (outlier-trimmed) mean squared error per range bin, interpolated linearly and
    extrapolated beyond the last populated bin as range²; ``f`` is the Sun-angle bin's
    mean squared error relative to its range bin's (empty bins: the nearest populated one).
    """

    def __init__(self, table: dict, cfg: CovarianceConfig, illumination: str = "solar", camera: dict | None = None):
        self.cfg = cfg
        if camera is not None and "camera" in table:
            tc = table["camera"]
            if any(abs(float(tc[k]) - float(camera[k])) > 1e-6 for k in camera if k in tc):
                raise ValueError(
                    f"characterization table is for camera {tc}, the scenario's is {camera}: run "
                    "`swarm characterize` for this camera, or use covariance.source fixed|pnp"
                )
        if "illuminations" in table:
            ill = table["illuminations"]
            table = ill[illumination] if illumination in ill else next(iter(ill.values()))
        rb = table["by_range"]
        r = np.asarray(rb["range_m"], float)
        v = np.asarray(rb["mse_trimmed"], float)  # (nr, 6) [att xyz, pos xyz] camera frame
        ok = np.all(np.isfinite(v), axis=1) & (np.asarray(rb["count"]) >= 3)
        if not np.any(ok):
            raise ValueError("characterization table has no populated range bin")
        self.r = r[ok]
        self.v = v[ok]
        sb = table.get("by_sun", None)
        if sb is not None:
            sun = np.asarray(sb["sun_deg"], float)
            f = np.asarray(sb["factor"], float)
            ok_s = np.all(np.isfinite(f) & (f > 0), axis=1) & (np.asarray(sb.get("count", [3] * len(sun))) >= 3)
            if np.any(ok_s):
                # Empty Sun bins (e.g. no sample within 30° of the line of sight) take the
                # nearest populated bin's factor: interpolation over the populated centres
                # holds the end values, never a neutral 1 next to a backlit 8.
                self.sun, self.f = sun[ok_s], f[ok_s]
            else:
                self.sun, self.f = np.array([0.0, 180.0]), np.ones((2, 6))
        else:
            self.sun = np.array([0.0, 180.0])
            self.f = np.ones((2, 6))

    def cov_C(self, range_m: float, sun_deg: float | None = None) -> np.ndarray:
        r = float(range_m)
        var = np.array([np.interp(r, self.r, self.v[:, k]) for k in range(6)])
        if r > self.r[-1]:
            var = self.v[-1] * (r / self.r[-1]) ** 2
        if sun_deg is not None:
            var = var * np.array([np.interp(sun_deg, self.sun, self.f[:, k]) for k in range(6)])
        return floor_cov(np.diag(var), self.cfg)
