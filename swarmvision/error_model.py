"""A pose pipeline's measurement noise as a function of what the agent knows when it measures.

Per camera axis k (``[a_x, a_y, a_z, e_x, e_y, e_z]`` in the camera frame, see
:mod:`swarmvision.covariance`), the error variance is log-linear in features φ of the
measurement:

    log σ_k² = β_k · φ

with φ built from quantities known at measurement time (:func:`quantities`): the
measured range, the Sun's angle to the line of sight, the target's apparent attitude (the
line of sight in the target's body frame), and the pipeline's own quality numbers — ICP
fitness, inlier RMSE and number of points (stereo), reprojection RMS and number of tags
(mono).

Fit (:func:`fit`, multiplicative heteroscedasticity, Harvey 1976): ordinary least squares
of ``log e_k²`` on φ (``numpy.linalg.lstsq``). For a Gaussian error ``e = σ z``,
``log e² = log σ² + log z²`` and ``E[log z²] = ψ(½) + log 2 = −1.2704``; the intercept is
corrected by that constant, then re-centred so that the MEDIAN of ``e²/σ²`` is the χ²₁
median 0.455 (the median, not the mean: gross ICP failures are the gate's business, and
one of them would otherwise set every σ).

Errors that persist from step to step (the same seed pose, the same point cloud, a slowly
changing geometry) are not independent; a filter that takes them as independent becomes
overconfident. ``temporal_inflation`` multiplies every variance by the integrated
autocorrelation time of the normalised errors ``τ = 1 + 2 Σ_{l≥1} ρ_l`` (the variance of a
mean of correlated samples is τ σ²/N), estimated from a run's measurement residuals
(:func:`autocorrelation`, ``swarm fit-noise --residuals``).

The fitted model is a JSON file (:meth:`ErrorModel.to_json`), shipped in ``data/`` and
named in a scenario's ``vision.covariance.model``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["ErrorModel", "FEATURES", "camera_error", "quantities", "feature_matrix", "fit", "autocorrelation", "load_model",
           "fit_robust", "GATE_Z2", "LOG_CHI2_1_MEAN", "CHI2_1_MEDIAN", "fit_from_samples"]

#: E[log z²] for z ~ N(0, 1): ψ(½) + log 2.
LOG_CHI2_1_MEAN = -1.2703628454614782
#: median of χ²₁.
CHI2_1_MEDIAN = 0.454936423119572

AXES = ["att_x", "att_y", "att_z", "pos_x", "pos_y", "pos_z"]

#: Features per pipeline (names; :func:`feature_matrix` computes them).
FEATURES = {
    "stereo": ["const", "log_range", "cos_sun", "cos_sun_sq", "los_x", "los_y", "los_z", "los_x_sq", "los_y_sq",
               "fitness", "log_rmse", "log_points"],
    "mono": ["const", "log_range", "cos_sun", "cos_sun_sq", "los_x", "los_y", "los_z", "los_x_sq", "los_y_sq",
             "log_rms_px", "inv_tags"],
}



class TooFewSamples(ValueError):
    """A characterisation too small to fit the model's coefficients."""

def camera_error(R_est, p_est, R_true, p_true) -> np.ndarray:
    """The camera-frame error vector ``[a_C, e_C]`` of an estimated pose against the true one:
    ``R_est = exp([a_C×]) R_true``, ``p_est = p_true + e_C`` (rad, m)."""
    import cv2

    a, _ = cv2.Rodrigues(R_est @ R_true.T)
    return np.r_[a.ravel(), np.asarray(p_est) - np.asarray(p_true)]


def quantities(R_CBj: np.ndarray, p_C: np.ndarray, sun_C: np.ndarray | None, **quality) -> dict:
    """What the agent knows about one measurement, as plain values (JSON-ready).

    ``R_CBj``, ``p_C``: the measured pose of target j in the camera frame; ``sun_C``: the
    direction to the Sun in the camera frame (from the agent's own attitude estimate), or
    None; ``quality``: the pipeline's numbers (stereo: ``fitness``, ``rmse_m``,
    ``n_points``; mono: ``rms_px``, ``n_tags``)."""
    p = np.asarray(p_C, float)
    rng = float(np.linalg.norm(p))
    u = p / max(rng, 1e-9)
    los_Bj = -(np.asarray(R_CBj, float).T @ u)  # target → observer, in the target's body frame
    cos_sun = None if sun_C is None else float(np.dot(u, np.asarray(sun_C, float)) / np.linalg.norm(sun_C))
    return {"range_m": rng, "cos_sun": cos_sun, "los_Bj": [float(x) for x in los_Bj],
            **{k: float(v) for k, v in quality.items()}}


