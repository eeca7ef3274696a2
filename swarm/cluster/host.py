"""What runs on each Ray node of a cluster run: :class:`NodeHost`, one Ray actor per node.

It is "start a role's process" on its node, what :class:`swarm.supervise.launch.LocalSwarm`
does on this machine: the node's Zenoh router, the roles placed there (world, selector,
recorder on the head) under :mod:`swarm.supervise.lifeline`, and the node's agents forked
from one fork server per node (:mod:`swarm.supervise.forkserver`: imports and compiled
kernels paid once per node and their pages shared), or a program of another language under
the lifeline's ``--exec`` (``--agent I=COMMAND``). The driver (``swarm run --cluster``,
:class:`swarm.cluster.swarm.RaySwarm`) sees each process through
:class:`swarm.cluster.swarm.RemoteProc`, a ``Popen`` look-alike fed by :meth:`NodeHost.events`.

Why one actor per node and not one per agent: a Ray actor is a Ray worker process of its
own, started cold by the raylet (no fork from a warm parent): measured here an idle actor
holds ~53 MB PSS (~99 MB RSS) before it imports numpy, scipy, numba and zenoh, and an
agent's imports and kernels come on top, unshared; a forked agent shares them with its
siblings. At 1,000 satellites that is the difference between fitting and not.

Ownership: the actor holds the write end of its children's lifeline pipe, so when the
actor's process ends — the run stopped, the driver gone (Ray kills a driver's actors), the
node killed — every process it started stops by itself within seconds (the forked agents
through the fork server's parent sentinel). :meth:`shutdown` stops them in order and
deletes the node's private directory (its credentials, its logs once collected).

Credentials: :meth:`make_keys` (on the head) makes the run's keys and hands out, as
separate Ray objects, each node's share: a worker node's router gets the password
dictionary of the agents and the mesh (never the world's, the recorder's or the CLI's),
each agent only its own file, on the node it runs on; with TLS (a cluster over several
hosts) each node's router its own certificate and key (the CA's key deleted once they are
signed, the routers' keys forgotten here once handed out).
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["NodeHost", "node_facts", "ROLE_MODULES"]

#: The Python module of each role (``python -m MODULE``).
ROLE_MODULES = {"world": "world_sim", "selector": "selector", "recorder": "swarm.record.recorder", "agent": "sat_agent"}

_ORPHAN_GRACE_S = 5.0
_ORPHAN_RECORDER_GRACE_S = 15.0


def node_facts() -> dict[str, Any]:
    """What a node runs (the driver checks every node against itself before a run):
    Python, Ray, numpy and the project's version, and a fingerprint of the project's code
    (same numbers need the same code). Imports nothing of the project at module level, so
    that a node without it still answers (:func:`swarm.cluster.versions.probe`)."""
    import platform

    facts: dict[str, Any] = {"python": platform.python_version(), "hostname": socket.gethostname(), "cpus": os.cpu_count()}
    try:
        import ray

        facts["ray"] = ray.__version__
    except ImportError:
        facts["ray"] = None
    from swarm.cluster.versions import code_fingerprint, project_version

    facts["project"] = project_version()
    facts["code"] = code_fingerprint()
    import numpy

    facts["numpy"] = numpy.__version__
    return facts


class NodeHost:
    """The run's processes on one node (a Ray actor; see the module docstring)."""

    def __init__(self, run: str, index: int, node_ip: str, python: str | None = None, lease_s: float | None = None):
        self.run = run
        self.lease_s = lease_s  # end everything when the driver has not called events() this long
        self._last_seen: float | None = None
        self.index = index
        self.ip = node_ip
        self.python = python or sys.executable
        self.dir = Path(tempfile.mkdtemp(prefix=f"swarm-node-{run}-{index}-"))
        os.chmod(self.dir, 0o700)
        (self.dir / "logs").mkdir()
        self.keys_dir: Path | None = None
        self.scenario_file = self.dir / "scenario.yaml"
        self.out: Path = self.dir / "out"  # the run folder here (the driver's own when the file system is shared)
        self.shared_out = False
        self.endpoints: list[str] = []  # how this node's processes reach its router
        self.local_endpoints: list[str] = []  # without the gate over TLS: its loopback TCP endpoint (set_endpoints)
        self.gate_endpoints: dict[str, str] = {}  # with the ingress gate: each identity's port on this host's loopback
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self.procs: dict[str, Any] = {}  # name → Popen | ForkedAgent (the current one)
        self._all: list[tuple[str, Any]] = []  # every process started here (name, handle), for exits
        self._exits: list[tuple[str, int, int]] = []  # (name, pid, status) in the order seen
        self._reported: set[int] = set()  # pids whose exit is in _exits
        self._lifeline = os.pipe()  # children hold the read end; the write end only this process
        self._forkserver: Any = None  # swarm.supervise.forkserver.AgentForkServer, on the first forked agent
        self._closed = False
        self._nets: list[subprocess.Popen] = []
        self._ports: Any = None  # swarm.supervise.gate.PortReservation of its router's gate, on the first router
        threading.Thread(target=self._reap, name="reap", daemon=True).start()

    # -- facts ------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        return {**node_facts(), "ip": self.ip, "pid": os.getpid(), "index": self.index, "dir": str(self.dir)}

    def ping(self) -> int:
        return self.index

    # -- set-up -----------------------------------------------------------------------
    def setup(self, scenario_yaml: str, out: str | None, marker: str | None, keys: dict[str, str] | None) -> dict[str, Any]:
        """The run's scenario, where to write the run's files (``out`` when this node
        sees the driver's folder: the marker file there has ``marker``; else a folder of its
        own) and this node's credentials."""
        self.scenario_file.write_text(scenario_yaml)
        if out is not None and marker is not None:
            with contextlib.suppress(OSError):
                if (Path(out) / ".cluster-marker").read_text() == marker:
                    self.out, self.shared_out = Path(out), True
        self.out.mkdir(parents=True, exist_ok=True)
        if keys:
            self.add_keys(keys)
        # (No separate warm-up of the compiled kernels as LocalSwarm runs: the node's fork
        # server compiles them, or loads them from numba's cache, once before its first agent.)
        return {"out": str(self.out), "shared": self.shared_out, "dir": str(self.dir)}

    def add_keys(self, keys: dict[str, str]) -> list[str]:
        """Write credential files (name → text) into this node's private keys folder."""
        if self.keys_dir is None:
            self.keys_dir = self.dir / "keys"
            self.keys_dir.mkdir(mode=0o700)
        for name, text in keys.items():
            if "/" in name or name.startswith("."):
                raise ValueError(f"bad key file name {name!r}")
            fd = os.open(self.keys_dir / name, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(text)
        return sorted(keys)

    def make_keys(self, n_sats: int, shares: list[list[str]], router_hosts: list[list[str]] | None = None) -> Any:
        """(On the head.) The run's credentials, made here; returns one dict of files per
        entry of ``shares`` (each a list of the file names that node gets), as separate Ray
        objects (``num_returns``), and keeps the set for :meth:`key_share`. ``router_hosts``:
        TLS between the nodes (a cluster over several hosts): a CA and a certificate per
        node's router, valid for that node's names (:func:`swarmrt.security.make_keys`); the
        CA's key is gone once they are signed, and the routers' keys once handed out (node i's
        share has its own router's only), so nothing here can sign or serve as another node;
        the driver's client certificate's key (mutual TLS) goes the same way."""
        from swarmrt.security import make_keys

        d = Path(tempfile.mkdtemp(prefix=f"swarm-keys-{self.run}-", dir=self.dir))
        try:
            make_keys(d, n_sats, router_hosts=router_hosts)
            self._all_keys = {p.name: p.read_text() for p in d.iterdir() if p.is_file()}
        finally:
            shutil.rmtree(d, ignore_errors=True)
        out = tuple(self.key_share(names) for names in shares)
        for name in [n for n in self._all_keys if n.endswith(".key")]:  # the routers' and the driver's: handed out once
            del self._all_keys[name]
        return out if len(out) > 1 else out[0]

    def key_share(self, names: list[str]) -> dict[str, str]:
        """(On the head.) The credential files ``names`` of the run's keys; ``passwords:agents``
        is the router's dictionary cut down to the agents and the mesh (a worker node's
        router: its clients are agents, its peers routers)."""
        out = {}
        for n in names:
            if n.startswith("router-tls:"):  # node i's router's certificate and key, under the names router.json gives
                i = int(n.removeprefix("router-tls:"))
                out["router.pem"], out["router.key"] = self._all_keys[f"router-{i}.pem"], self._all_keys[f"router-{i}.key"]
            elif n == "passwords:agents":
                lines = [ln for ln in self._all_keys["passwords"].splitlines()
                         if ln.startswith("agent-") or ln.startswith("mesh:")]
                out["passwords"] = "".join(f"{ln}\n" for ln in lines)
            elif n in self._all_keys:
                out[n] = self._all_keys[n]
            else:
                raise KeyError(f"no key file {n}")
        return out

    def free_port(self, host: str | None = None) -> int:
        """A free TCP port on this node's address (or on ``host``: 127.0.0.1)."""
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host or self.ip, 0))
            return s.getsockname()[1]

    # -- processes ----------------------------------------------------------------------
    def _log(self, name: str) -> Path:
        return self.dir / "logs" / f"{name}.log"

    def _popen(self, name: str, args: list[str], env_extra: dict[str, str] | None = None, **kw) -> subprocess.Popen:
        r = self._lifeline[0]
        grace = _ORPHAN_RECORDER_GRACE_S if name == "recorder" else _ORPHAN_GRACE_S
        cleanup = ["--remove-when-orphaned", str(self.dir)]
        cmd = [self.python, "-m", "swarm.supervise.lifeline", "--fd", str(r), "--grace-s", str(grace), *cleanup, *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
        for k in [k for k in env if k.startswith("RAY_")]:
            env.pop(k)  # a role is no Ray worker
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, env=env, pass_fds=(r,), start_new_session=True, **kw)

    def _track(self, name: str, p: Any) -> int:
        with self._cond:
            self.procs[name] = p
            self._all.append((name, p))
            self._cond.notify_all()
        return p.pid

    def connect_to(self, identity: str) -> list[str]:
        """Where a process of this node connecting as ``identity`` reaches the node's router:
        its own port of the node's ingress gate (the host's loopback) when there is one."""
        if self.gate_endpoints:
            from swarm.supervise.gate import OTHER

            return [self.gate_endpoints.get(identity, self.gate_endpoints[OTHER])]
        return list(self.local_endpoints or self.endpoints)  # (no gate: the router's loopback listener, if any)

    def bus_args(self, identity: str) -> list[str]:
        cred = ["--credential", str(self.keys_dir / f"{identity}.json")] if self.keys_dir is not None else []
        return ["--mode", "client", *[a for e in self.connect_to(identity) for a in ("--connect", e)], *cred]

    def role_args(self, identity: str) -> list[str]:
        return ["--scenario", str(self.scenario_file), "--run", self.run, *self.bus_args(identity)]

    def start_router(self, name: str, listen: list[str], connect: list[str], index: int, timeout: float = 60.0,
                     gate: list[dict[str, Any]] | None = None) -> int:
        """This node's Zenoh router, listening on ``listen`` (the mesh's and the driver's way
        in) and dialling ``connect`` (the other nodes' routers); returns its pid once it says
        READY. ``gate``: the entries of its ingress gate (:func:`swarm.supervise.gate.plan_entries`,
        as dicts): the node's own processes then reach it through the gate, each identity at its
        own port of this host's loopback (:meth:`connect_to`); a restarted router binds the
        same ports (its plan, written back once it listens)."""
        secure = (["--keys", str(self.keys_dir), "--run", self.run, "--scenario", str(self.scenario_file)]
                  if self.keys_dir is not None else [])
        mesh = [a for e in connect for a in ("--connect", e)]
        listens = [a for e in listen for a in ("--listen", e)]
        plan = self.dir / f"gate-{name}.json"
        if gate is not None:
            from swarm.supervise.gate import Entry, PortReservation, write_plan

            if not plan.exists():
                # Its ports reserved by this actor, which outlives the router (a restart binds
                # them again whatever ran meanwhile: swarm.supervise.gate.PortReservation).
                if self._ports is None:
                    self._ports = PortReservation()
                write_plan(plan, self._ports.assign([Entry(**e) for e in gate]), str(self.dir / f"{name}.sock"))
            listens += ["--gate", str(plan), "--gate-counts", str(self.dir / "logs" / f"gate-{name}.json")]
        with open(self._log(name), "ab") as logf:
            p = self._popen(name, ["swarm.supervise.router", *listens, "--index", str(index), *mesh, *secure],
                            stdout=subprocess.PIPE, stderr=logf)
        line: list[bytes] = []
        out = p.stdout
        assert out is not None
        t = threading.Thread(target=lambda: line.append(out.readline()), daemon=True)
        t.start()
        t.join(timeout)
        if not line or b"READY" not in line[0]:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            raise RuntimeError(f"node {self.index}: the Zenoh router {name} did not start within {timeout:.0f} s "
                               f"(its log: {self._log(name)}: {self._tail(name)})")
        if gate is not None:
            from swarm.supervise.gate import loopback_endpoints, read_plan

            self.gate_endpoints = loopback_endpoints(read_plan(plan)[0])
        return self._track(name, p)

    def set_endpoints(self, endpoints: list[str], local: list[str] | None = None) -> None:
        """How this node's router is reached (``endpoints``); ``local``: a loopback TCP
        endpoint of it, for this node's processes when the cluster's links are mutual TLS and
        there is no gate: reachable from this host only."""
        self.endpoints = list(endpoints)
        self.local_endpoints = list(local or [])

    def spawn_role(self, name: str, identity: str, extra: list[str] | None = None) -> int:
        """World, selector or recorder (``python -m MODULE``) under the lifeline."""
        module = ROLE_MODULES[name]
        args = [module, *self.role_args(identity), *(extra or [])]
        if name == "recorder":
            args = [module, "--run", self.run, "--out", str(self.out / "run.mcap"), "--scenario", str(self.scenario_file),
                    *(extra or []), *self.bus_args("recorder")]
        with open(self._log(name), "ab" if name in self.procs else "wb") as logf:
            p = self._popen(name, args, stdout=logf, stderr=subprocess.STDOUT)
        return self._track(name, p)

    def spawn_agent(self, i: int, restart: bool, command: str | None, start: str) -> int:
        """Satellite i's agent: forked from this node's fork server (``start == "fork"``),
        a fresh interpreter (``spawn``), or ``command`` (another language) under the lifeline."""
        name = f"agent-{i}"
        if command is not None:
            from swarm.supervise.launch import foreign_agent_env
            from swarmrt.bus.session import BusConfig
            from swarmrt.node import load_role_scenario

            sc = load_role_scenario(str(self.scenario_file))
            bus = BusConfig(mode="client", connect=self.connect_to(name),
                            credential_file=str(self.keys_dir / f"{name}.json") if self.keys_dir is not None else None)
            env = foreign_agent_env(sc, i, self.run, bus, self.dir, restart)
            with open(self._log(name), "ab" if name in self.procs else "wb") as logf:
                p = self._popen(name, ["--exec", *shlex.split(command)], env_extra=env, stdout=logf, stderr=subprocess.STDOUT)
            return self._track(name, p)
        args = ["--id", str(i), *(["--restart"] if restart else []), *self.role_args(name)]
        if start == "fork":
            from swarm.supervise.forkserver import AgentForkServer

            if self._forkserver is None:
                self._forkserver = AgentForkServer()
            log = self._log(name)
            if name not in self.procs and log.exists():
                log.unlink()
            env = {"PYTHONUNBUFFERED": "1"}
            p = self._forkserver.spawn(args, log, env=env, grace_s=_ORPHAN_GRACE_S, remove_when_orphaned=(str(self.dir),))
            return self._track(name, p)
        with open(self._log(name), "ab" if name in self.procs else "wb") as logf:
            p = self._popen(name, ["sat_agent", *args], stdout=logf, stderr=subprocess.STDOUT)
        return self._track(name, p)

    def spawn_agents(self, specs: list[tuple[int, bool, str | None]], start: str) -> list[int]:
        """:meth:`spawn_agent` for each (satellite, restart, command): one call for a node's agents."""
        return [self.spawn_agent(i, restart, command, start) for i, restart, command in specs]

    def _find(self, name: str, pid: int):
        with self._lock:
            for n, p in reversed(self._all):
                if n == name and p.pid == pid:
                    return p
        return None

    def signal(self, name: str, pid: int, sig: int, group: bool = True) -> bool:
        """Send ``sig`` to process ``name`` (pid ``pid``, still running), its whole process
        group by default. False when it had ended."""
        p = self._find(name, pid)
        if p is None or p.poll() is not None:
            return False
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if group:
                os.killpg(pid, sig)
            else:
                os.kill(pid, sig)
        return True

    def stall_net(self, pid: int, down_s: float) -> int:
        """The safety net of a stall (see LocalSwarm._stall): a shell of its own continues
        the group ``down_s`` later should nobody else. Returns its pid."""
        from swarm.supervise.launch import stall_safety_net

        return self._track(f"stall-net-{pid}", stall_safety_net(pid, down_s))

    def _reap(self) -> None:
        """Notice every exit (the driver's :meth:`events` hands them out), and the driver's
        silence (its lease: see swarm.cluster.swarm.LEASE_S)."""
        while not self._closed:
            if self.lease_s is not None and self._last_seen is not None and time.monotonic() - self._last_seen > self.lease_s:
                sys.stderr.write(f"node host {self.index}: no word from the driver for {self.lease_s:g} s; stopping everything\n")
                self.shutdown(2.0)
                os._exit(1)
            with self._cond:
                for name, p in self._all:
                    if p.pid not in self._reported and p.poll() is not None:
                        self._reported.add(p.pid)
                        self._exits.append((name, p.pid, p.returncode))
                        self._cond.notify_all()
            threading.Event().wait(0.05)  # a poll period, not a synchronisation (waitpid has no timeout)

    def events(self, cursor: int, timeout: float) -> tuple[list[tuple[str, int, int]], int]:
        """The exits seen since ``cursor`` (waiting up to ``timeout`` s for one), and the
        new cursor."""
        self._last_seen = time.monotonic()
        with self._cond:
            self._cond.wait_for(lambda: len(self._exits) > cursor or self._closed, timeout)
            return self._exits[cursor:], len(self._exits)

    def terminate(self, names: list[str], grace: float) -> dict[str, int]:
        """SIGTERM each named running process, wait at most ``grace`` s in all, SIGKILL the
        process group of whoever is left (LocalSwarm._terminate, here)."""
        with self._lock:
            procs = [(n, p) for n in names if (p := self.procs.get(n)) is not None]
        for _n, p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        out = {}
        for n, p in procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()
            out[n] = p.returncode
        return out

    def names(self) -> list[str]:
        with self._lock:
            return list(self.procs)

    # -- files ------------------------------------------------------------------------
    def _tail(self, name: str, n: int = 400) -> str:
        with contextlib.suppress(OSError):
            return self._log(name).read_bytes()[-n:].decode(errors="replace")
        return ""

    def logs(self, limit: int = 4 << 20) -> dict[str, bytes]:
        """Every log here (the last ``limit`` bytes of each), and its router's gate counts."""
        out = {}
        for p in sorted([*(self.dir / "logs").glob("*.log"), *(self.dir / "logs").glob("gate-*.json")]):
            with contextlib.suppress(OSError):
                data = p.read_bytes()
                out[p.name] = data[-limit:]
        return out

    def read_chunk(self, rel: str, offset: int, size: int = 8 << 20) -> bytes:
        """A piece of a file of this node's run folder (the recording, when the driver does
        not share it)."""
        path = (self.out / rel).resolve()
        if self.out.resolve() not in path.parents:
            raise ValueError(f"{rel}: not in the run folder")
        with open(path, "rb") as f:
            f.seek(offset)
            return f.read(size)

    def file_size(self, rel: str) -> int:
        p = self.out / rel
        return p.stat().st_size if p.exists() else -1

    # -- the end ----------------------------------------------------------------------
    def shutdown(self, grace: float = 5.0) -> list[tuple[str, int]]:
        """Stop whatever still runs here, the fork server too, and delete this node's
        folder (its credentials). Returns the processes still running after it (name, pid):
        none, unless a SIGKILL did not take within 10 s."""
        with self._lock:
            names = list(self.procs)
        self.terminate(names, grace)
        for _name, p in self._all:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGKILL)
        deadline = time.monotonic() + 10.0
        for _name, p in self._all:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
        left = [(n, p.pid) for n, p in self._all if p.poll() is None]
        if self._forkserver is not None:
            self._forkserver.close()
            self._forkserver = None
        if self._ports is not None:
            self._ports.release()
        for fd in self._lifeline:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._closed = True
        with self._cond:
            self._cond.notify_all()
        shutil.rmtree(self.dir, ignore_errors=True)
        return left

    def die(self) -> str:
        """kill-node on a cluster of real hosts: SIGKILL everything this node runs for the
        run, then its raylet (this worker's parent), then this process. What an operator's
        ``kill -9`` of the node's Ray would do; the node leaves the cluster."""
        raylet = os.getppid()
        with self._lock:
            pids = [p.pid for _n, p in self._all if p.poll() is None]
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(pid, signal.SIGKILL)
        detail = f"SIGKILL {len(pids)} processes of the run and the raylet (pid {raylet})"

        def later() -> None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(raylet, signal.SIGKILL)
            os._exit(137)

        threading.Timer(0.2, later).start()  # after this reply has gone out
        return json.dumps({"detail": detail})
