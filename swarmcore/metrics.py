"""Errors, NEES and the run summary, computed from truth and estimate arrays (pure)."""

from __future__ import annotations

import contextlib
import warnings
from typing import TYPE_CHECKING

import numpy as np

from . import quat
from .mekf import observed_indices

if TYPE_CHECKING:
    from .links import LinkCounters
    from .result import BusRecord, RunResult
    from .scenario import Scenario

__all__ = ["bound_summary", "estimator_summary", "relative_errors_of", "run_summary", "link_summary", "bus_summary", "security_summary",
           "pose_errors", "pose_nees", "pose_cov_blocks", "summarize"]


def pose_errors(q_hat, r_hat, q_true, r_true):
    """Attitude error vectors ``a`` (q = δq(a) ⊗ q̂) and position errors, broadcast.

    Shapes: estimates (..., n, 4|3), truth (n, 4|3) or broadcastable.
    """
    a = quat.local(q_true, q_hat)
    dr = r_true - r_hat
    return a, dr


def relative_errors_of(q_hat, r_hat, own: int, q_true, r_true):
    """One filter's estimate of every satellite relative to its own satellite ``own``,
    against the truth: ``a_rel`` (…, n, 3), the error of ``q_BjBown = q_j ⊗ q_own⁻¹``
    (``q_rel = δq(a_rel) ⊗ q̂_rel``, in B_j), and ``dr_rel`` (…, n, 3), the error of
    ``r_j − r_own`` (H); NaN on the own row. Estimates and truth (…, n, 4 | 3)."""
    def rel(q, r):
        qo = np.broadcast_to(q[..., own : own + 1, :], q.shape)
        return quat.qmul(q, quat.qconj(qo)), r - r[..., own : own + 1, :]

    q_rel_hat, r_rel_hat = rel(np.asarray(q_hat, float), np.asarray(r_hat, float))
    q_rel, r_rel = rel(np.broadcast_to(q_true, np.shape(q_hat)), np.broadcast_to(r_true, np.shape(r_hat)))
    a_rel = quat.local(q_rel, q_rel_hat)
    dr_rel = r_rel - r_rel_hat
    a_rel[..., own, :] = np.nan
    dr_rel[..., own, :] = np.nan
    return a_rel, dr_rel


def pose_nees(a, dr, P_pose):
    """6-dof NEES ``eᵀ P⁻¹ e`` with ``e = [a, Δr]`` and ``P_pose`` (..., 6, 6). Numbers no
    honest filter claims are scored, not raised or warned about: an overflowing error or
    covariance gives inf or NaN, and a singular covariance (a filter claiming certainty, or a
    damaged recording) inf."""
    e = np.concatenate([a, dr], axis=-1)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        try:
            x = np.linalg.solve(P_pose, e[..., None])[..., 0]
        except np.linalg.LinAlgError:  # one of them singular: each solved alone, the singular ones inf
            P = np.broadcast_to(P_pose, (*e.shape, 6))
            x = np.where(e == 0, 0.0, np.inf * np.sign(e))  # any error against a claimed certainty: inf
            for i in np.ndindex(e.shape[:-1]):
                with contextlib.suppress(np.linalg.LinAlgError):
                    x[i] = np.linalg.solve(P[i], e[i])
        return np.einsum("...i,...i->...", e, x)


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
    extra: dict | None = None,
) -> dict:
    """The ``summary.json`` contract shared by ``swarm sim`` and ``swarm run``.

    NaN entries in the error arrays (steps a filter did not run, satellites it does not
    track) are left out. ``nis`` / ``nis_dof`` (K, F): each update's
    joint NIS and its degrees of freedom; the summary gives their sums and ratio (≈ 1 for
    a consistent filter).
    """
    dof = float(np.nansum(nis_dof))
    nis_block = {"sum": float(np.nansum(nis)), "dof": dof, "ratio": float(np.nansum(nis) / dof) if dof else None}
    extra = {"nis": nis_block, **(extra or {})}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: steps nobody estimated
        return _summarize(n_sats, dt, seed, att_err, pos_err, nees, gate_accepted, gate_rejected, step_ms, extra)


def _summarize(n_sats, dt, seed, att_err, pos_err, nees, gate_accepted, gate_rejected, step_ms, extra):
    K, F, n = att_err.shape

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


