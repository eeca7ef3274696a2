"""What the live 3-D view costs a run: the real-time factor of ``swarm run`` (lockstep) with
no view, with the view and no client, and with the view and a client subscribed to every
channel (``python -m swarm.live.client``, its own process, reading all the time).

Runs alternate between the three settings (``repeats`` rounds), so that a machine whose load
drifts (other work on the same cores) affects each alike. The real-time factor is taken over
the steady stepping, from the recorded clocks of steps ``skip`` … K−1 (start-up excluded).
The view's own CPU time (its process: decoding, building, serving) and what the client
received are reported too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["bench_live", "MODES"]

#: The settings compared: no view; the view with nobody watching; the view and a client.
MODES = ("off", "view", "view+client")


def _stepping(mcap: Path, skip: int) -> tuple[float, int]:
    """(wall seconds, steps) of the recorded clocks from step ``skip`` on."""
    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.messages import MessageError
    from swarmrt.bus.receive import receive

    t: dict[int, int] = {}
    for topic, _s, data, log_ns, _p in iter_messages(mcap):
        if topic.endswith("/clock") and not topic.startswith("/"):
            try:
                m = receive(topic, data, None, expect="clock").msg
            except MessageError:
                continue
            if not m.done:
                t.setdefault(int(m.k), log_ns)
    ks = sorted(k for k in t if k >= skip)
    if len(ks) < 2:
        return float("nan"), 0
    return (t[ks[-1]] - t[ks[0]]) / 1e9, ks[-1] - ks[0]


def _one(n: int, duration_s: float, mode: str, out: Path, skip: int, log) -> dict[str, Any]:
    from swarm.supervise.launch import LocalSwarm
    from swarmcore.scenario import Scenario

    sc = Scenario(name=f"bench-live-n{n}", seed=1, n_sats=n, duration_s=duration_s)
    live = "127.0.0.1:0" if mode != "off" else None
    sw = LocalSwarm(sc, out, log=lambda s: None, live=live)
    client = None
    t0 = time.perf_counter()
    try:
        sw.start()
        if mode == "view+client":
            url = json.loads((out / "live.json").read_text())["url"]
            with open(out / "logs" / "client.log", "wb") as err:
                client = subprocess.Popen([sys.executable, "-m", "swarm.live.client", url, "--seconds", "100000", "--json",
                                           str(out / "client.json")], stdout=subprocess.DEVNULL, stderr=err,
                                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
        code = sw.run_to_end()
    finally:
        sw.stop()
        if client is not None:
            try:
                client.wait(timeout=30)  # it ends when the view closes the connection
            except subprocess.TimeoutExpired:
                client.kill()
                client.wait()
    total = time.perf_counter() - t0
    wall, steps = _stepping(out / "run.mcap", skip)
    row: dict[str, Any] = {"n": n, "mode": mode, "sim_seconds": steps * sc.dt_s, "stepping_wall_s": wall,
                           "realtime_factor": steps * sc.dt_s / wall if wall > 0 else None, "total_wall_s": total,
                           "world_exit_code": code}
    if mode != "off":
        st = json.loads((out / "live.json").read_text()).get("stats") or {}
        row["view"] = st
    if client is not None and (out / "client.json").exists():
        c = json.loads((out / "client.json").read_text())
        row["client"] = {"messages": c["messages"], "bytes": c["bytes"], "cpu_s": c["cpu_s"]}
    log(f"n={n} {mode:12s}: real-time factor {row['realtime_factor']:.1f}× ({row['sim_seconds']:.0f} sim s in {wall:.1f} wall s)"
        + (f"; view CPU {row['view'].get('cpu_s', float('nan')):.1f} s, {row['view'].get('scene_messages', 0)} scene messages"
           if "view" in row else "")
        + (f"; client got {row['client']['messages']} messages ({row['client']['bytes'] / 1e6:.1f} MB)" if "client" in row else ""))
    return row


def bench_live(n: int = 10, duration_s: float = 60.0, repeats: int = 3, log=print, workdir: Path | None = None,
               skip: int = 3) -> dict[str, Any]:
    """Rounds of the three :data:`MODES` at swarm size ``n``; returns every run and, per
    mode, the median and spread of the real-time factor."""
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="swarm-bench-live-"))
    rows = []
    for r in range(repeats):
        for mode in MODES:
            rows.append({"round": r, **_one(n, duration_s, mode, base / f"r{r}-{mode.replace('+', '-')}", skip, log)})
    summary = {}
    for mode in MODES:
        rtf = np.array([x["realtime_factor"] for x in rows if x["mode"] == mode and x["realtime_factor"]], dtype=float)
        summary[mode] = {"rtf_median": float(np.median(rtf)) if rtf.size else None, "rtf_min": float(rtf.min()) if rtf.size else None,
                         "rtf_max": float(rtf.max()) if rtf.size else None, "runs": int(rtf.size)}
    off = summary["off"]["rtf_median"]
    for mode in MODES[1:]:
        m = summary[mode]["rtf_median"]
        summary[mode]["vs_off"] = m / off if m and off else None
    return {"n": n, "duration_s": duration_s, "repeats": repeats, "skip_steps": skip, "load_avg_1min_before": os.getloadavg()[0],
            "summary": summary, "rows": rows}