def _col(qs: list[dict], key: str, default: float = 0.0) -> np.ndarray:
    return np.array([default if q.get(key) is None else float(q[key]) for q in qs], float)


def feature_matrix(names: list[str], qs: list[dict]) -> np.ndarray:
    """(N, p) features of N measurements' :func:`quantities`. A missing Sun angle counts as
    side light (cos 0); the constants centre each feature near the shipped scenarios'."""
    n = len(qs)
    los = np.array([q["los_Bj"] for q in qs], float).reshape(n, 3)
    cs = _col(qs, "cos_sun")
    cols = {
        "const": lambda: np.ones(n),
        "log_range": lambda: np.log(np.maximum(_col(qs, "range_m"), 0.1) / 10.0),
        "cos_sun": lambda: cs,
        "cos_sun_sq": lambda: cs**2,
        "los_x": lambda: los[:, 0],
        "los_y": lambda: los[:, 1],
        "los_z": lambda: los[:, 2],
        "los_x_sq": lambda: los[:, 0] ** 2,
        "los_y_sq": lambda: los[:, 1] ** 2,
        "fitness": lambda: _col(qs, "fitness", 1.0),
        "log_rmse": lambda: np.log(np.maximum(_col(qs, "rmse_m", 0.01), 1e-5) / 0.01),
        "log_points": lambda: np.log(np.maximum(_col(qs, "n_points", 500.0), 1.0) / 500.0),
        "log_rms_px": lambda: np.log(np.maximum(_col(qs, "rms_px", 0.3), 1e-3) / 0.3),
        "inv_tags": lambda: 1.0 / np.maximum(_col(qs, "n_tags", 1.0), 1.0),
    }
    unknown = [k for k in names if k not in cols]
    if unknown:
        raise ValueError(f"unknown error-model feature(s) {unknown}; known: {sorted(cols)}")
    return np.stack([cols[k]() for k in names], axis=1) if n else np.zeros((0, len(names)))


@dataclass
class ErrorModel:
    """``σ_k² = exp(β_k · φ) · temporal_inflation`` per camera axis k."""

    pipeline: str
    camera: dict
    features: list[str]
    coef: np.ndarray  # (6, p)
    temporal_inflation: np.ndarray = field(default_factory=lambda: np.ones(6))  # (6,) τ per axis
    min_var: np.ndarray = field(default_factory=lambda: np.zeros(6))  # (6,) floor on each variance
    max_var: np.ndarray = field(default_factory=lambda: np.full(6, np.inf))  # (6,) cap (extrapolation)
    meta: dict = field(default_factory=dict)

    def var_C(self, qs: list[dict] | dict) -> np.ndarray:
        """(N, 6) camera-frame variances (or (6,) for one measurement's quantities)."""
        one = isinstance(qs, dict)
        X = feature_matrix(self.features, [qs] if isinstance(qs, dict) else qs)
        v = np.clip(np.exp(np.clip(X @ self.coef.T, -60.0, 60.0)), self.min_var, self.max_var)
        v = v * np.asarray(self.temporal_inflation, float)
        return v[0] if one else v

    def var_C_single(self, qs: list[dict] | dict) -> np.ndarray:
        """The variances of one measurement taken alone (without the temporal inflation)."""
        return self.var_C(qs) / np.asarray(self.temporal_inflation, float)

    def cov_C(self, q: dict) -> np.ndarray:
        return np.diag(self.var_C(q))

    def to_json(self) -> dict:
        return {"kind": "log-linear error model", "pipeline": self.pipeline, "camera": self.camera, "axes": AXES,
                "features": list(self.features), "coef": np.asarray(self.coef).tolist(),
                "temporal_inflation": np.broadcast_to(np.asarray(self.temporal_inflation, float), (6,)).tolist(), "min_var": np.asarray(self.min_var).tolist(),
                "max_var": [None if not np.isfinite(x) else float(x) for x in self.max_var], "meta": self.meta}

    @classmethod
    def from_json(cls, d: dict) -> ErrorModel:
        if d.get("kind") != "log-linear error model":
            raise ValueError("not an error model (expected \"kind\": \"log-linear error model\")")
        coef = np.asarray(d["coef"], float)
        if coef.shape != (6, len(d["features"])):
            raise ValueError(f"error model: coef has shape {coef.shape}, expected (6, {len(d['features'])})")
        feature_matrix(d["features"], [])  # unknown names fail here
        mx = np.array([np.inf if x is None else float(x) for x in d.get("max_var", [None] * 6)])
        tau = np.broadcast_to(np.asarray(d.get("temporal_inflation", 1.0), float), (6,)).copy()
        if np.any(tau < 1.0) or not np.all(np.isfinite(tau)):
            raise ValueError(f"error model: temporal_inflation {tau.tolist()} must be finite and ≥ 1")
        return cls(d["pipeline"], d["camera"], list(d["features"]), coef, tau,
                   np.asarray(d.get("min_var", np.zeros(6)), float), mx, d.get("meta", {}))

    def write(self, path: Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=1) + "\n")
        return path


