"""A throw-away Ray cluster on this machine (``swarm run --cluster local-ray``, the tests,
``swarm bench cluster-run``): N nodes started with Ray's own ``ray start``, each in a
network namespace of its own (:mod:`swarm.cluster.netns`) with its own address, so that
nothing a node says can leave the machine and each node looks like a host to Ray and Zenoh.

Without root (no namespaces) it starts one node in this namespace, which Ray makes
advertise the machine's interface address (and listen on every interface): it says so.

Ownership: each ``ray start --block`` runs under :mod:`swarm.supervise.lifeline` (``--exec``),
so it ends when this process ends, whatever the signal; the namespaces' reaper then kills
whatever is left in them and deletes them; :meth:`LocalRayCluster.close` does all of it at
once on a normal end. Ray's session folder (a temporary folder of its own) goes too. Never
``ray stop``: it kills every Ray process of the machine, other users' too.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from swarm.cluster.netns import Hosts, NetnsError, can_make_hosts
from swarm.cluster.versions import ClusterError

__all__ = ["LocalRayCluster", "RAY_ENV"]

#: The environment of every Ray process this project starts or talks to: no usage report
#: (it would send one off the machine), no workers started before they are asked for
#: (each a Python interpreter; the run's actors are few), a driver gone for 5 s (not
#: Ray Client's 30 s) ends its actors, and a node silent for ~10 s is dead.
RAY_ENV = {
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_enable_worker_prestart": "0",
    "RAY_prestart_worker_first_driver": "0",
    "RAY_CLIENT_RECONNECT_GRACE_PERIOD": "5",
    "RAY_health_check_period_ms": "1000",
    "RAY_health_check_failure_threshold": "10",
}

_GCS_PORT = 6379
_CLIENT_PORT = 10001
_STARTED = b"Ray runtime started"


def _ray_bin() -> str:
    exe = Path(sys.executable).with_name("ray")
    if exe.exists():
        return str(exe)
    found = shutil.which("ray")
    if found is None:
        raise RuntimeError("the ray command is missing (pip install ray; it comes with the project's dependencies)")
    return found


class LocalRayCluster:
    """``n`` Ray nodes on this machine; :attr:`address` is the Ray Client address
    (``ray://IP:PORT``) a driver connects to."""

    def __init__(self, n: int = 3, cpus_per_node: int | None = None, namespaces: bool | None = None,
                 object_store_mb: int = 128, log=lambda s: None, start_timeout_s: float = 180.0):
        if n < 1:
            raise ValueError(f"a cluster of {n} nodes")
        self.n = n
        # Ray takes whole CPUs (ray start --num-cpus is an integer).
        self.cpus = int(cpus_per_node) if cpus_per_node is not None else max(1, round((os.cpu_count() or 2) / n))
        why = can_make_hosts()
        if namespaces is None:
            namespaces = why is None
        if namespaces and why is not None:
            raise NetnsError(why)
        self.namespaces = namespaces
        self.object_store_mb = object_store_mb
        self.say = log
        self.start_timeout_s = start_timeout_s
        self.hosts: Hosts | None = None
        self.tmp = Path(tempfile.mkdtemp(prefix="swr-", dir="/tmp"))  # short: Ray's socket paths must stay < 108 bytes
        self.node_ips: list[str] = []
        self.procs: list[subprocess.Popen | None] = []
        self.address = ""
        self._lifeline = os.pipe()
        os.set_inheritable(self._lifeline[1], False)
        self._closed = False
        self._client_port = _CLIENT_PORT
        self._gcs = ""
        self.down: set[int] = set()  # nodes killed by :meth:`kill` and not started again

    # -- start --------------------------------------------------------------------------
    def start(self) -> LocalRayCluster:
        try:
            if self.namespaces:
                self.hosts = Hosts(self.n).up()
                self.node_ips = [h.ip for h in self.hosts.hosts]
            else:
                if self.n > 1:
                    raise NetnsError(f"{self.n} nodes need network namespaces: {can_make_hosts()}")
                self.node_ips = [""]
            t0 = time.monotonic()
            self.procs = [None] * self.n
            self._start_node(0)
            head_ip = self.node_ips[0] or "127.0.0.1"
            self.address = f"ray://{head_ip}:{self.client_port}"
            # The other nodes join one after the other: on one machine they share the head's
            # session folder, and two raylets starting together picked the same socket name
            # (seen: "bind: Address already in use" in the plasma store, the node never registered).
            for i in range(1, self.n):
                self._start_node(i)
            self.say(f"local Ray cluster: {self.n} node(s) {', '.join(ip or 'this host' for ip in self.node_ips)} "
                     f"in {time.monotonic() - t0:.1f} s")
        except BaseException:
            self.close()
            raise
        return self

    @property
    def client_port(self) -> int:
        return self._client_port

    def _cmd(self, i: int) -> list[str]:
        ray = _ray_bin()
        common = ["--block", f"--num-cpus={self.cpus}", f"--object-store-memory={self.object_store_mb * 1024 * 1024}",
                  "--disable-usage-stats", "--include-log-monitor=false"]
        if i == 0:
            if self.namespaces:
                gcs, self._client_port = _GCS_PORT, _CLIENT_PORT
                ip = ["--node-ip-address", self.node_ips[0]]
            else:
                from swarm.supervise.launch import free_port

                gcs, self._client_port = free_port(), free_port()
                ip = []
            self._gcs = f"{self.node_ips[0] or '127.0.0.1'}:{gcs}"
            cmd = [ray, "start", "--head", f"--port={gcs}", f"--ray-client-server-port={self._client_port}",
                   "--include-dashboard=false", "--no-monitor", f"--temp-dir={self.tmp}", *ip, *common]
        else:
            cmd = [ray, "start", f"--address={self._gcs}", "--node-ip-address", self.node_ips[i], *common]
        if self.hosts is not None:
            cmd = self.hosts.hosts[i].cmd(*cmd)
        return cmd

    def _start_node(self, i: int, attempts: int = 3) -> None:
        """Start node i and wait (on its output) until Ray says it started; a node whose
        raylet did not register within Ray's fixed 30 s (a loaded machine) is tried again."""
        for attempt in range(attempts):
            log = self.tmp / f"node-{i}.log"
            cmd = self._cmd(i)
            # The tag goes to every process of the node (Ray's workers and what they start
            # inherit it): :meth:`processes` finds them by it.
            env = dict(os.environ, **RAY_ENV, SWARM_LOCAL_CLUSTER=self.tmp.name)
            p = subprocess.Popen([sys.executable, "-m", "swarm.supervise.lifeline", "--fd", str(self._lifeline[0]), "--grace-s", "10",
                                  "--exec", *cmd], env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, pass_fds=(self._lifeline[0],), start_new_session=True)
            self.procs[i] = p
            ok, over = threading.Event(), threading.Event()

            def pump(p: subprocess.Popen = p, log: Path = log, ok: threading.Event = ok, over: threading.Event = over) -> None:
                with open(log, "ab") as f:
                    assert p.stdout is not None
                    for line in p.stdout:
                        f.write(line)
                        f.flush()
                        if _STARTED in line:
                            ok.set()
                            over.set()
                over.set()  # EOF: the node is gone

            threading.Thread(target=pump, daemon=True).start()
            over.wait(self.start_timeout_s)
            if ok.is_set() and p.poll() is None:
                return
            _kill_group(p)
            if self.hosts is not None and i > 0:
                self.hosts.kill(i)
            tail = log.read_bytes()[-600:].decode(errors="replace") if log.exists() else ""
            last = (tail.strip().splitlines() or ["?"])[-1]
            self.say(f"Ray node {i} did not start (attempt {attempt + 1} of {attempts}): {last}")
        raise ClusterError(f"Ray node {i} did not start in {attempts} attempts (the last said: {last})")

    def processes(self) -> list:
        """Every process still running that belongs to this cluster (its environment carries
        the cluster's tag): none after :meth:`close`."""
        return tagged_processes("SWARM_LOCAL_CLUSTER", self.tmp.name)

    # -- faults -------------------------------------------------------------------------
    def kill(self, i: int) -> list[int]:
        """SIGKILL every process of node i (its raylet and everything on it)."""
        if self.hosts is None:
            raise NetnsError("kill-node on a one-node local cluster without namespaces")
        self.down.add(i)
        return self.hosts.kill(i)

    def restart(self, i: int) -> None:
        """Start node i again after :meth:`kill` (the host came back): a new raylet at the
        same address joins the head as a new Ray node."""
        if i == 0:
            raise ClusterError("the head node cannot be started again: its cluster is gone with it")
        if i not in self.down:
            raise ClusterError(f"node {i} is not down")
        old = self.procs[i]
        if old is not None:
            _kill_group(old)
        self._start_node(i)
        self.down.discard(i)

    @property
    def live_ips(self) -> list[str]:
        """The addresses of the nodes not killed."""
        return [ip for i, ip in enumerate(self.node_ips) if i not in self.down]

    def partition(self, a: int, b: int) -> None:
        if self.hosts is None:
            raise NetnsError("a partition needs namespaced nodes")
        self.hosts.partition(a, b)

    def heal(self, a: int, b: int) -> None:
        if self.hosts is not None:
            self.hosts.heal(a, b)

    # -- the end ------------------------------------------------------------------------
    def close(self) -> None:
        """Every node's processes killed, the namespaces deleted, Ray's folder removed."""
        if self._closed:
            return
        self._closed = True
        for p in self.procs:
            if p is not None:
                _kill_group(p)
        if self.hosts is not None:
            self.hosts.close()
        for p in self.procs:
            if p is not None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=10)
        for fd in self._lifeline:
            with contextlib.suppress(OSError):
                os.close(fd)
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> LocalRayCluster:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def _kill_group(p: subprocess.Popen) -> None:
    """SIGKILL a node's process and every descendant (``ray start`` makes a process group
    of its own, so its lifeline's group is not all of it)."""
    import psutil

    if p.poll() is None:
        with contextlib.suppress(psutil.Error):
            procs = [psutil.Process(p.pid)]
            procs += procs[0].children(recursive=True)
            for q in procs:
                with contextlib.suppress(psutil.Error):
                    q.send_signal(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=10)


def tagged_processes(key: str, value: str) -> list:
    """Running processes whose environment has ``key=value`` (zombies left out)."""
    import psutil

    out = []
    for p in psutil.process_iter():
        with contextlib.suppress(psutil.Error):
            if p.status() != psutil.STATUS_ZOMBIE and p.environ().get(key) == value:
                out.append(p)
    return out
