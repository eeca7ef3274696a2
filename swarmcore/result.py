"""One run's result, whatever ran it: the in-process simulator (``swarm sim``,
:func:`swarmcore.sim.simulate`) and the recording of a distributed run (``swarm run``,
:func:`swarm.record.recording.load_recording`) both fill a :class:`RunResult` through one
:class:`RunBuilder`, and ``summary.json`` is built from it alone
(:func:`swarmcore.metrics.run_summary`). The API (:class:`swarm.api.Result`), the report,
``swarm mc`` and the studies read it.

Shapes: K steps, F filters (one per satellite: filter f is satellite f's, F = n), n
satellites. Quaternions scalar-last (Shuster), ``q_BI`` from the inertial frame to each
body frame; positions and velocities in the Hill (HCW) frame H of the formation. NaN where
a filter has no estimate of a satellite (it does not track it, was dead, or its message
never arrived) and where a step has no truth.

Adding a metric (one place for both runs): a per-step array is a field here, filled in
:meth:`RunBuilder.estimate_at` (what a filter claimed against the truth) or
:meth:`RunBuilder.report_at` (what a filter reported, a field of the ``Estimate`` message
for distributed runs); its ``summary.json`` block goes in
:func:`swarmcore.metrics.run_summary`. Both runs then have it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from .crlb import BoundArrays, posterior_crlb
from .links import LinkCounters
from .metrics import pose_errors, pose_nees, relative_errors_of, run_summary

if TYPE_CHECKING:
    from .scenario import Scenario

__all__ = ["RunResult", "RunBuilder", "TruthArrays", "EstimateArrays", "LinkArrays", "BusRecord", "BusTimes", "BoundArrays",
           "LINK_TOTALS", "POSE_ROWS"]

#: The columns of :attr:`LinkArrays.totals`: copies over every directed link, cumulative.
LINK_TOTALS = ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")
#: The pose rows [a (rad), Δr (m)] among a satellite's 12 error states (``P_diag``'s layout).
POSE_ROWS = np.r_[0:3, 6:9]


@dataclass
class TruthArrays:
    """The world's truth at each step."""

    q_BI: np.ndarray  # (K, n, 4) attitude
    omega_BI_B_rad_s: np.ndarray  # (K, n, 3) body rate, in B
    r_H_m: np.ndarray  # (K, n, 3) position, in H
    v_H_m_s: np.ndarray  # (K, n, 3) velocity, in H
    bias_B_rad_s: np.ndarray  # (K, n, 3) each gyro's bias, in B


