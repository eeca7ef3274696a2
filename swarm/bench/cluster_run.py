"""``swarm bench cluster-run``: a swarm over a Ray cluster of 1, 2, 3 ... nodes on this machine.

For each node count a throw-away local cluster (:class:`swarm.cluster.local.LocalRayCluster`:
each node in a network namespace of its own, the machine's cores shared between them: the
point is correctness and overhead, not speed-up), and on it, for each swarm size, one
lockstep run (``swarm run --cluster``, synthetic measurements, security on):

* **real-time factor** over the steady stepping (the clocks of the recording), **start-up**
  (the cluster's, then the run's to its first clock);
* **CPU per step by role** (user + system of every process of every node between the
  clocks of step 2 and of the last step, by role: agent, world, recorder, selector, router,
  ray — raylet, GCS, the host actors, Ray Client's server —, forkserver, driver);
* **PSS by role** at the peak of the summed PSS (sampled every 2 s);
* **cross-node bytes per step** per directed link between nodes: what host i's namespace
  sent host j's over the Zenoh routers' link, and everything else (Ray's own), counted by
  iptables in the namespaces (IP bytes, headers included), over the same steps.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["bench_cluster_run", "roles_now"]


def _role(name: str) -> str:
    base = name.rsplit("-", 1)
    return base[0] if len(base) == 2 and base[1].isdigit() else name


def roles_now(sw, hosts, memory: bool = True) -> dict[str, dict[str, float]]:
    """CPU seconds and (``memory``) PSS bytes of every process of the cluster's namespaces
    (and of this driver), summed by role (see the module docstring). Without memory it is
    quick (no /proc/PID/smaps): what the step marks take, on the supervisor's thread."""
    import psutil

    from swarm.cluster.netns import _ns_pids

    owner = {p.pid: ("router" if name.startswith("router") else _role(name)) for name, p in sw.procs.items()}
    out: dict[str, dict[str, float]] = {}

    def add(role: str, p) -> None:
        try:
            t = p.cpu_times()
            pss = p.memory_full_info().pss if memory else 0
        except psutil.Error:
            return
        r = out.setdefault(role, {"cpu_s": 0.0, "pss_bytes": 0.0, "processes": 0})
        r["cpu_s"] += t.user + t.system
        r["pss_bytes"] += pss
        r["processes"] += 1

    for h in hosts.hosts:
        for pid in _ns_pids(h.ns):
            try:
                p = psutil.Process(pid)
                role = None
                q: psutil.Process | None = p
                while q is not None and q.pid > 1:
                    if q.pid in owner:
                        role = owner[q.pid]
                        break
                    q = q.parent()
                if role is None:
                    name, cmd = p.name(), " ".join(p.cmdline())
                    if "forkserver" in cmd:
                        role = "forkserver"  # the node's agents' fork server (their shared pages are counted in it too)
                    elif (name in ("raylet", "gcs_server") or name.startswith("ray::") or "ray::" in cmd
                          or "site-packages/ray/" in cmd or "/bin/ray " in cmd):
                        role = "ray"  # raylet, GCS, the host actors, Ray Client's server, Ray's agents
                    else:
                        role = "other"
            except psutil.Error:
                continue
            add(role, p)
    add("driver", psutil.Process(os.getpid()))
    return out


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def bench_cluster_run(nodes: list[int], sats: list[int], duration_s: float = 30.0, estimator: str = "ci", graph: str = "nearest",
                      log=print, workdir: Path | None = None, agent_commands: str | None = None,
                      scenario: Path | None = None, out_json: Path | None = None) -> list[dict]:
    from swarm.bench.bus import bench_scenario
    from swarm.cluster.local import LocalRayCluster
    from swarm.cluster.swarm import RaySwarm
    from swarm.record.mcaplog import iter_messages
    from swarmrt.scenario_files import scenario_from_dict

    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="swarm-bench-cluster-"))
    rows: list[dict] = []
    for N in nodes:
        t0 = time.monotonic()
        # Ray counts whole CPUs per node: the machine's cores split between the nodes, at least one each.
        cluster = LocalRayCluster(N, cpus_per_node=max(1, round((os.cpu_count() or 2) / N)), namespaces=True, log=log)
        try:
            cluster.start()
            cluster_s = time.monotonic() - t0
            for n in sats:
                if scenario is not None:  # a scenario file, n_sats and duration_s set here
                    from swarmrt.scenario_files import load_scenario

                    sc = load_scenario(str(scenario), [f"n_sats={n}", f"duration_s={duration_s}"], None)
                else:
                    sc = bench_scenario(n, duration_s, True, estimator, graph, "fork")
                if agent_commands:
                    doc = sc.model_dump(mode="json")
                    doc["emulator"]["agent_commands"] = dict.fromkeys(range(n), agent_commands)
                    sc = scenario_from_dict(doc, "bench")
                out = base / f"nodes{N}-n{n}-{estimator}-{graph}"
                sw = RaySwarm(sc, out, "local-ray", log=lambda s: None, local_cluster=cluster)
                marks: dict[int, tuple[dict, dict[str, int]]] = {}
                peak: dict[str, Any] = {"pss": 0.0, "by_role": {}}
                stop = threading.Event()
                # The marks: the clocks of step 2 and of the step before the last (at the last
                # clock the agents may already be leaving, and their CPU with them).
                last = sc.steps - 2
                load_at_start = _uptime()

                def sample(sw=sw, peak=peak, stop=stop, cluster=cluster) -> None:
                    while not stop.wait(2.0):
                        if not sw.procs:
                            continue
                        r = roles_now(sw, cluster.hosts)
                        tot = sum(v["pss_bytes"] for v in r.values())
                        if tot > peak["pss"]:
                            peak["pss"], peak["by_role"] = tot, {k: v["pss_bytes"] for k, v in r.items()}
                            peak["processes"] = {k: v["processes"] for k, v in r.items()}

                def progress(k1: int, _K: int, marks=marks, sw=sw, last=last, cluster=cluster) -> None:
                    k = k1 - 1
                    if (k == 2 or k == last) and k not in marks:
                        link = cluster.hosts.link_bytes()  # first: the quicker, and the one a late read skews most
                        marks[k] = (roles_now(sw, cluster.hosts, memory=False), link)

                t_start, t_start_ns = time.perf_counter(), time.time_ns()
                sampler = threading.Thread(target=sample, daemon=True)
                code = None
                try:
                    assert cluster.hosts is not None  # namespaced nodes (root): the counters need them
                    # The byte counters go in once the routers listen, before any role starts.
                    sw.on_routers = lambda eps, hosts=cluster.hosts: hosts.count_links([int(e.rsplit(":", 1)[1]) for e in eps])
                    sw.start()
                    sampler.start()
                    code = sw.run_to_end(progress=progress)
                finally:
                    stop.set()
                    sw.stop()
                    _clear_counters(cluster.hosts)
                total = time.perf_counter() - t_start
                clocks = [lt for topic, _s, _d, lt, _p in iter_messages(out / "run.mcap") if topic.endswith("/clock")]
                wall = (max(clocks) - min(clocks)) / 1e9 if clocks else None
                row: dict[str, Any] = {"nodes": N, "n": n, "estimator": sc.estimator.kind, "graph": sc.graph.kind,
                                       "scenario": str(scenario) if scenario else sc.name,
                                       "agents": "rust" if agent_commands else "python", "world_exit_code": code,
                                       "cluster_start_s": cluster_s, "startup_s": (min(clocks) - t_start_ns) / 1e9 if clocks else None,
                                       "run_startup_s": dict(sw.startup_s), "sim_seconds": duration_s, "stepping_wall_s": wall,
                                       "realtime_factor": duration_s / wall if wall else None, "total_wall_s": total,
                                       "uptime_at_start": load_at_start, "uptime_at_end": _uptime(),
                                       "pss_peak_gib": peak["pss"] / 2**30,
                                       "pss_peak_gib_by_role": {k: v / 2**30 for k, v in peak["by_role"].items()},
                                       "processes_by_role": peak.get("processes", {})}
                if 2 in marks and last in marks and last > 2:
                    (ra, ba), (rb, bb) = marks[2], marks[last]
                    steps = last - 2
                    row["cpu_ms_per_step_by_role"] = {r: 1e3 * (rb.get(r, {}).get("cpu_s", 0) - ra.get(r, {}).get("cpu_s", 0)) / steps
                                                      for r in sorted(set(ra) | set(rb))}
                    row["cpu_ms_per_step_total"] = sum(row["cpu_ms_per_step_by_role"].values())
                    link = {k: (bb.get(k, 0) - ba.get(k, 0)) / steps for k in sorted(set(ba) | set(bb))}
                    row["bytes_per_step_by_link"] = link
                    row["zenoh_bytes_per_step_between_nodes"] = sum(v for k, v in link.items() if k.endswith("zenoh"))
                    row["other_bytes_per_step_between_nodes"] = sum(v for k, v in link.items() if k.endswith("other"))
                rtf = row["realtime_factor"]
                if out_json is not None:  # every row as soon as it is measured
                    from swarm.outputs import write_json

                    write_json(out_json, {"rows": [*rows, row]})
                log(f"nodes={N} n={n:4d} {sc.name} {row['estimator']}/{row['graph']} ({row['agents']} agents): real-time factor "
                    f"{rtf:.2f}× " if rtf else f"nodes={N} n={n}: no clock recorded ")
                log(f"  start-up: cluster {cluster_s:.1f} s, run {row['startup_s']:.1f} s; PSS peak {row['pss_peak_gib']:.2f} GiB "
                    f"({', '.join(f'{k} {v:.2f}' for k, v in sorted(row['pss_peak_gib_by_role'].items(), key=lambda kv: -kv[1]))})")
                if "cpu_ms_per_step_by_role" in row:
                    log("  CPU per step: " + ", ".join(f"{k} {v:.0f} ms" for k, v in sorted(row["cpu_ms_per_step_by_role"].items(),
                                                                                         key=lambda kv: -kv[1]))
                        + f" (total {row['cpu_ms_per_step_total']:.0f} ms)")
                    log(f"  between nodes per step: Zenoh {row['zenoh_bytes_per_step_between_nodes']:.0f} B, Ray and other "
                        f"{row['other_bytes_per_step_between_nodes']:.0f} B; {load_at_start}")
                rows.append(row)
        finally:
            cluster.close()
    return rows


def _clear_counters(hosts) -> None:
    from swarm.cluster.netns import _run_in

    for h in hosts.hosts:
        _run_in(h.ns, "iptables", "-w", "-D", "OUTPUT", "-j", "SWARM_ACCT", check=False)
        _run_in(h.ns, "iptables", "-w", "-F", "SWARM_ACCT", check=False)
        _run_in(h.ns, "iptables", "-w", "-X", "SWARM_ACCT", check=False)
