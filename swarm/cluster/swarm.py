"""``swarm run --cluster``: one swarm over the nodes of a Ray cluster.

:class:`RaySwarm` is :class:`swarm.supervise.launch.LocalSwarm` whose processes live on Ray
nodes: the supervisor (this process, the driver) keeps everything that decides — faults,
the run's end, broken runs, the summary — and each node's :class:`swarm.cluster.host.NodeHost`
actor starts and signals the processes there. What it adds:

* **a Zenoh router per node, meshed** (every router dials the ones started before it, as
  ``--routers 2`` does; each has its fixed id from ``--index``); every process connects to
  its own node's router; the driver (and ``swarm fault``) to the head's.
* **placement** (``emulator.placement``): world, selector and recorder on the head (node 0)
  unless the scenario says otherwise; satellite i on node ``i mod N`` (``spread``) or where the
  scenario's list puts it. Ray places the host actors (node affinity, one per node).
* **credentials made on the head** (:meth:`NodeHost.make_keys`) and handed to each node as
  Ray objects the driver never fetches: a node gets its router's dictionary (the head's
  whole; a worker's, the agents' and the mesh's only), the credentials of the roles and
  agents it runs, nothing else; the driver gets the supervisor's, the CLI's and the
  observer's (``swarm fault --run-dir`` works as for a local run). When the cluster spans
  hosts (two nodes or more, :func:`cluster_tls`) every Zenoh link between hosts is mutual
  TLS: the head makes a CA, one certificate per node's router (its address) and the driver's
  client certificate; node i gets its own router's key only, and the routers listen on
  ``tls/`` endpoints for the mesh and the driver only.
* **an ingress gate per node** (:mod:`swarm.supervise.gate`, as a local run has): the node's
  own processes reach its router through it, each identity at its own port of the host's
  loopback, rate-limited; its counts go into ``summary.json`` (``router_gate``).
* **hosts that fail**: ``kill-node N`` takes node N down (on a local cluster every process of
  its namespace SIGKILLed, the raylet included; on real hosts its actor SIGKILLs the run's
  processes there and its raylet); its agents are started again on the surviving nodes (the
  fewest agents first) with ``--restart`` (warm: a live peer's estimate), and the faults
  table says where each went. A node that dies by itself (Ray reports its actor dead) is
  treated the same way; a lost node that held the world or the recorder breaks the run.
  ``partition-nodes A B --down-s S`` cuts two nodes apart (iptables in their namespaces) and
  heals them S seconds later.
* **ownership**: the host actors end with the driver (Ray ends a driver's actors when it
  disconnects; each host also ends itself when the driver has not asked for news for
  :data:`LEASE_S`), and every process a host started ends with its host (the lifeline).
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from swarm.cluster.host import NodeHost
from swarm.cluster.local import RAY_ENV, LocalRayCluster
from swarm.cluster.versions import ClusterError, make_probe, mismatch
from swarm.supervise.launch import LocalSwarm
from swarmcore.scenario import Scenario
from swarmrt.bus.messages import Fault, opt
from swarmrt.bus.session import BusConfig
from swarmrt.protocol import BUS_LEASE_S, EXIT_AGENT_LOST

__all__ = ["RaySwarm", "RemoteProc", "parse_cluster", "cluster_shape", "LEASE_S"]

#: A host ends itself (and every process it started) when the driver has not asked it for
#: news this long (the driver asks every second): the driver is gone or cut off.
LEASE_S = 20.0
_CALL_TIMEOUT_S = 120.0


def parse_cluster(spec: str) -> tuple[str, int | None]:
    """``ray://HOST:PORT`` → (address, None); ``local-ray`` or ``local-ray:N`` → ("local-ray", N
    nodes, default 1). Raises ValueError naming what is wrong."""
    if spec.startswith("ray://"):
        rest = spec.removeprefix("ray://")
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ValueError(f"--cluster {spec}: expected ray://HOST:PORT (the Ray Client address of the head, port 10001 by default)")
        return spec, None
    if spec == "local-ray" or spec.startswith("local-ray:"):
        n = spec.partition(":")[2] or "1"
        if not n.isdigit() or not 1 <= int(n) <= 16:
            raise ValueError(f"--cluster {spec}: local-ray:N with N nodes, 1 to 16")
        return "local-ray", int(n)
    raise ValueError(f"--cluster {spec}: expected ray://HOST:PORT or local-ray[:N]")


def cluster_tls(nodes: int) -> bool:
    """Whether a secure cluster run of ``nodes`` nodes links its routers, and every process
    to its node's router, over TLS: when it spans hosts (two nodes or more; a namespaced
    local node counts as a host). ``SWARM_CLUSTER_TLS=off`` (or ``on``) overrides it, to
    measure what TLS costs."""
    force = os.environ.get("SWARM_CLUSTER_TLS", "auto")
    return force == "on" or (force != "off" and nodes > 1)


def cluster_shape(spec: str) -> tuple[int, bool]:
    """(How many nodes a run with ``--cluster spec`` gets, whether two of them can be cut
    apart): ``local-ray:N`` → N nodes, partitions when namespaced (root); ``ray://HOST:PORT``
    → the live nodes the cluster has now (asked through Ray Client), no partitions (real
    hosts). What ``swarm chaos --cluster`` draws node faults for."""
    address, n = parse_cluster(spec)
    if address == "local-ray":
        from swarm.cluster.netns import NetnsError, can_make_hosts

        why = can_make_hosts()
        if why is not None and (n or 1) > 1:
            raise NetnsError(f"--cluster {spec}: {why}")
        return n or 1, why is None and (n or 1) > 1
    os.environ.update({k: v for k, v in RAY_ENV.items() if k == "RAY_USAGE_STATS_ENABLED"})
    import ray

    try:
        ray.init(address, log_to_driver=False)
    except (ConnectionError, TimeoutError) as exc:
        raise ClusterError(f"cannot connect to the Ray cluster at {address}: {str(exc).splitlines()[0][:300]}") from None
    try:
        return sum(1 for nd in ray.nodes() if nd["Alive"]), False
    finally:
        ray.shutdown()


class RemoteProc:
    """A process on a node, seen as a ``subprocess.Popen`` (what the supervisor uses of one)."""

    def __init__(self, host: HostProxy, name: str, pid: int):
        self.host = host
        self.name = name
        self.pid = pid
        self.returncode: int | None = None

    def __repr__(self) -> str:
        return f"RemoteProc({self.name}, pid {self.pid} on node {self.host.index})"

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        with self.host.cond:
            if not self.host.cond.wait_for(lambda: self.returncode is not None, timeout):
                raise subprocess.TimeoutExpired(f"{self.name} (pid {self.pid}, node {self.host.index})", timeout or 0.0)
        assert self.returncode is not None
        return self.returncode

    def _signal(self, sig: int, group: bool) -> None:
        if self.returncode is None and self.host.dead is None:
            with contextlib.suppress(Exception):  # a node going away as we signal it
                self.host.call("signal", self.name, self.pid, int(sig), group, timeout=30.0)

    def send_signal(self, sig: int) -> None:
        self._signal(sig, False)

    def terminate(self) -> None:
        self._signal(signal.SIGTERM, False)

    def kill(self) -> None:
        self._signal(signal.SIGKILL, False)

    def killpg(self, sig: int) -> None:
        self._signal(sig, True)


class HostProxy:
    """The driver's side of one node's :class:`NodeHost`: its actor, its processes, and a
    thread that hands their exits to them (and notices the node's death)."""

    def __init__(self, actor, index: int, node_id: str, ip: str, on_lost):
        self.actor = actor
        self.index = index
        self.node_id = node_id
        self.ip = ip
        self.cond = threading.Condition()
        self.procs: dict[int, RemoteProc] = {}
        self.dead: str | None = None
        self.info: dict[str, Any] = {}
        self.setup: dict[str, Any] = {}
        self._on_lost = on_lost
        self._closing = False
        self._thread: threading.Thread | None = None

    def call(self, method: str, *args, timeout: float = _CALL_TIMEOUT_S):
        import ray

        return ray.get(getattr(self.actor, method).remote(*args), timeout=timeout)

    def track(self, name: str, pid: int) -> RemoteProc:
        p = RemoteProc(self, name, pid)
        with self.cond:
            self.procs[pid] = p
        return p

    def watch(self) -> None:
        self._thread = threading.Thread(target=self._watch, name=f"node-{self.index}", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        import ray
        from ray.exceptions import ActorUnavailableError, GetTimeoutError, RayActorError

        cursor = 0
        while not self._closing and self.dead is None:
            try:
                evs, cursor = ray.get(self.actor.events.remote(cursor, 1.0), timeout=30.0)
            except (GetTimeoutError, ActorUnavailableError):
                continue  # slow or out of reach for now (a partition): ask again
            except RayActorError as exc:
                if not self._closing:
                    self.lost(f"Ray reports its host actor dead ({type(exc).__name__})")
                return
            except Exception as exc:  # the client's connection gone: the run is ending
                if not self._closing:
                    self.lost(f"{type(exc).__name__}: {str(exc)[:200]}")
                return
            with self.cond:
                for _name, pid, code in evs:
                    if (p := self.procs.get(pid)) is not None and p.returncode is None:
                        p.returncode = code
                self.cond.notify_all()

    def lost(self, reason: str) -> None:
        """The node is gone: every process of it is gone with it (SIGKILL)."""
        with self.cond:
            if self.dead is not None:
                return
            self.dead = reason
            for p in self.procs.values():
                if p.returncode is None:
                    p.returncode = -signal.SIGKILL
            self.cond.notify_all()
        self._on_lost(self, reason)

    def close(self) -> None:
        self._closing = True


class RaySwarm(LocalSwarm):
    """A run over a Ray cluster (see the module docstring): ``cluster`` is ``ray://HOST:PORT``
    or ``local-ray`` (then ``nodes`` namespaced nodes are started here for the run)."""

    def __init__(self, sc: Scenario, out: Path, cluster: str, nodes: int | None = None, run_id: str | None = None, log=print,
                 local_cluster: LocalRayCluster | None = None):
        super().__init__(sc, out, run_id=run_id, log=log)
        self.address, n_local = parse_cluster(cluster)
        self.n_local = nodes or n_local or 1
        self.local = local_cluster  # a cluster the caller made and keeps (tests, benchmarks)
        self._own_local = False
        self.hosts: list[HostProxy] = []
        self.place: dict[str, int] = {}  # process name → node index
        self._lost: list[tuple[int, str]] = []  # nodes lost and not yet handled (index, why)
        self._handled: set[int] = set()
        self._partitions: list[tuple[float, int, int, Fault, float]] = []  # (heal at, a, b, command, cut at)
        self._head_keys = None  # the head host actor (it keeps the run's keys)
        self.startup_s: dict[str, float] = {}
        self.on_routers: Any = None  # called with the routers' endpoints once they are up (benchmarks: byte counters)
        self.tls = False  # the routers' links (the mesh, every process's) over TLS: security on, two nodes or more
        self.listens: list[list[str]] = []  # each router's endpoints (its TLS or TCP one; without the gate over TLS, a loopback TCP one)
        self.gate_plan: list[dict[str, Any]] | None = None  # each node's ingress gate (its entries; None: off)
        self.local_endpoints: list[str] = []
        self._tokens: set[int] = set()  # the agents whose liveliness token the supervisor holds live (its hold applied)
        self._moved: dict[int, tuple[int, int, int]] = {}  # satellite → (step, dead node, new node) of a move not yet seen flying
        self._moved_lost: str | None = None  # a moved agent the world went on without

    # -- the cluster ---------------------------------------------------------------------
    def _connect(self) -> None:
        os.environ.update({k: v for k, v in RAY_ENV.items() if k == "RAY_USAGE_STATS_ENABLED"})
        import ray

        t0 = time.monotonic()
        if self.address == "local-ray":
            if self.local is None:
                self.local = LocalRayCluster(self.n_local, log=self.say)
                self._own_local = True
                self.local.start()
            address = self.local.address
        else:
            address = self.address
        self.startup_s["cluster"] = time.monotonic() - t0
        for attempt in range(3):
            try:
                ray.init(address, namespace=f"swarm-{self.run}", log_to_driver=False)
                break
            except (ConnectionError, TimeoutError) as exc:
                # Ray Client's server starts a process per driver, within its own 30 s: a loaded
                # machine misses that now and then (seen at load 30 on 2 cores). Again.
                self.say(f"Ray Client at {address}: {str(exc).splitlines()[0][:200]} (attempt {attempt + 1} of 3)")
                self._check_interrupted()
                if attempt == 2:
                    raise ClusterError(f"cannot connect to the Ray cluster at {address}: {str(exc).splitlines()[0][:300]}") from None
        self.startup_s["connect"] = time.monotonic() - t0

    def _nodes(self) -> list[dict]:
        """The cluster's live nodes, the head first, then by address; checked against this
        driver (versions) and, on a local cluster, against the addresses it was given."""
        import ray
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        want = len(self.local.live_ips) if self.local is not None else 1
        deadline = time.monotonic() + 120.0
        while True:
            nodes = [n for n in ray.nodes() if n["Alive"]]
            if len(nodes) >= want or time.monotonic() > deadline:
                break
            threading.Event().wait(0.5)  # Ray has no "nodes changed" wait; a bounded poll
        if len(nodes) < want:
            raise ClusterError(f"the local Ray cluster has {len(nodes)} live nodes of {want}")

        def key(n: dict):
            head = "node:__internal_head__" in n.get("Resources", {})
            try:
                ip: Any = ipaddress.ip_address(n["NodeManagerAddress"])
            except ValueError:
                ip = n["NodeManagerAddress"]
            return (not head, str(type(ip)), ip)

        nodes.sort(key=key)
        if self.local is not None and self.local.namespaces:
            got = sorted(n["NodeManagerAddress"] for n in nodes)
            if got != sorted(self.local.live_ips):
                raise ClusterError(f"the local nodes advertise {got}, not their namespaces' addresses {sorted(self.local.live_ips)}: "
                                   "refusing to run (traffic would leave the namespaces)")
        probe = ray.remote(make_probe())
        refs = [probe.options(num_cpus=0, scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote()
                for n in nodes]
        facts = ray.get(refs, timeout=_CALL_TIMEOUT_S)
        from swarm.cluster.host import node_facts

        mine = node_facts()
        for i, (n, f) in enumerate(zip(nodes, facts, strict=True)):
            if (why := mismatch(f"{i} ({n['NodeManagerAddress']})", f, mine)) is not None:
                raise ClusterError(why)
            n["facts"] = f
        return nodes

    def _node_of(self, name: str) -> int:
        pl = self.sc.emulator.placement
        n = len(self.hosts)
        if name.startswith("agent-"):
            i = int(name.removeprefix("agent-"))
            idx = i % n if pl.agents == "spread" else pl.agents[i]
        else:
            idx = {"world": pl.world, "selector": pl.selector, "recorder": pl.recorder}[name]
        if not 0 <= idx < n:
            raise ClusterError(f"emulator.placement puts {name} on node {idx}; the cluster has {n} nodes (0..{n - 1})")
        return idx

    def _shares(self, n_nodes: int) -> list[list[str]]:
        """Which credential files each node gets (the driver's first): see the module docstring."""
        roles = {i: [r for r in ("world", "selector", "recorder") if self.place.get(r) == i] for i in range(n_nodes)}
        tls = ["ca.pem"] if self.tls else []
        driver_cert = ["driver.pem", "driver.key"] if self.tls else []  # mutual TLS: the driver's client certificate
        shares: list[list[str]] = [["supervisor.json", "cli.json", "observer.json", *tls, *driver_cert]]
        for i in range(n_nodes):
            files = ["router.json", "mesh.json", "passwords" if i == 0 else "passwords:agents", *tls,
                     *([f"router-tls:{i}"] if self.tls else [])]
            files += [f"{r}.json" for r in roles[i]]
            if "world" in roles[i]:
                files.append("agents.json")
            files += [f"{name}.json" for name, j in self.place.items() if j == i and name.startswith("agent-")]
            shares.append(files)
        return shares

    # -- start ------------------------------------------------------------------------------
    def start(self) -> None:
        import ray
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        t0 = time.monotonic()
        self._connect()
        self._check_interrupted()
        nodes = self._nodes()
        self._check_interrupted()
        actor = ray.remote(NodeHost)
        for i, n in enumerate(nodes):
            a = actor.options(num_cpus=0, max_concurrency=64, name=f"host-{self.run}-{i}",
                              scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(
                self.run, i, n["NodeManagerAddress"], None, LEASE_S)
            self.hosts.append(HostProxy(a, i, n["NodeID"], n["NodeManagerAddress"], self._on_lost))
        for h in self.hosts:
            h.info = h.call("info")
        self.startup_s["hosts"] = time.monotonic() - t0
        N = len(self.hosts)
        for name in ["world", "recorder", *(["selector"] if self.sc.selection.strategy != "none" else []),
                     *(f"agent-{i}" for i in range(self.sc.n_sats))]:
            self.place[name] = self._node_of(name)
        self.router_names = ["router" if i == 0 else f"router-{i}" for i in range(N)]
        self.n_routers = N
        # The run folder, as the nodes see it: the same one when they share this file system.
        marker = secrets.token_hex(8)
        (self.out / ".cluster-marker").write_text(marker)
        scenario_yaml = self.scenario_file.read_text()
        head = self.hosts[0]
        self.tls = self.sc.emulator.security and cluster_tls(N)
        shares = self._shares(N)
        if self.sc.emulator.security:
            router_hosts = [[h.ip, *([h.info["hostname"]] if h.info.get("hostname") else [])] for h in self.hosts] if self.tls else None
            refs = head.actor.make_keys.options(num_returns=len(shares)).remote(self.sc.n_sats, shares, router_hosts)
            self.keys_dir = Path(tempfile.mkdtemp(prefix=f"swarm-keys-{self.run}-"))
            for name, text in ray.get(refs[0], timeout=_CALL_TIMEOUT_S).items():
                fd = os.open(self.keys_dir / name, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                with os.fdopen(fd, "w") as f:
                    f.write(text)
            node_keys: list[Any] = list(refs[1:])  # Ray objects: resolved on each node, never fetched here
        else:
            self.say("[bold red]SECURITY OFF[/bold red] (emulator.security: off): no credentials, no access rules; "
                     "anyone who reaches a node's router can publish anything on this run's bus")
            node_keys = [None] * N
        setups = [h.actor.setup.remote(scenario_yaml, str(self.out), marker, k) for h, k in zip(self.hosts, node_keys, strict=True)]
        for h, s in zip(self.hosts, ray.get(setups, timeout=600.0), strict=True):
            h.setup = s
        ports = ray.get([h.actor.free_port.remote() for h in self.hosts], timeout=_CALL_TIMEOUT_S)
        scheme = "tls" if self.tls else "tcp"
        self.endpoints = [f"{scheme}/{h.ip}:{p}" for h, p in zip(self.hosts, ports, strict=True)]
        self.endpoint = self.endpoints[0]
        self.listens = [[e] for e in self.endpoints]
        # Each node's ingress gate (issue 35): the node's processes reach its router through
        # it, each identity at its own port of the host's loopback, rate-limited; the router's
        # host address is for the mesh and the driver (mutual TLS across hosts).
        from dataclasses import asdict

        from swarm.supervise.gate import plan_entries

        entries = plan_entries(self.sc)
        self.gate_plan = [asdict(e) for e in entries] if entries is not None else None
        if self.tls and self.gate_plan is None:
            # No gate: the routers' TLS listeners take only the mesh and the driver (mutual TLS:
            # a client certificate no role or agent holds), so each router also listens on its
            # host's loopback, which no other host reaches, for the node's own processes.
            lports = ray.get([h.actor.free_port.remote("127.0.0.1") for h in self.hosts], timeout=_CALL_TIMEOUT_S)
            self.local_endpoints = [f"tcp/127.0.0.1:{p}" for p in lports]
            for ls, e in zip(self.listens, self.local_endpoints, strict=True):
                ls.append(e)
        # Every router at once, each dialling all the others (a router retries until its peer
        # listens): one after the other cost N router start-ups (~14 s each at load 30).
        starts = [h.actor.start_router.remote(self.router_names[i], self.listens[i],
                                              [e for j, e in enumerate(self.endpoints) if j != i], i, 120.0, self.gate_plan)
                  for i, h in enumerate(self.hosts)]
        for h, pid in zip(self.hosts, ray.get(starts, timeout=300.0), strict=True):
            h.call("set_endpoints", [self.endpoints[h.index]], self.local_endpoints[h.index:h.index + 1])
            self._track(self.router_names[h.index], h.track(self.router_names[h.index], pid))
        self.startup_s["routers"] = time.monotonic() - t0
        if self.on_routers is not None:
            self.on_routers(list(self.endpoints))
        for h in self.hosts:
            h.watch()
        self.bus = BusConfig(mode="client", connect=[self.endpoints[0]],
                             credential_file=str(self.keys_dir / "supervisor.json") if self.keys_dir is not None else None)
        self.node = self._open_node()
        self._spawn_role("recorder", ["--flush-every-s", str(self.sc.emulator.flush_every_s)])
        self._wait_alive("recorder", 60.0)
        self._check_interrupted()
        by_node: dict[int, list[int]] = {}
        for i in range(self.sc.n_sats):
            by_node.setdefault(self.place[f"agent-{i}"], []).append(i)
        spawned = ray.get([self.hosts[j].actor.spawn_agents.remote([(i, False, self.sc.emulator.agent_commands.get(i))
                                                                    for i in sats], self.sc.emulator.agent_start)
                           for j, sats in by_node.items()], timeout=max(600.0, self.sc.emulator.startup_timeout_s))
        for (j, sats), pids in zip(by_node.items(), spawned, strict=True):
            for i, pid in zip(sats, pids, strict=True):
                self._track(f"agent-{i}", self.hosts[j].track(f"agent-{i}", pid))
        if self.sc.selection.strategy != "none":
            self.spawn_selector()
        self._spawn_role("world", [])
        self._write_run_json()
        self.startup_s["spawned"] = time.monotonic() - t0
        self._check_interrupted()

    def _track(self, name: str, p: RemoteProc) -> None:
        with self._lock:
            self.procs[name] = p
            self._started_at[name] = time.monotonic()

    def _spawn_role(self, name: str, extra: list[str]) -> RemoteProc:
        h = self.hosts[self.place[name]]
        pid = h.call("spawn_role", name, name, extra)
        p = h.track(name, pid)
        self._track(name, p)
        return p

    def spawn_selector(self) -> None:
        self._spawn_role("selector", [])

    def spawn_live(self) -> None:
        raise ClusterError("--live is not available with --cluster yet (the live view would run on the head; see docs/cluster.md)")

    def spawn_agent(self, i: int, restart: bool = False) -> None:
        """Satellite i's agent on its node (a restart: the same node while it lives, else the
        surviving node with the fewest agents)."""
        import ray

        name = f"agent-{i}"
        j = self.place[name]
        if self.hosts[j].dead is not None:
            j = self._least_loaded()
            if self.keys_dir is not None:
                share = self._head().actor.key_share.remote([f"{name}.json"])
                ray.get(self.hosts[j].actor.add_keys.remote(share), timeout=_CALL_TIMEOUT_S)
            self.place[name] = j
        h = self.hosts[j]
        pid = h.call("spawn_agent", i, restart, self.sc.emulator.agent_commands.get(i), self.sc.emulator.agent_start)
        self._track(name, h.track(name, pid))

    def _head(self) -> HostProxy:
        return self.hosts[0]

    def _least_loaded(self) -> int:
        alive = [h.index for h in self.hosts if h.dead is None]
        if not alive:
            raise ClusterError("no node of the cluster is left")
        load = {j: sum(1 for n, k in self.place.items() if k == j and n.startswith("agent-")) for j in alive}
        return min(alive, key=lambda j: (load[j], j))

    def _start_router(self, i: int, timeout: float) -> None:
        """Router i on node i, listening on its endpoint, dialling every other running router."""
        name = self.router_names[i]
        running = [e for j, e in enumerate(self.endpoints) if j != i and (q := self.procs.get(self.router_names[j])) is not None
                   and q.poll() is None]
        h = self.hosts[i]
        pid = h.call("start_router", name, self.listens[i], running, i, timeout, self.gate_plan)
        h.call("set_endpoints", [self.endpoints[i]], self.local_endpoints[i:i + 1])
        p = h.track(name, pid)
        self._track(name, p)

    def _write_run_json(self) -> None:
        info = {
            "run": self.run,
            "supervisor_pid": os.getpid(),
            "cluster": self.address if self.address != "local-ray" else (self.local.address if self.local else "local-ray"),
            "endpoint": self.endpoint,
            "endpoints": [self.endpoint],  # the driver's and swarm fault's way in: the head's router
            "routers": self.endpoints,
            "tls": self.tls,
            "n_sats": self.sc.n_sats,
            "pids": {k: p.pid for k, p in self.procs.items()},
            "process_nodes": {k: p.host.index for k, p in self.procs.items() if isinstance(p, RemoteProc)},
            "nodes": [{"index": h.index, "ip": h.ip, "hostname": h.info.get("hostname"), "node_id": h.node_id,
                       "alive": h.dead is None} for h in self.hosts],
            "placement": dict(self.place),
            "scenario": str(self.scenario_file),
            "recording": str(self.out / "run.mcap"),
            "security": "on" if self.keys_dir is not None else "off",
            "keys": str(self.keys_dir) if self.keys_dir is not None else None,
            "startup_s": self.startup_s,
        }
        (self.out / "run.json").write_text(json.dumps(info, indent=2) + "\n")

    # -- faults -------------------------------------------------------------------------------
    def _handle(self, ev) -> None:
        if ev.kind == "alive" and ev.role == "agent" and ev.sat is not None:
            (self._tokens.add if ev.alive else self._tokens.discard)(int(ev.sat))
        if ev.kind == "clock" and self._moved:
            # The world puts a step's clock past a node's death only once its moved agents are
            # back, or once it gave up on them (startup_timeout_s): a clock after it without
            # one of them means the run would finish with that agent gone.
            live = {int(i) for i in ev.msg.live_agents}
            for sat, (k, i, j) in list(self._moved.items()):
                if ev.msg.k > k and sat in live:
                    del self._moved[sat]
                elif ev.msg.k > k and self._moved_lost is None:
                    self._moved_lost = (f"agent {sat}, moved from node {i} (lost at step {k}) to node {j}, is not flying at step "
                                        f"{ev.msg.k}: the world went on without it")
        super()._handle(ev)

    def agent_gone(self) -> str | None:
        self._handle_lost()
        if self._moved_lost is not None:
            return self._moved_lost
        return super().agent_gone()

    def run_to_end(self, progress=None, timeout: float | None = None) -> int | None:
        code = super().run_to_end(progress=progress, timeout=timeout)
        if code == 0 and self.broken is None and self._moved_lost is not None:  # seen with the last clock
            self.broken, self.broken_code = self._moved_lost, EXIT_AGENT_LOST
            self.say(f"[bold red]the run is broken[/bold red]: {self._moved_lost}")
            return None
        return code

    def _wait_tokens_gone(self, sats: list[int], timeout: float) -> list[int]:
        """Wait until the supervisor has counted the tokens of agents ``sats`` gone (each
        held ``liveliness_hold_s`` after it vanished, as the world holds it), at most
        ``timeout`` s; the ones still live then. The world hears the same undeclarations
        from the same router: once they are gone here they are (nearly) gone there, and its
        agents' replacements are started only after, so that the world's wait for them
        (``kill-node`` holds the step until every agent that was alive is back) waits for
        the new processes, not for the dying tokens of the old ones. Found by
        ``swarm chaos --cluster local-ray:3`` (seed 21): the world took the old tokens, not
        yet held out, for the agents being back, put the step's clock, and flew to the end
        without the two moved agents, exit 0."""
        left = lambda: [i for i in sats if i in self._tokens]  # noqa: E731
        if left():
            self._node().wait_for(lambda: not left() or self.interrupted is not None, timeout, self._handle,
                                  wake=lambda: time.monotonic() + 0.2)
        return left()

    def _on_lost(self, host: HostProxy, reason: str) -> None:
        with self._lock:
            self._lost.append((host.index, reason))

    def _handle_lost(self, fault: Fault | None = None) -> list[str]:
        """Nodes lost since the last call: their processes count as ended by a fault, their
        agents are started on the surviving nodes; a lost node with the world or the
        recorder breaks the run. Returns one line per moved agent."""
        with self._lock:
            lost = [(i, r) for i, r in self._lost if i not in self._handled]
            self._lost = []
        moves: list[str] = []
        for i, reason in lost:
            self._handled.add(i)
            h = self.hosts[i]
            for p in list(h.procs.values()):
                self._faulted.add(p.pid)
            vital = [r for r in ("world", "recorder") if self.place.get(r) == i]
            if vital and not self.world_done:
                self.broken = f"node {i} ({h.ip}) was lost ({reason}) with the {' and the '.join(vital)}"
                self.say(f"[bold red]the run is broken[/bold red]: {self.broken}")
                continue
            if self.world_done:
                continue
            names = sorted((n for n, j in self.place.items() if j == i and n.startswith("agent-")),
                           key=lambda n: int(n.removeprefix("agent-")))
            # Its agents' tokens go with its router's links (at once when the kernel closes
            # them; at the Zenoh lease, 10 s, when the host vanished): their replacements wait.
            em = self.sc.emulator
            still = self._wait_tokens_gone([int(n.removeprefix("agent-")) for n in names],
                                           BUS_LEASE_S + em.bus_grace_s + em.liveliness_hold_s + 5.0)
            if still:
                self.say(f"node {i}: the tokens of agents {still} are still live {BUS_LEASE_S:g} s after its death; "
                         "starting their replacements anyway")
            for name in names:
                sat = int(name.removeprefix("agent-"))
                try:
                    self.spawn_agent(sat, restart=True)
                except Exception as exc:  # said, and the run goes on without it
                    moves.append(f"agent {sat}: not restarted ({exc})")
                    continue
                j = self.place[name]
                if fault is not None and fault.sender == "world":
                    # Scheduled: the world waits at this step for every agent that was alive
                    # (by hand or lost by itself, it goes on and they rejoin a few steps later).
                    self._moved[sat] = (max(self.k, fault.k), i, j)
                moves.append(f"agent {sat} → node {j} ({self.hosts[j].ip}), pid {self.procs[name].pid}")
            if self.selector_on(i):
                self.spawn_selector()  # placement.selector is dead: the least loaded node
                moves.append(f"selector → node {self.place['selector']}")
            self._write_run_json()
            f = fault or Fault(run=self.run, sender="supervisor", k=self.k, t_s=self.k * self.sc.dt_s, phase="command",
                               action="kill-node", target=i, detail="lost")
            for line in moves:
                self._report(f, "done", f"node {i}: {line}")
            self._report(f, "done", f"node {i} ({h.ip}) {'killed' if fault is not None else 'lost: ' + reason}; "
                         f"{len(moves)} agent(s) restarted on the surviving nodes")
        return moves

    def selector_on(self, i: int) -> bool:
        if self.place.get("selector") != i:
            return False
        self.place["selector"] = self._least_loaded()
        return True

    def _cluster_fault(self, f: Fault) -> None:
        i = int(opt(f, "target") or 0)
        if not 0 <= i < len(self.hosts):
            self._report(f, "failed", f"no node {i} (the cluster has {len(self.hosts)}: 0..{len(self.hosts) - 1})")
            return
        h = self.hosts[i]
        if h.dead is not None:
            self._report(f, "failed", f"node {i} is already gone ({h.dead})")
            return
        if f.action == "kill-node":
            if self.local is not None and self.local.namespaces:
                pids = self.local.kill(i)
                how = f"every process of its namespace SIGKILLed ({len(pids)}, the raylet among them)"
            else:
                try:
                    how = json.loads(h.call("die", timeout=30.0))["detail"]
                except Exception as exc:  # the node went with the call
                    how = f"its host killed itself ({type(exc).__name__})"
            self.say(f"step {self.k}: node {i} ({h.ip}) killed: {how}")
            h.lost(f"killed by the fault kill-node: {how}")
            self._handle_lost(fault=f)
            return
        # partition-nodes
        j = int(opt(f, "peer") if f.HasField("peer") else -1)
        down_s = float(opt(f, "down_s") or 0.0)
        if not 0 <= j < len(self.hosts) or j == i:
            self._report(f, "failed", f"partition-nodes: peer node {j} is not another node of the cluster")
            return
        if self.local is None or not self.local.namespaces:
            self._report(f, "failed", "partition-nodes needs a local namespaced cluster (--cluster local-ray as root)")
            return
        self.local.partition(i, j)
        self._partitions.append((time.monotonic() + down_s, i, j, f, time.time()))
        self.say(f"step {self.k}: nodes {i} and {j} cut apart for {down_s:g} s")
        self._report(f, "done", f"nodes {i} ({h.ip}) and {j} ({self.hosts[j].ip}) cut apart (iptables DROP both ways) for {down_s:g} s")

    def continue_stalled(self, everyone: bool = False, process=None) -> None:
        super().continue_stalled(everyone=everyone, process=process)
        now = time.monotonic()
        due = [x for x in self._partitions if everyone or x[0] <= now]
        if not due:
            return
        self._partitions = [x for x in self._partitions if x not in due]
        for _t, a, b, f, t_cut in due:
            if self.local is not None:
                self.local.heal(a, b)
            with contextlib.suppress(Exception):
                self._report(f, "done", f"nodes {a} and {b} healed after {time.time() - t_cut:.2f} s")

    def _stall_net(self, p, down_s: float):
        h: HostProxy = p.host
        pid = h.call("stall_net", p.pid, down_s)
        return h.track(f"stall-net-{p.pid}", pid)

    # -- the end --------------------------------------------------------------------------------
    def kill_all(self) -> None:
        if self.local is not None:
            self.local.close()
            return
        for h in self.hosts:
            if h.dead is None:
                with contextlib.suppress(Exception):
                    h.actor.shutdown.remote(0.0)

    def _terminate(self, names: list[str], grace: float) -> None:
        """As LocalSwarm's, one call per node, the nodes in parallel."""
        import ray

        by_host: dict[int, list[str]] = {}
        for n in names:
            p = self.procs.get(n)
            if isinstance(p, RemoteProc) and p.returncode is None and p.host.dead is None:
                by_host.setdefault(p.host.index, []).append(n)
        refs = {j: self.hosts[j].actor.terminate.remote(ns, grace) for j, ns in by_host.items()}
        for ref in refs.values():
            with contextlib.suppress(Exception):
                ray.get(ref, timeout=grace + 60.0)
        for n in names:  # their exits come through the watcher; wait for it a little
            p = self.procs.get(n)
            if isinstance(p, RemoteProc) and p.host.dead is None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=5.0)

    def stop(self) -> None:
        try:
            if self.hosts:
                super().stop()
        finally:
            self._stop_cluster()

    def _stop_cluster(self) -> None:
        import ray

        if ray.is_initialized():
            self._collect()
            live = [h for h in self.hosts if h.dead is None]
            refs = [h.actor.shutdown.remote(5.0) for h in live]
            left: dict[str, list] = {}
            for h, ref in zip(live, refs, strict=True):
                try:
                    if got := ray.get(ref, timeout=60.0):
                        left[str(h.index)] = got
                except Exception as exc:  # a host that cannot say is a finding too
                    left[str(h.index)] = [["(its host did not answer)", f"{type(exc).__name__}"]]
            self._note_left(left)
            for h in self.hosts:
                h.close()
            with contextlib.suppress(Exception):
                ray.shutdown()
        for h in self.hosts:
            self._salvage(h)
        if self._own_local and self.local is not None:
            self.local.close()
        if self.keys_dir is not None:
            shutil.rmtree(self.keys_dir, ignore_errors=True)
        with contextlib.suppress(OSError):
            (self.out / ".cluster-marker").unlink()

    def _note_left(self, left: dict[str, list]) -> None:
        """What each live host said was still running after its shutdown (nothing, normally),
        into run.json (``left_on_nodes``: a chaos campaign's invariant a on other hosts)."""
        with contextlib.suppress(OSError, ValueError):
            info = json.loads((self.out / "run.json").read_text())
            info["left_on_nodes"] = left
            (self.out / "run.json").write_text(json.dumps(info, indent=2) + "\n")

    def _collect(self) -> None:
        """The nodes' logs into OUT/logs, and the recording when its node does not share
        OUT (fetched in pieces)."""
        import ray

        logs = self.out / "logs"
        for h in self.hosts:
            if h.dead is not None:
                continue
            with contextlib.suppress(Exception):
                for name, data in ray.get(h.actor.logs.remote(), timeout=_CALL_TIMEOUT_S).items():
                    (logs / name).write_bytes(data)
        rec = self.hosts[self.place.get("recorder", 0)] if self.hosts else None
        if rec is not None and rec.dead is None and not rec.setup.get("shared", False):
            size = ray.get(rec.actor.file_size.remote("run.mcap"), timeout=_CALL_TIMEOUT_S)
            with open(self.out / "run.mcap", "wb") as f:
                off = 0
                while off < size:
                    chunk = ray.get(rec.actor.read_chunk.remote("run.mcap", off), timeout=_CALL_TIMEOUT_S)
                    if not chunk:
                        break
                    f.write(chunk)
                    off += len(chunk)

    def _salvage(self, h: HostProxy) -> None:
        """A node killed on this machine (a local cluster) left its folder: its logs into
        OUT/logs, then the folder (its credentials) deleted."""
        d = h.info.get("dir")
        if h.dead is None or not d or h.info.get("hostname") != socket.gethostname() or not Path(d).is_dir():
            return
        for p in [*(Path(d) / "logs").glob("*.log"), *(Path(d) / "logs").glob("gate-*.json")]:
            with contextlib.suppress(OSError):  # agent-2.log of the lost node 2: agent-2.node2.log
                shutil.copyfile(p, self.out / "logs" / f"{p.stem}.node{h.index}{p.suffix}")
        shutil.rmtree(d, ignore_errors=True)
