"""Run folders: ``summary.json``, ``truth.npz``, ``estimates.npz``, ``scenario.yaml``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import yaml

from swarmcore.sim import SimResult

__all__ = ["write_run", "write_json", "read_json", "number", "NO_DATA", "no_data_reason"]

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


def _link_arrays(result: SimResult) -> dict:
    """With links: the per-step cumulative link totals (K, 6: sent, delivered, delivered
    late, lost, dropped at the queue, unreachable) and each filter's late-measurement counts
    (K, F), for ``swarm report``."""
    if not result.scenario.links.enabled or result.link_series is None:
        return {}
    out = {"link_series": result.link_series, "late_used": result.late_used, "late_dropped": result.late_dropped,
           "replayed": result.replayed}
    if result.queue_bytes is not None:
        out["queue_bytes"] = result.queue_bytes
    if result.link_latencies is not None:
        out["link_latencies"] = np.array(result.link_latencies, dtype=float).reshape(-1, 4)
    return out


def write_run(result: SimResult, out: Path, *, arrays: bool = True, extra_summary: dict | None = None) -> dict:
    """Write a run folder and return the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    if extra_summary:
        summary.update(extra_summary)
    (out / "scenario.yaml").write_text(yaml.safe_dump(result.scenario.model_dump(mode="json"), sort_keys=False))
    if arrays:
        np.savez_compressed(out / "truth.npz", t=result.t, **result.truth)
        np.savez_compressed(
            out / "estimates.npz",
            t=result.t,
            **result.est,
            att_err=result.att_err,
            pos_err=result.pos_err,
            nees=result.nees,
            gate_accepted=result.gate_accepted,
            gate_rejected=result.gate_rejected,
            nis=result.nis,
            nis_dof=result.nis_dof,
            step_ms=result.step_ms,
            schedule=result.schedule,
            **_link_arrays(result),
        )
    write_json(out / "summary.json", summary)
    return summary
