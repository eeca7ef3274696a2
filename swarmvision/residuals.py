"""A run's vision measurements against the truth: how wrong each was, in units of the σ
the agent attached, and how those normalised errors persist from step to step.

Camera-frame error ``[a_C, e_C]`` exactly as :mod:`swarmvision.characterize` defines it
(the measured pose against the true one, seen from the same camera), normalised by the
variances the pose estimator attached (:attr:`VisionPoseEstimator.record`). Input to the
error model's temporal inflation (:func:`swarmvision.error_model.autocorrelation`) and
the evidence that the attached R fits the errors in flight.
"""

from __future__ import annotations

import numpy as np

from swarmcore.sensors import relative_pose

__all__ = ["residuals", "summarize_residuals", "normalised_series", "write_residuals", "read_residuals", "Z_CLIP"]

#: |e/σ| beyond this is clipped in the autocorrelation (an ICP failure the gate rejects
#: would otherwise dominate the sums).
Z_CLIP = 5.0


def residuals(records: list[dict], truth, t: np.ndarray, mean_motion: float) -> dict:
    """Arrays over the recorded measurements: step, observer, target (N,), err (N, 6)
    camera frame, var (N, 6) attached, and the quantities (list of dicts). ``truth``: the
    run's :class:`~swarmcore.result.TruthArrays`."""
    from .error_model import camera_error
    from .mono import camera_pose_from_truth

    n = len(records)
    err = np.full((n, 6), np.nan)
    for m, rc in enumerate(records):
        k, i, j = rc["step"], rc["observer"], rc["target"]
        q, r = relative_pose(mean_motion, float(t[k]), truth.q_BI[k], truth.r_H_m[k], np.array([i]), np.array([j]))
        R_true, p_true = camera_pose_from_truth(q[0], r[0], rc["T_CB"], rc["r_C_B"])
        err[m] = camera_error(rc["R_CBj"], rc["p_C"], R_true, p_true)
    return {
        "step": np.array([rc["step"] for rc in records], dtype=int),
        "observer": np.array([rc["observer"] for rc in records], dtype=int),
        "target": np.array([rc["target"] for rc in records], dtype=int),
        "err": err,
        "var": np.array([rc["var_C"] for rc in records], float).reshape(n, 6),
        "q": [rc["q"] for rc in records],
    }


def normalised_series(res: dict, var: np.ndarray | None = None) -> list[np.ndarray]:
    """Per (observer, target) pair, the (T, 6) normalised errors at consecutive steps (NaN
    where not measured), clipped to ±``Z_CLIP``. ``var``: other variances to normalise by
    (default: the attached ones)."""
    v = res["var"] if var is None else var
    z = np.clip(res["err"] / np.sqrt(v), -Z_CLIP, Z_CLIP)
    if z.shape[0] == 0:
        return []
    T = int(res["step"].max()) + 1
    out = []
    for i, j in sorted(set(zip(res["observer"].tolist(), res["target"].tolist()))):
        m = (res["observer"] == i) & (res["target"] == j)
        s = np.full((T, 6), np.nan)
        s[res["step"][m]] = z[m]
        out.append(s)
    return out


def summarize_residuals(res: dict, var: np.ndarray | None = None, max_lag: int = 10) -> dict:
    """Mean and median of (e/σ)² per axis (1 and 0.455 when R fits Gaussian errors), the
    fraction beyond 3σ, and the autocorrelation of e/σ (lag 1, τ)."""
    from .error_model import autocorrelation

    v = res["var"] if var is None else var
    z2 = res["err"] ** 2 / v
    ok = np.all(np.isfinite(z2), axis=1)
    z2 = z2[ok]
    ac = autocorrelation(normalised_series(res, var), max_lag)
    z2c = np.minimum(z2, Z_CLIP**2)
    return {"n": int(z2.shape[0]),
            "mean_z2": np.mean(z2, 0).tolist() if z2.size else None,
            "mean_z2_clipped": np.mean(z2c, 0).tolist() if z2.size else None,
            "median_z2": np.median(z2, 0).tolist() if z2.size else None,
            "frac_beyond_3sigma": np.mean(z2 > 9.0, 0).tolist() if z2.size else None,
            "lag1": ac["lag1"], "tau": ac["tau"], "rho": ac["rho"]}


def write_residuals(res: dict, path) -> None:
    """``measurements.npz``: the arrays, and the quantities as columns (NaN when unknown)."""
    qs = res["q"]
    keys = sorted({k for q in qs for k in q if k != "los_Bj"})
    cols = {f"q_{k}": np.array([np.nan if q.get(k) is None else float(q[k]) for q in qs], float) for k in keys}
    los = np.array([q["los_Bj"] for q in qs], float).reshape(len(qs), 3)
    arrays: dict[str, np.ndarray] = {"step": res["step"], "observer": res["observer"], "target": res["target"],
                                     "err": res["err"], "var": res["var"], "q_los_Bj": los, **cols}
    np.savez_compressed(path, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as allow_pickle


def read_residuals(path) -> dict:
    """Inverse of :func:`write_residuals`."""
    d = np.load(path)
    keys = [k[2:] for k in d.files if k.startswith("q_") and k != "q_los_Bj"]
    n = d["step"].shape[0]
    qs = []
    for m in range(n):
        q = {"los_Bj": d["q_los_Bj"][m].tolist()}
        for k in keys:
            x = float(d[f"q_{k}"][m])
            q[k] = None if np.isnan(x) else x
        qs.append(q)
    return {"step": d["step"], "observer": d["observer"], "target": d["target"], "err": d["err"], "var": d["var"], "q": qs}
