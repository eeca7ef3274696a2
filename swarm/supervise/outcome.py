"""What a distributed run came to: its summary, computed from the recording, and the exit
status ``swarm run`` returns.

A run ends in one of three ways. It **finished**: the summary covers every step and the
status is the world's (0). It was **interrupted** by a signal (SIGINT, SIGTERM, SIGHUP):
the summary covers the steps recorded and says ``"interrupted": {"reason": "SIGINT", ...}``,
the status is 128 + the signal. It **broke** (the bus was lost, the world died): the
summary says ``"interrupted": {"reason": <why>, ...}`` and the status is 3 (bus lost), 4
(the world died) or 5 (an agent left by itself, not by a fault, while the world ran; an
agent, the selector or the recorder lost its bus session while it ran; the recording misses
steps the world ran). Router
faults the supervisor carried out are listed even when no router was left to carry
their report over the bus.
"""

from __future__ import annotations

import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from swarmcore.scenario import Scenario
from swarmrt.protocol import EXIT_AGENT_LOST, EXIT_BUS_LOST, EXIT_WORLD_LOST

__all__ = ["RunOutcome", "run_outcome", "summary_of_steps_recorded", "last_step"]


@dataclass
class RunOutcome:
    summary: dict
    exit_code: int
    signal: signal.Signals | None = None  # interrupted by this signal
    broken: str | None = None  # why the run could not go on

    @property
    def finished(self) -> bool:
        return self.signal is None and self.broken is None


def last_step(summary: dict) -> int:
    """The last step the recording holds an estimate of (or its last truth step)."""
    return int(summary.get("last_estimated_step", summary["steps"] - 1))


def summary_of_steps_recorded(path: Path, sc: Scenario, log=None) -> dict:
    """The summary of an interrupted or broken run over the steps it recorded (0..last
    truth step), or an empty one if it never got to step 0."""
    from swarm.record.recording import load_recording

    try:
        return load_recording(path, sc.n_sats, None, scenario=sc).summary(sc)  # K from the recorded truth
    except (ValueError, FileNotFoundError) as exc:
        if log is not None:
            log(f"no step to summarise: {exc}")
        return {"scenario": sc.name, "n_sats": sc.n_sats, "seed": sc.seed, "steps": 0, "faults": []}


def run_outcome(sc: Scenario, recording: Path, *, run: str, world_exit_code: int | None, interrupted: signal.Signals | None,
                broken: str | None, router_faults: list[dict[str, Any]] = (), log=None,  # type: ignore[assignment]
                broken_code: int | None = None, router_gate: dict[str, Any] | None = None) -> RunOutcome:
    """The summary and exit status of a run (see the module docstring). ``world_exit_code``
    None: the run was interrupted before the world ended (or the supervisor stopped a broken
    run: ``broken_code``, its status)."""
    from swarm.record.recording import load_recording

    sig = interrupted if world_exit_code is None else None
    why = broken if sig is None else None
    summary: dict = {}
    if sig is None and why is None:
        rec = load_recording(recording, sc.n_sats, sc.steps, scenario=sc)  # with it, the run's bound (sc.bound)
        summary = rec.summary(sc)
        if (gaps := np.flatnonzero(~np.isfinite(rec.t_s))).size:
            # The world ran every step, the recording does not hold them all: the recorder
            # lost them (stalled past the lease, cut off). Its summary is not the run's.
            why = (f"the recording misses {gaps.size} of the {sc.steps} steps the world ran (from step {gaps[0]}): the "
                   "recorder lost them (stalled past the Zenoh lease, or cut off; see logs/recorder.log)")
            broken_code = EXIT_AGENT_LOST
    if why is not None or sig is not None:
        if not summary:
            summary = summary_of_steps_recorded(recording, sc, log)
        last = last_step(summary)
        if sig is not None:
            summary["interrupted"] = {"reason": sig.name, "signal": int(sig), "last_step": last, "steps_planned": sc.steps}
        else:
            summary["interrupted"] = {"reason": why, "world_exit_code": world_exit_code, "last_step": last, "steps_planned": sc.steps}
    known = {(f.get("action"), f.get("target"), f.get("phase")) for f in summary.get("faults", [])}
    for f in router_faults:
        if (f["action"], f["target"], f["phase"]) not in known:
            summary.setdefault("faults", []).append({k: v for k, v in f.items() if not k.endswith("_unix_s")})
    if router_gate:
        summary["router_gate"] = router_gate  # what the routers' ingress gates counted, per identity
    summary["run"] = run
    summary["world_exit_code"] = world_exit_code
    if sig is not None:
        code = 128 + int(sig)
    elif why is not None:
        code = broken_code or (EXIT_BUS_LOST if world_exit_code == EXIT_BUS_LOST else EXIT_WORLD_LOST)
    else:
        code = int(world_exit_code or 0)
    return RunOutcome(summary, code, sig, why)
