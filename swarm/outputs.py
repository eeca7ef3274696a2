"""Run folders: ``summary.json``, ``truth.npz``, ``estimates.npz``, ``scenario.yaml``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from swarmcore.links import LinkCounters
from swarmcore.result import LinkArrays, RunBuilder, RunResult
from swarmcore.scenario import Scenario

__all__ = ["write_run", "read_run", "write_json", "read_json", "number", "NO_DATA", "no_data_reason"]

NO_DATA = "no data"


def number(x, spec: str = ".3g") -> str:
    """``x`` formatted with ``spec``, or "no data" when it is missing or not finite: a
    table never presents a NaN as a result."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return NO_DATA
    return format(v, spec) if math.isfinite(v) else NO_DATA


def no_data_reason(summary: dict) -> str:
    """Why a summary's table has "no data" cells."""
    intr = summary.get("interrupted")
    if intr:
        return (f"the run ended at step {intr.get('last_step')} of {intr.get('steps_planned', 0) - 1} "
                f"({intr.get('reason')}): no estimate to compare")
    est = summary.get("estimator", "full")
    others = (summary.get("rms") or {}).get("others") or {}
    own = (summary.get("rms") or {}).get("self") or {}
    if est != "full" and all(v == v for v in own.values()) and any(v != v for v in others.values()):
        return f"estimator {est!r} claims no estimate of the other satellites (it tracks its own)"
    return "no filter estimated those steps (every agent dead, or nothing recorded)"


def write_json(path: Path, data) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
    tmp.replace(path)


def read_json(path: Path):
    return json.loads(Path(path).read_text())


#: truth.npz's arrays: file key → the :class:`~swarmcore.result.TruthArrays` field.
_TRUTH_NPZ = {"q_BI": "q_BI", "omega_BI_B": "omega_BI_B_rad_s", "r_H": "r_H_m", "v_H": "v_H_m_s", "bias_B": "bias_B_rad_s"}
#: estimates.npz's arrays of every run: file key → the :class:`~swarmcore.result.RunResult`
#: field (``est.``: of its :class:`~swarmcore.result.EstimateArrays`).
_EST_NPZ = {"q_BI": "est.q_BI", "omega_BI_B": "est.omega_BI_B_rad_s", "r_H": "est.r_H_m", "v_H": "est.v_H_m_s",
            "bias_B": "est.bias_B_rad_s", "P_diag": "est.P_diag", "att_err": "att_err_rad", "pos_err": "pos_err_m", "nees": "nees",
            "gate_accepted": "gate_accepted", "gate_rejected": "gate_rejected", "nis": "nis", "nis_dof": "nis_dof",
            "step_ms": "step_ms", "schedule": "schedule", "taken": "taken"}
#: ... and of runs with links (the filters' late-measurement counts with them).
_LINK_NPZ = {"late_used": "late_used", "late_dropped": "late_dropped", "replayed": "replayed_steps"}


def _get(result: RunResult | RunBuilder, name: str):
    obj, _, attr = name.rpartition(".")
    return getattr(result.est if obj else result, attr)


def write_run(result: RunResult, out: Path, *, arrays: bool = True, extra_summary: dict | None = None) -> dict:
    """Write a run folder and return the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    if extra_summary:
        summary.update(extra_summary)
    assert result.scenario is not None  # summary() needs it
    (out / "scenario.yaml").write_text(yaml.safe_dump(result.scenario.model_dump(mode="json"), sort_keys=False))
    if arrays:
        np.savez_compressed(out / "truth.npz", t=result.t_s, **{key: getattr(result.truth, f) for key, f in _TRUTH_NPZ.items()})
        links = {}
        if result.links is not None:
            links = {"link_series": result.links.totals, **{key: _get(result, f) for key, f in _LINK_NPZ.items()},
                     "queue_bytes": result.links.queue_bytes,
                     "link_latencies": np.array(result.links.latencies, dtype=float).reshape(-1, 4)}
        np.savez_compressed(out / "estimates.npz", t=result.t_s, **{key: _get(result, f) for key, f in _EST_NPZ.items()}, **links)
    write_json(out / "summary.json", summary)
    return summary


def read_run(folder: Path, scenario: Scenario | None = None) -> RunResult:
    """The :class:`~swarmcore.result.RunResult` of a ``swarm sim`` folder written with its
    arrays (:func:`write_run`): what its npz files keep (arrays they do not keep, NaN; the
    radio's per-link counters from summary.json)."""
    folder = Path(folder)
    with np.load(folder / "truth.npz") as tr, np.load(folder / "estimates.npz") as es:
        K, n = tr["r_H"].shape[:2]
        b = RunBuilder(K, n)
        b.t_s[:] = tr["t"]
        for key, f in _TRUTH_NPZ.items():
            getattr(b.truth, f)[:] = tr[key]
        for key, f in _EST_NPZ.items():
            if key in es.files:  # (taken: written since one result schema; before, the pairs selected stand for it)
                _get(b, f)[:] = es[key]
            elif key == "taken":
                b.taken[:] = es["schedule"]
        summary = read_json(folder / "summary.json") if (folder / "summary.json").exists() else {}
        b.estimator = summary.get("estimator", "full")
        links = None
        if "link_series" in es.files and summary.get("links"):
            for key, f in _LINK_NPZ.items():
                _get(b, f)[:] = es[key]
            links = LinkArrays(es["link_series"], es["queue_bytes"], [tuple(x) for x in es["link_latencies"].tolist()],
                               LinkCounters(**{k: np.asarray(v) for k, v in summary["links"]["per_link"].items()}))
    res = b.result(scenario)
    res.links = links
    return res