def load_model(path: str | Path) -> ErrorModel:
    return ErrorModel.from_json(json.loads(Path(path).read_text()))


def fit(X: np.ndarray, E: np.ndarray, ridge: float = 1e-3, calibrate: str = "median") -> tuple[np.ndarray, dict]:
    """Per column k of the errors ``E`` (N, 6): β_k from ``log E[:, k]² ≈ X β_k``.

    ``ridge``: Tikhonov weight on every coefficient but the first (the intercept) relative
    to N, keeping collinear features (a design with little Sun-angle spread) finite.
    ``calibrate``: ``median`` (median of e²/σ² = χ²₁ median) or ``harvey`` (the Gaussian
    bias correction alone). Returns (coef (6, p), diagnostics)."""
    X = np.asarray(X, float)
    E = np.asarray(E, float)
    ok = np.all(np.isfinite(E), axis=1) & np.all(np.isfinite(X), axis=1)
    X, E = X[ok], E[ok]
    n, p = X.shape
    if n < p + 2:
        raise TooFewSamples(f"error model: {n} usable samples for {p} features")
    coef = np.zeros((E.shape[1], p))
    diag: dict = {"n": int(n), "axes": {}}
    L = np.sqrt(ridge * n) * np.eye(p)
    L[0, 0] = 0.0
    for k in range(E.shape[1]):
        e2 = np.maximum(E[:, k] ** 2, 1e-30)
        y = np.log(e2)
        b, *_ = np.linalg.lstsq(np.vstack([X, L]), np.r_[y, np.zeros(p)], rcond=None)
        b[0] -= LOG_CHI2_1_MEAN
        z2 = e2 / np.exp(X @ b)
        if calibrate == "median":
            b[0] += np.log(np.median(z2) / CHI2_1_MEDIAN)
            z2 = e2 / np.exp(X @ b)
        elif calibrate != "harvey":
            raise ValueError(f"calibrate must be median or harvey, got {calibrate!r}")
        coef[k] = b
        resid = y - X @ b
        diag["axes"][AXES[k]] = {"mean_z2": float(np.mean(z2)), "median_z2": float(np.median(z2)),
                                 "frac_beyond_3sigma": float(np.mean(z2 > 9.0)),
                                 "r2_log": float(1.0 - np.var(resid) / max(np.var(y), 1e-30))}
    return coef, diag


#: A sample whose squared normalised error exceeds this on any axis (χ²₁ 0.999 quantile) is
#: an outlier — an ICP that converged to the wrong pose, a mirrored tag — for the validation
#: gate, not R: it is left out of the next fit.
GATE_Z2 = 10.83


def fit_robust(X: np.ndarray, E: np.ndarray, ridge: float = 1e-3, calibrate: str = "median", rounds: int = 4):
    """:func:`fit`, then refit without the outliers (``GATE_Z2``) until the set is stable.
    Returns (coef, diagnostics on the kept samples, kept mask)."""
    X = np.asarray(X, float)
    E = np.asarray(E, float)
    keep = np.all(np.isfinite(E), axis=1) & np.all(np.isfinite(X), axis=1)
    coef, diag = fit(X[keep], E[keep], ridge=ridge, calibrate=calibrate)
    for _ in range(rounds):
        ok = np.all(np.isfinite(E), axis=1) & np.all(np.isfinite(X), axis=1)
        z2 = np.where(ok[:, None], E, 0.0) ** 2 / np.exp(X @ coef.T)
        new = ok & np.all(z2 <= GATE_Z2, axis=1)
        if np.array_equal(new, keep):
            break
        keep = new
        coef, diag = fit(X[keep], E[keep], ridge=ridge, calibrate=calibrate)
    return coef, diag, keep