def estimator_summary(kind: str, dt: float, rel_att_err, rel_pos_err, rel_nees, bytes_sent, cpu_ms) -> dict:
    """The blocks of ``summary.json`` every estimator shares, whatever it keeps.

    ``relative``: time-RMS of each filter's estimate of its peers relative to itself
    (attitude and position, averaged over filters and the peers it tracks; full run and
    second half) and the mean NEES of those estimates against the relative covariance the
    estimator claims (6 dof). ``traffic``: bytes each satellite put on its radio (its
    batch and its estimator's message) per second, mean and max over satellites.
    ``cpu``: CPU time of a filter step (predict and update, the thread's), median and p95.
    Arrays (K, F, n) / (K, n); NaN where nothing was estimated or sent.
    """
    out: dict = {"estimator": kind}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if rel_att_err is not None and rel_pos_err is not None and rel_nees is not None:
            ra, rp, rn = rel_att_err, rel_pos_err, rel_nees
            K = ra.shape[0]

            def rms(x, start):
                per_filter = np.sqrt(np.nanmean(x[start:].reshape(K - start, x.shape[1], -1) ** 2, axis=(0, 2)))
                return float(np.nanmean(per_filter))

            out["relative"] = {
                "rms": {"att_rad": rms(ra, 0), "pos_m": rms(rp, 0)},
                "rms_second_half": {"att_rad": rms(ra, K // 2), "pos_m": rms(rp, K // 2)},
                "nees": {"mean": float(np.nanmean(rn)), "dof": 6},
            }
        if bytes_sent is not None and np.isfinite(bytes_sent).any():
            per_sat = np.nansum(bytes_sent, axis=0) / (np.isfinite(bytes_sent).sum(axis=0).clip(1) * dt)
            out["traffic"] = {"bytes_per_sat_per_s_mean": float(np.mean(per_sat)), "bytes_per_sat_per_s_max": float(np.max(per_sat))}
        if cpu_ms is not None and np.isfinite(cpu_ms).any():
            out["cpu"] = {"filter_step_cpu_ms_median": float(np.nanmedian(cpu_ms)), "filter_step_cpu_ms_p95": float(np.nanpercentile(cpu_ms, 95))}
    return out


def run_summary(result: RunResult, sc: Scenario) -> dict:
    """``summary.json`` of a run, built from its :class:`~swarmcore.result.RunResult` alone
    (the in-process simulator's and a recording's alike): :func:`summarize`, the scenario,
    ``measurements_per_step_mean`` (relative measurements in the batches the agents put on
    the radio, per step), the estimator's blocks (:func:`estimator_summary`), the late
    deliveries (with links), the radio's counters (:func:`link_summary`) and, for a
    recording, what only the bus shows (:func:`bus_summary`). A new metric's block goes here."""
    r = result
    blocks = {
        "scenario": sc.name,
        "mode": sc.filter.mode,
        "measurements_per_step_mean": float(r.taken.sum(axis=(1, 2)).mean()),
        **estimator_summary(r.estimator, sc.dt_s, r.rel_att_err_rad, r.rel_pos_err_m, r.rel_nees, r.bytes_sent, r.cpu_ms),
    }
    if sc.links.enabled:
        blocks["late"] = {"used": int(np.sum(r.late_used)), "dropped": int(np.sum(r.late_dropped)),
                          "replayed_steps": int(np.sum(r.replayed_steps))}
    if r.links is not None:
        blocks["links"] = link_summary(r.links.counters, r.links.latencies)
    if r.bus is not None:
        blocks.update(bus_summary(r.bus, sc))
    if r.bound is not None:
        blocks.update(bound_summary(r))
    return summarize(n_sats=sc.n_sats, dt=sc.dt_s, seed=sc.seed, att_err=r.att_err_rad, pos_err=r.pos_err_m, nees=r.nees,
                     gate_accepted=r.gate_accepted, gate_rejected=r.gate_rejected, step_ms=r.step_ms, nis=r.nis, nis_dof=r.nis_dof,
                     extra=blocks)


def bound_summary(r: RunResult) -> dict:
    """``summary.json``'s ``bound`` (the Cramér–Rao bound of the run, :mod:`swarmcore.crlb`:
    time-RMS of √bound per satellite, their mean, and of each pair's relative position) and
    ``rms_over_bound``: each filter's time-RMS error over the bound's time-RMS, for the
    same steps (its own satellite ``self``, the others it tracks ``others``, each tracked
    peer relative to itself ``relative``), averaged over filters and satellites; full run
    and second half. 1 is the limit; an unbiased estimator cannot go below it (on average)."""
    b = r.bound
    assert b is not None
    K, n = b.pos_m2.shape
    off = ~np.eye(n, dtype=bool)

    def bound_block(start):
        att, pos, rel = (np.sqrt(np.nanmean(x[start:], axis=0)) for x in (b.att_rad2, b.pos_m2, b.rel_pos_m2))
        return {"att_rad": float(np.mean(att)), "pos_m": float(np.mean(pos)), "rel_pos_m": float(np.mean(rel[off])),
                "per_sat": [{"sat": i, "att_rad": float(att[i]), "pos_m": float(pos[i])} for i in range(n)]}

    def ratio(err, bnd, start):
        """(F, n) time-RMS of err over time-RMS of √bnd on the steps both exist (a recording's
        bound ends at its first step without truth); NaN elsewhere."""
        e = err[start:]
        bb = np.broadcast_to(bnd[start:], e.shape)
        have = np.isfinite(e) & np.isfinite(bb)
        cnt = have.sum(axis=0)
        num = np.sqrt(np.where(have, e**2, 0.0).sum(axis=0) / np.maximum(cnt, 1))
        den = np.sqrt(np.where(have, bb, 0.0).sum(axis=0) / np.maximum(cnt, 1))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where((cnt > 0) & (den > 0), num / np.where(den > 0, den, 1.0), np.nan)

    def over(start):
        F = r.pos_err_m.shape[1]
        own = np.eye(F, n, dtype=bool)
        a = ratio(r.att_err_rad, b.att_rad2[:, None, :], start)
        p = ratio(r.pos_err_m, b.pos_m2[:, None, :], start)
        rp = ratio(r.rel_pos_err_m, b.rel_pos_m2[:, :F, :], start)

        def mean(x, mask):
            v = x[mask]
            v = v[np.isfinite(v)]
            return float(np.mean(v)) if v.size else None

        return {"self": {"att": mean(a, own), "pos": mean(p, own)}, "others": {"att": mean(a, ~own), "pos": mean(p, ~own)},
                "relative": {"pos": mean(rp, ~own)}}

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return {"bound": {"kind": b.kind, "rms": bound_block(0), "rms_second_half": bound_block(K // 2)},
                "rms_over_bound": {**over(0), "second_half": over(K // 2)}}


def link_summary(counters: LinkCounters, latencies) -> dict:
    """The ``links`` block of summary.json: totals, per directed link, delivered latency."""
    lat = np.array([x[3] for x in latencies], dtype=float)
    tot = {k: int(np.sum(v)) for k, v in counters.as_dict().items()}
    stats = None
    if lat.size:
        stats = {"count": int(lat.size), "mean": float(lat.mean()), "p50": float(np.percentile(lat, 50)),
                 "p95": float(np.percentile(lat, 95)), "max": float(lat.max())}
    return {"totals": tot, "per_link": counters.as_dict(), "latency_s": stats}


def bus_summary(bus: BusRecord, sc: Scenario) -> dict:
    """The blocks of a distributed run's summary.json that only its recording knows: bus
    latency per sender, faults, the selector's fallbacks, message counts, security and the
    recorder's bus gaps."""
    return {
        **({"bus_latency_ms": lat} if (lat := bus.latency_ms()) else {}),
        "faults": bus.faults,
        "selector_fallback_steps": bus.fallback_steps,
        "messages": {**bus.counts, **({"not_recorded_over_the_flood_cap": bus.not_recorded} if bus.not_recorded else {}),
                     **({"resent_not_written": bus.resent_not_written} if bus.resent_not_written else {})},
        "security": security_summary(sc.emulator.security, bus.dropped),
        **({"bus_gaps": bus.gaps} if bus.gaps else {}),
        **({"recorder_lag": {"max_lag_steps": sc.emulator.recorder_max_lag_steps, "steps_waited": bus.recorder_waits[0],
                             "wait_s": round(bus.recorder_waits[1], 3)}}
           if bus.recorder_waits is not None and sc.emulator.time_mode == "lockstep" else {}),
    }


def security_summary(on: bool, dropped: dict) -> dict:
    """``summary.json``'s ``security``: on or off (off says so in words), and what the world
    and each agent dropped: malformed messages, and of those the ones on a key their sender
    field may not use (someone speaking for another, whatever the router let through)."""
    out: dict = {"state": "on" if on else "off"}
    if not on:
        out["warning"] = ("emulator.security was off: no authentication and no access rules on the bus; "
                          "any process that reached the router could publish anything")
    names = sorted(dropped, key=lambda a: (a != "world", int(a.split("-")[1]) if a.startswith("agent-") else -1))
    out["malformed_dropped"] = {a: int(dropped[a][0]) for a in names}
    out["key_mismatch_dropped"] = {a: int(dropped[a][1]) for a in names}
    return out
