"""Errors, NEES and the run summary, computed from truth and estimate arrays (pure)."""

from __future__ import annotations

import warnings

import numpy as np

from . import quat
from .mekf import observed_indices

__all__ = ["pose_errors", "pose_nees", "pose_cov_blocks", "summarize"]


def pose_errors(q_hat, r_hat, q_true, r_true):
    """Attitude error vectors ``a`` (q = δq(a) ⊗ q̂) and position errors, broadcast.

    Shapes: estimates (..., n, 4|3), truth (n, 4|3) or broadcastable.
    """
    a = quat.local(q_true, q_hat)
    dr = r_true - r_hat
    return a, dr


def pose_nees(a, dr, P_pose):
    """6-dof NEES ``eᵀ P⁻¹ e`` with ``e = [a, Δr]`` and ``P_pose`` (..., 6, 6)."""
    e = np.concatenate([a, dr], axis=-1)
    return np.einsum("...i,...i->...", e, np.linalg.solve(P_pose, e[..., None])[..., 0])


def pose_cov_blocks(P: np.ndarray, n: int) -> np.ndarray:
    """(n, 6, 6) covariance of each satellite's [a, Δr] from a full 12n × 12n P."""
    O = observed_indices(n)
    P4 = P[np.ix_(O, O)].reshape(n, 6, n, 6)
    idx = np.arange(n)
    return P4[idx, :, idx, :]


def summarize(
    *,
    n_sats: int,
    dt: float,
    seed: int,
    att_err: np.ndarray,
    pos_err: np.ndarray,
    nees: np.ndarray,
    gate_accepted: np.ndarray,
    gate_rejected: np.ndarray,
    step_ms: np.ndarray,
    nis: np.ndarray,
    nis_dof: np.ndarray,
    alive: np.ndarray | None = None,
    extra: dict | None = None,
) -> dict:
    """The ``summary.json`` contract shared by ``swarm sim`` and ``swarm run``.

    ``alive`` (K, F) masks filter steps that did not run (dead agents); NaN entries in the
    error arrays are ignored the same way. ``nis`` / ``nis_dof`` (K, F): each update's
    joint NIS and its degrees of freedom; the summary gives their sums and ratio (≈ 1 for
    a consistent filter).
    """
    dof = float(np.nansum(nis_dof))
    nis_block = {"sum": float(np.nansum(nis)), "dof": dof, "ratio": float(np.nansum(nis) / dof) if dof else None}
    extra = {"nis": nis_block, **(extra or {})}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: steps nobody estimated
        return _summarize(n_sats, dt, seed, att_err, pos_err, nees, gate_accepted, gate_rejected, step_ms, alive, extra)


def _summarize(n_sats, dt, seed, att_err, pos_err, nees, gate_accepted, gate_rejected, step_ms, alive, extra):
    K, F, n = att_err.shape
    if alive is not None:
        m = ~alive[:, :, None]
        att_err = np.where(m, np.nan, att_err)
        pos_err = np.where(m, np.nan, pos_err)
        nees = np.where(m, np.nan, nees)

    def block(start):
        a = att_err[start:]
        p = pos_err[start:]
        idx = np.arange(F)
        sa = np.sqrt(np.nanmean(a[:, idx, idx] ** 2, axis=0))
        sp = np.sqrt(np.nanmean(p[:, idx, idx] ** 2, axis=0))
        mask = ~np.eye(F, n, dtype=bool)
        oa = np.array([np.sqrt(np.nanmean(a[:, f, mask[f]] ** 2)) for f in range(F)])
        op = np.array([np.sqrt(np.nanmean(p[:, f, mask[f]] ** 2)) for f in range(F)])
        return {
            "self": {"att_rad": float(np.nanmean(sa)), "pos_m": float(np.nanmean(sp))},
            "others": {"att_rad": float(np.nanmean(oa)), "pos_m": float(np.nanmean(op))},
        }

    per_pair = []
    pa = np.sqrt(np.nanmean(att_err**2, axis=0))
    pp = np.sqrt(np.nanmean(pos_err**2, axis=0))
    for f in range(F):
        for j in range(n):
            per_pair.append({"observer": f, "target": j, "att_rad": float(pa[f, j]), "pos_m": float(pp[f, j])})
    out = {
        "n_sats": int(n_sats),
        "steps": int(K),
        "dt": float(dt),
        "seed": int(seed),
        "rms": block(0),
        "rms_second_half": block(K // 2),
        "per_pair": per_pair,
        "nees": {"mean": float(np.nanmean(nees)), "dof": 6},
        "gate": {"accepted": int(np.nansum(gate_accepted)), "rejected": int(np.nansum(gate_rejected))},
        "timing": {"filter_step_ms_median": float(np.nanmedian(step_ms)) if np.isfinite(step_ms).any() else None},
    }
    if extra:
        out.update(extra)
    return out