@dataclass
class EstimateArrays:
    """Every filter's posterior at each step (what its ``Estimate`` message carries)."""

    q_BI: np.ndarray  # (K, F, n, 4)
    omega_BI_B_rad_s: np.ndarray  # (K, F, n, 3)
    r_H_m: np.ndarray  # (K, F, n, 3)
    v_H_m_s: np.ndarray  # (K, F, n, 3)
    bias_B_rad_s: np.ndarray  # (K, F, 3) the filter's own gyro bias
    P_diag: np.ndarray  # (K, F, 12 n) diagonal of the covariance, 12 error states per satellite

    @cached_property
    def pose_var(self) -> np.ndarray:
        """(K, F, n, 6) the variances of each satellite's [a (rad², body frame), Δr (m², H)]:
        the pose rows of ``P_diag`` (the diagonal of the ``P_pose`` the filter claims)."""
        K, F, m = self.P_diag.shape
        return self.P_diag.reshape(K, F, m // 12, 12)[..., POSE_ROWS]


@dataclass
class LinkArrays:
    """What the radio did (runs with ``links.enabled``)."""

    totals: np.ndarray  # (K, 6) int, cumulative after each step, columns LINK_TOTALS
    queue_bytes: np.ndarray  # (K, n) int: each transmitter's backlog at the step (bytes)
    latencies: list  # (sender, receiver, sent step, latency s) of every delivered batch
    counters: LinkCounters  # per directed link, cumulative at the last step


@dataclass
class BusTimes:
    """Publish and receive times of every bus message of a recording (one row each)."""

    sender: np.ndarray  # (M,) str: the message header's sender
    kind: np.ndarray  # (M,) str: message kind (est, meas, health, ...)
    k: np.ndarray  # (M,) step
    published_ns: np.ndarray  # (M,) int64: MCAP publish time (the publisher's Zenoh timestamp)
    received_ns: np.ndarray  # (M,) int64: MCAP log time (the recorder's receive time)

    @property
    def latency_ms(self) -> np.ndarray:
        return (self.received_ns - self.published_ns) / 1e6

    def latency_stats(self, published_from_ns: int | None = None, published_to_ns: int | None = None) -> dict:
        """Per sender (``agent-3``, ``world``, ...): the one-way bus latency of its messages
        (receive time − the publisher's Zenoh timestamp, ms) as ``n``, ``min``, ``p50``,
        ``p95``, ``max``; optionally only messages published in ``[published_from_ns,
        published_to_ns)`` (Unix ns). Messages that carried no timestamp (publish time =
        log time) are left out and counted as ``unstamped``."""
        sel = np.ones(self.k.shape, dtype=bool)
        if published_from_ns is not None:
            sel &= self.published_ns >= published_from_ns
        if published_to_ns is not None:
            sel &= self.published_ns < published_to_ns
        lat = self.latency_ms
        out = {}
        for sender in sorted(set(self.sender[sel].tolist())):
            mine = sel & (self.sender == sender)
            stamped = mine & (self.published_ns != self.received_ns)
            x = lat[stamped]
            row: dict[str, float] = {"n": int(x.size)}
            if x.size:
                row.update({"min": round(float(x.min()), 3), "p50": round(float(np.percentile(x, 50)), 3),
                            "p95": round(float(np.percentile(x, 95)), 3), "max": round(float(x.max()), 3)})
            if (unstamped := int(mine.sum() - stamped.sum())):
                row["unstamped"] = unstamped
            out[sender] = row
        return out


@dataclass
class BusRecord:
    """What only the recording of a distributed run holds: its bus traffic and events."""

    faults: list = field(default_factory=list)  # every fault command and report (dicts, as in summary.json)
    fallback_steps: list = field(default_factory=list)  # steps the selector fell back to its state-free strategy
    select_ms: list = field(default_factory=list)  # the selector's time per selection (ms)
    counts: dict = field(default_factory=dict)  # message kind → messages recorded
    liveliness: list = field(default_factory=list)  # liveliness changes (dicts, with log_time_ns)
    rejoins: list = field(default_factory=list)  # the radio's fates of restarted agents' state transfers
    dropped: dict = field(default_factory=dict)  # agent-<i> or world → (malformed, of which key mismatch): its last report
    not_recorded: dict = field(default_factory=dict)  # key → messages the recorder's flood cap did not write
    times: BusTimes | None = None  # every bus message's sender, kind, step, publish and receive time
    gaps: list = field(default_factory=list)  # the recorder's bus gaps (no router reachable)
    resent: int = 0  # messages recorded twice (sent again after a bus gap; read once)
    resent_not_written: dict = field(default_factory=dict)  # key → resends the recorder counted and did not write again
    recorder_waits: tuple[int, float] | None = None  # the world's last clock: (steps it waited for the recorder, wall s)

    def latency_ms(self, published_from_ns: int | None = None, published_to_ns: int | None = None) -> dict:
        """:meth:`BusTimes.latency_stats` of the recording ({} without bus times)."""
        return self.times.latency_stats(published_from_ns, published_to_ns) if self.times is not None else {}


@dataclass
class RunResult:
    """One run (see the module docstring): truth, every filter's estimates, their errors
    and claims, the filters' reports, the measurement schedule and, as the run had them,
    the radio's and the bus's records."""

    scenario: Scenario | None  # None: a recording read without its scenario
    estimator: str  # estimator.kind of the filters
    t_s: np.ndarray  # (K,) time of each step (s)
    truth: TruthArrays
    est: EstimateArrays
    # Each filter's estimate of each satellite against the truth (NaN where none):
    att_err_rad: np.ndarray  # (K, F, n) |a|, q = δq(a) ⊗ q̂
    pos_err_m: np.ndarray  # (K, F, n) |r − r̂| (H)
    nees: np.ndarray  # (K, F, n) 6-dof NEES of [a, Δr] against the filter's P_pose
    # ... and of each tracked peer relative to the filter's own satellite:
    rel_att_err_rad: np.ndarray  # (K, F, n) error of q_BjBf (in B_j); NaN on the own row
    rel_pos_err_m: np.ndarray  # (K, F, n) error of r_j − r_f (H)
    rel_nees: np.ndarray  # (K, F, n) against the relative covariance the filter claims
    # What each filter reported of its step (K, F):
    gate_accepted: np.ndarray  # relative measurements the χ² gate accepted
    gate_rejected: np.ndarray  # and rejected
    nis: np.ndarray  # joint NIS of the update (NaN: none)
    nis_dof: np.ndarray  # its degrees of freedom
    late_used: np.ndarray  # late measurements inserted at their own step (replay)
    late_dropped: np.ndarray  # late measurements dropped
    replayed_steps: np.ndarray  # filter steps re-run for them
    step_ms: np.ndarray  # wall time of the filter step (predict + update, ms)
    cpu_ms: np.ndarray  # CPU time of the filter step (the thread's, ms)
    bytes_sent: np.ndarray  # bytes the satellite put on its radio (its batch and estimator message)
    schedule: np.ndarray  # (K, n, n) bool: [observer, target] pairs selected for the step (a recording: the selector's; none without one)
    taken: np.ndarray  # (K, n, n) bool: relative measurements in the batches put on the radio
    links: LinkArrays | None = None  # runs with links
    bus: BusRecord | None = None  # distributed runs (the recording's)
    bound: BoundArrays | None = None  # the Cramér–Rao bound (bound.enabled: swarmcore.crlb; a recording read with its scenario)

    @property
    def K(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n(self) -> int:
        return int(self.truth.q_BI.shape[1])

    @cached_property
    def alive(self) -> np.ndarray:
        """(K, F) bool: filter f has a posterior at step k (its agent ran the step)."""
        return np.isfinite(self.est.r_H_m[..., 0]).any(axis=-1)

    @cached_property
    def tracked(self) -> np.ndarray:
        """(K, F, n) bool: filter f has an estimate of satellite j at step k."""
        return np.isfinite(self.est.r_H_m[..., 0])

    def pose_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Error vectors ``a`` (rad, q = δq(a) ⊗ q̂, body frame) and ``Δr = r − r̂`` (m, H) of
        every filter's estimate of every satellite, (K, F, n, 3) each (NaN where none)."""
        return pose_errors(self.est.q_BI, self.est.r_H_m, self.truth.q_BI[:, None], self.truth.r_H_m[:, None])

    def summary(self, sc: Scenario | None = None) -> dict:
        """``summary.json`` of the run (:func:`swarmcore.metrics.run_summary`); ``sc``: the
        scenario, if the result was read without one."""
        scenario = sc if sc is not None else self.scenario
        if scenario is None:
            raise ValueError("summary(): this result has no scenario; pass the one it ran")
        return run_summary(self, scenario)


class RunBuilder:
    """Fills a :class:`RunResult` step by step: the simulator as it runs, the recording
    reader message by message. Every per-step array of a run is computed here (once for
    both), from what a filter claims and the truth of its step."""

    def __init__(self, K: int, n: int):
        nan = np.nan
        F = n
        self.K, self.n = K, n
        self.t_s = np.full(K, nan)
        self.truth = TruthArrays(q_BI=np.full((K, n, 4), nan), omega_BI_B_rad_s=np.full((K, n, 3), nan),
                                 r_H_m=np.full((K, n, 3), nan), v_H_m_s=np.full((K, n, 3), nan), bias_B_rad_s=np.full((K, n, 3), nan))
        self.est = EstimateArrays(q_BI=np.full((K, F, n, 4), nan), omega_BI_B_rad_s=np.full((K, F, n, 3), nan),
                                  r_H_m=np.full((K, F, n, 3), nan), v_H_m_s=np.full((K, F, n, 3), nan),
                                  bias_B_rad_s=np.full((K, F, 3), nan), P_diag=np.full((K, F, 12 * n), nan))
        self.att_err_rad, self.pos_err_m, self.nees, self.rel_att_err_rad, self.rel_pos_err_m, self.rel_nees = (
            np.full((K, F, n), nan) for _ in range(6))
        self.gate_accepted, self.gate_rejected, self.nis_dof, self.late_used, self.late_dropped, self.replayed_steps = (
            np.zeros((K, F), dtype=int) for _ in range(6))
        self.nis, self.step_ms, self.cpu_ms, self.bytes_sent = (np.full((K, F), nan) for _ in range(4))
        self.schedule = np.zeros((K, n, n), dtype=bool)
        self.taken = np.zeros((K, n, n), dtype=bool)
        self.estimator = "full"
        self._link_totals: np.ndarray | None = None  # (K, 6), with a row per step given
        self._link_queue: np.ndarray | None = None
        self._link_given: np.ndarray | None = None  # (K,) bool
        self._link_last: tuple[int, LinkCounters] | None = None
        self.link_latencies: list = []
        # What the Cramér–Rao bound counts (measured_at, absolute_at); None: no bound.
        self._bound_rel: list[list] | None = None
        self._bound_abs: np.ndarray | None = None

    # -- the world ------------------------------------------------------------------------------
    def truth_at(self, k: int, t_s: float, q_BI, omega_BI_B_rad_s, r_H_m, v_H_m_s, bias_B_rad_s) -> None:
        self.t_s[k] = t_s
        tr = self.truth
        tr.q_BI[k], tr.omega_BI_B_rad_s[k], tr.r_H_m[k], tr.v_H_m_s[k], tr.bias_B_rad_s[k] = (
            q_BI, omega_BI_B_rad_s, r_H_m, v_H_m_s, bias_B_rad_s)

    def selected_at(self, k: int, observers, targets) -> None:
        """The pairs selected for step k (observer → target)."""
        self.schedule[k, observers, targets] = True

    def taken_at(self, k: int, observer: int, targets) -> None:
        """Observer's relative measurements of step k in the batch it put on the radio."""
        self.taken[k, observer, targets] = True

    def measured_at(self, k: int, batch) -> None:
        """Relative measurements (a :class:`~swarmcore.mekf.RelativeMeasurements`) taken at
        step k that the Cramér–Rao bound counts (called once or more per step; a step never
        called counts nothing)."""
        if self._bound_rel is None:
            self._bound_rel = [[] for _ in range(self.K)]
        if len(batch):
            self._bound_rel[k].append(batch)

    def absolute_at(self, k: int, sats) -> None:
        """The satellites whose absolute reading (star tracker, GPS) of step k the bound counts."""
        if self._bound_abs is None:
            self._bound_abs = np.zeros((self.K, self.n), dtype=bool)
        self._bound_abs[k, sats] = True

    def links_at(self, k: int, counters: LinkCounters, queue_bytes) -> None:
        """The radio's cumulative per-link counters after step k and each transmitter's
        backlog then."""
        if self._link_totals is None:
            self._link_totals = np.zeros((self.K, len(LINK_TOTALS)), dtype=int)
            self._link_queue = np.zeros((self.K, self.n), dtype=int)
            self._link_given = np.zeros(self.K, dtype=bool)
        assert self._link_queue is not None and self._link_given is not None
        self._link_totals[k] = [getattr(counters, c).sum() for c in LINK_TOTALS]
        self._link_queue[k] = queue_bytes
        self._link_given[k] = True
        if self._link_last is None or k >= self._link_last[0]:
            self._link_last = (k, counters)

    # -- a filter -------------------------------------------------------------------------------
    def estimate_at(self, k: int, f: int, ids: np.ndarray, q_BI, omega_BI_B_rad_s, r_H_m, v_H_m_s, bias_B_rad_s, P_diag,
                    P_pose, P_rel_pose=None) -> None:
        """Filter f's posterior at step k of the satellites ``ids`` (rows, ascending, f
        among them): states (m, ·), its own gyro bias (3,), the diagonal of what it keeps
        (12 m), pose covariances ``P_pose`` (m, 6, 6) and, if claimed, ``P_rel_pose`` (m, 6,
        6) of each relative to f. Scored against the truth of step k (given already): its
        errors and NEES of each satellite, and of each peer relative to itself."""
        e = self.est
        e.q_BI[k, f, ids] = q_BI
        e.omega_BI_B_rad_s[k, f, ids] = omega_BI_B_rad_s
        e.r_H_m[k, f, ids] = r_H_m
        e.v_H_m_s[k, f, ids] = v_H_m_s
        e.bias_B_rad_s[k, f] = bias_B_rad_s
        e.P_diag[k, f, (12 * ids[:, None] + np.arange(12)).ravel()] = P_diag
        # A diverged filter or a damaged recording (numbers near the float limit, NaN) is
        # scored inf or NaN, never warned about (the mcap fuzz harness: an error of 1e200 m).
        with np.errstate(over="ignore", invalid="ignore"):
            self._score(k, f, ids, q_BI, r_H_m, P_pose, P_rel_pose)

    def _score(self, k: int, f: int, ids: np.ndarray, q_BI, r_H_m, P_pose, P_rel_pose) -> None:
        q_true, r_true = self.truth.q_BI[k], self.truth.r_H_m[k]
        a, dr = pose_errors(q_BI, r_H_m, q_true[ids], r_true[ids])
        self.att_err_rad[k, f, ids] = np.linalg.norm(a, axis=-1)
        self.pos_err_m[k, f, ids] = np.linalg.norm(dr, axis=-1)
        self.nees[k, f, ids] = pose_nees(a, dr, P_pose)
        own = np.flatnonzero(ids == f)
        if own.size and ids.size > 1:
            a_rel, dr_rel = relative_errors_of(q_BI, r_H_m, int(own[0]), q_true[ids], r_true[ids])
            others = ids != f
            oi = ids[others]
            self.rel_att_err_rad[k, f, oi] = np.linalg.norm(a_rel[others], axis=-1)
            self.rel_pos_err_m[k, f, oi] = np.linalg.norm(dr_rel[others], axis=-1)
            if P_rel_pose is not None:
                self.rel_nees[k, f, oi] = pose_nees(a_rel[others], dr_rel[others], P_rel_pose[others])

    def report_at(self, k: int, f: int, *, gate_accepted: int, gate_rejected: int, nis: float, nis_dof: int, late_used: int,
                  late_dropped: int, replayed_steps: int) -> None:
        """What filter f reported of its update at step k."""
        self.gate_accepted[k, f] = gate_accepted
        self.gate_rejected[k, f] = gate_rejected
        self.nis[k, f] = nis
        self.nis_dof[k, f] = nis_dof
        self.late_used[k, f] = late_used
        self.late_dropped[k, f] = late_dropped
        self.replayed_steps[k, f] = replayed_steps

    def result(self, scenario: Scenario | None, bus: BusRecord | None = None) -> RunResult:
        links = None
        if self._link_totals is not None and self._link_last is not None:
            assert self._link_queue is not None and self._link_given is not None
            totals, queue = self._link_totals, self._link_queue
            for k in range(1, self.K):  # a step with no record keeps the last one's (the totals are cumulative)
                if not self._link_given[k]:
                    totals[k], queue[k] = totals[k - 1], queue[k - 1]
            links = LinkArrays(totals, queue, list(self.link_latencies), self._link_last[1])
        return RunResult(
            scenario=scenario, estimator=self.estimator, t_s=self.t_s, truth=self.truth, est=self.est,
            att_err_rad=self.att_err_rad, pos_err_m=self.pos_err_m, nees=self.nees, rel_att_err_rad=self.rel_att_err_rad,
            rel_pos_err_m=self.rel_pos_err_m, rel_nees=self.rel_nees, gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected, nis=self.nis, nis_dof=self.nis_dof, late_used=self.late_used,
            late_dropped=self.late_dropped, replayed_steps=self.replayed_steps, step_ms=self.step_ms, cpu_ms=self.cpu_ms,
            bytes_sent=self.bytes_sent, schedule=self.schedule, taken=self.taken, links=links, bus=bus,
            bound=self._bound(scenario))

    def _bound(self, scenario: Scenario | None) -> BoundArrays | None:
        """The Cramér–Rao bound of what was given to :meth:`measured_at` and
        :meth:`absolute_at` along the truth (``scenario.bound``: on, and whose gyros)."""
        if scenario is None or not scenario.bound_on or (self._bound_rel is None and self._bound_abs is None):
            return None
        from .mekf import RelativeMeasurements

        # Along the truth from step 0 to the first step without one (a recording that misses
        # steps: the recursion cannot cross them); NaN from there on.
        missing = np.flatnonzero(~np.isfinite(self.truth.q_BI).all(axis=(1, 2)))
        K = int(missing[0]) if missing.size else self.K
        if K == 0:
            return None
        rel = [RelativeMeasurements.concat(b) for b in (self._bound_rel or [[] for _ in range(self.K)])[:K]]
        absolute = self._bound_abs if self._bound_abs is not None else np.zeros((self.K, self.n), dtype=bool)
        tr = self.truth
        truth = tr if K == self.K else TruthArrays(*(x[:K] for x in (tr.q_BI, tr.omega_BI_B_rad_s, tr.r_H_m, tr.v_H_m_s,
                                                                      tr.bias_B_rad_s)))
        f = scenario.bound.filter
        b = posterior_crlb(scenario, truth, rel, absolute[:K], gyros=None if f is None else [f],
                           kind="central" if f is None else f"filter {f}")
        if K < self.K:
            for name in ("att_rad2", "pos_m2", "rel_pos_m2", "att_axes_rad2", "pos_axes_m2"):
                x = getattr(b, name)
                if x is not None:
                    setattr(b, name, np.concatenate([x, np.full((self.K - K, *x.shape[1:]), np.nan)]))
        return b
