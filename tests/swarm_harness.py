"""Run a real swarm (router, recorder, world, selector, agents as processes) from a test."""

from __future__ import annotations

import threading

import numpy as np

from swarm.record.recording import load_recording
from swarm.supervise.launch import LocalSwarm
from swarmcore.scenario import Scenario


def scenario(**kw) -> Scenario:
    base = dict(name="it", seed=3, n_sats=4, duration_s=20, emulator={"step_timeout_s": 20.0})
    for k, v in kw.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            base[k] = {**base[k], **v}
        else:
            base[k] = v
    return Scenario(**base)


def run_swarm(sc: Scenario, out, during=None, timeout: float = 600.0, run_id: str | None = None):
    """Start the swarm, call ``during(swarm)`` on a thread (if given), run to the end,
    stop everything and return (recording, summary, exit codes by process name)."""
    sw = LocalSwarm(sc, out, run_id=run_id, log=lambda s: None)
    codes = {}
    th = None
    try:
        sw.start()
        if during is not None:
            th = threading.Thread(target=during, args=(sw,), daemon=True)
            th.start()
        codes["world"] = sw.run_to_end(timeout=timeout)
    finally:
        sw.stop()
        if th is not None:
            th.join(30)
        for name, p in sw.procs.items():
            codes.setdefault(name, p.returncode)
    rec = load_recording(out / "run.mcap", sc.n_sats, sc.steps)
    return rec, rec.summary(sc), codes, sw


def within_3sigma_per_observer(rec, observers, target, k_from=0, k_to=None) -> dict[int, float]:
    """For each observer alone: the fraction of its (step, component) errors on ``target``
    within 3σ over ``k_from ≤ k < k_to``."""
    return {o: within_3sigma_fraction(rec, [o], target, k_from, k_to)[0] for o in observers}


def within_3sigma_fraction(rec, observers, target, k_from=0, k_to=None):
    """Fraction of (step, observer, component) with |error| ≤ 3σ for one target, over
    steps ``k_from ≤ k < k_to``."""
    a, dr = rec.pose_errors()
    steps = slice(k_from, k_to)
    e = np.concatenate([a, dr], axis=-1)[steps, observers, target]  # (K', F', 6)
    sd = np.sqrt(rec.est.pose_var[steps, observers, target])
    ok = np.isfinite(e) & np.isfinite(sd)
    return float(np.mean(np.abs(e[ok]) <= 3 * sd[ok])), int(ok.sum())