def fit_from_samples(samples: list[dict], pipeline: str, camera: dict, features: list[str] | None = None,
                     ridge: float = 1e-3, calibrate: str = "median", illumination: str | None = None) -> ErrorModel:
    """An :class:`ErrorModel` from characterisation samples (those with ``ok`` and ``q``)."""
    names = list(features or FEATURES[pipeline])
    ss = [s for s in samples if s.get("ok") and s.get("q") is not None
          and (illumination is None or s.get("illumination") == illumination)]
    if not ss:
        raise ValueError("no successful characterisation sample carries the measurement quantities (\"q\"): "
                         "re-run `swarm characterize` with this version")
    E = np.array([s["err"] for s in ss], float)
    X = feature_matrix(names, [s["q"] for s in ss])
    coef, diag, keep = fit_robust(X, E, ridge=ridge, calibrate=calibrate)
    # Never extrapolate beyond what was measured by more than ×10 in variance, never below
    # a tenth of the smallest error measured (a log-linear law has no floor of its own).
    e2 = E**2
    e2 = e2[np.all(np.isfinite(e2), axis=1)]
    lo = 0.1 * np.percentile(e2, 5, axis=0)
    hi = 10.0 * np.percentile(e2, 99, axis=0)
    rng = np.array([q["q"]["range_m"] for q in ss])
    meta = {"fit": diag, "outliers": int((~keep).sum()), "gate_z2": GATE_Z2, "illumination": illumination, "ridge": ridge, "calibrate": calibrate,
            "range_m": [float(rng.min()), float(rng.max())], "samples": len(ss)}
    return ErrorModel(pipeline, dict(camera), names, coef, np.ones(6), lo, hi, meta)


def autocorrelation(series: list[np.ndarray], max_lag: int = 10, window: int | None = None) -> dict:
    """Autocorrelation of normalised errors pooled over sequences.

    ``series``: per (observer, target) pair an (T, 6) array of normalised errors ``e/σ`` at
    consecutive steps (NaN where no measurement). ``ρ_l = Σ z_t z_{t+l} / Σ z_t²`` over the
    pairs present at both steps, per axis (not de-meaned: a persistent bias is exactly the
    correlation a filter must not average away). ``tau`` = 1 + 2 Σ ρ_l, summed while ρ_l
    stays positive (the initial positive sequence, Geyer 1992), at least 1. With
    ``window`` W (steps; the filter's memory): the variance factor of a W-step mean,
    ``τ_W = 1 + 2 Σ_{l<W} (1 − l/W) ρ_l`` (Bartlett weights), at least 1 — what matters
    for a filter that averages about W steps of measurements, when ρ does not die out
    (a bias that persists as long as the geometry)."""
    if window is not None:
        max_lag = max(max_lag, int(window) - 1)
    rho = np.full((max_lag + 1, 6), np.nan)
    for lag in range(max_lag + 1):
        num = np.zeros(6)
        den = np.zeros(6)
        for z in series:
            z = np.asarray(z, float)
            if z.shape[0] <= lag:
                continue
            a, b = z[: z.shape[0] - lag], z[lag:]
            m = np.isfinite(a) & np.isfinite(b)
            num += np.where(m, a * b, 0.0).sum(0)
            den += np.where(m, 0.5 * (a * a + b * b), 0.0).sum(0)
        rho[lag] = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    tau = np.ones(6)
    for k in range(6):
        if window is not None:
            lags = np.arange(1, int(window))
            r = np.nan_to_num(rho[lags, k])
            tau[k] = max(1.0, 1.0 + 2.0 * float(np.sum((1.0 - lags / window) * r)))
            continue
        for lag in range(1, max_lag + 1):
            r = rho[lag, k]
            if not np.isfinite(r) or r <= 0:
                break
            tau[k] += 2 * r
    return {"rho": rho.tolist(), "lag1": rho[1].tolist(), "tau": tau.tolist(), "window": window}
