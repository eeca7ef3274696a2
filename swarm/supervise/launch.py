"""``swarm run``: a whole swarm as local processes on loopback, supervised.

Starts a Zenoh router, the recorder, N agents, the selector (when the scenario selects)
and the world, each its own process (``python -m ...``) connected to the router. The
supervisor (this process) executes the process-level faults — kill, stop or restart an
agent or the selector — whether they come from the scenario (via the world) or from
``swarm fault`` at any time, and reports each on the bus so it lands in the recording.
When the world finishes, every process is stopped cleanly and ``summary.json`` is
computed from the recording.

Ownership: whatever ends the supervisor ends its processes within seconds.

- Each child is started through :mod:`swarm.supervise.lifeline`, holding the read end of a pipe
  whose write end only the supervisor holds: when the supervisor dies (even by SIGKILL)
  the kernel closes it, the child reads EOF and stops itself (SIGTERM, then a hard exit
  after a grace period). ``lifeline.py`` says why this and not ``PR_SET_PDEATHSIG``.
- SIGINT, SIGTERM and SIGHUP to the supervisor (:meth:`LocalSwarm.handling_signals`)
  interrupt the run: the world, the selector and the agents are stopped first, then the
  recorder, which closes ``run.mcap`` (finalised and indexed), then the router; the
  caller writes a summary marked as interrupted. A second signal kills everything at once.
- Every child runs in its own session (its own process group): a Ctrl-C typed in the
  terminal reaches only the supervisor, which stops the roles in the order above rather
  than all at once; and a fault (``kill-agent 2``) signals one process, its target.

Security (``emulator.security``, on by default): the run's credentials are made afresh in
a private temporary directory named in ``run.json`` (owner-only; :mod:`swarmrt.security`),
every process connects with its own
(agent i as ``agent-<i>``), the router enforces the run's access rules, and ``swarm fault
--run-dir OUT`` uses its ``cli.json``. The keys are deleted when the run ends. Off, the
bus is open to anyone on this machine, and the supervisor and the router say so loudly.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import yaml

from swarm.supervise.forkserver import AgentForkServer, ForkedAgent
from swarm.supervise.gate import PortReservation
from swarmcore.scenario import AGENT_PROCESS_FAULTS, CLUSTER_FAULTS, ROUTER_FAULTS, STALL_FAULTS, Scenario
from swarmrt.bus.messages import Fault, Keys, as_dict, opt, replace
from swarmrt.bus.session import BusConfig
from swarmrt.node import Node
from swarmrt.protocol import BUS_LEASE_S, EXIT_AGENT_LOST, EXIT_BUS_LOST, first_time, outbox_steps

__all__ = ["LocalSwarm", "Interrupted", "free_port", "client_bus"]

# Grace periods (s): after SIGTERM, how long a role may take to stop before SIGKILL.
_ROLE_GRACE_S = 15.0  # a normal end: the roles are finishing by themselves
_INTERRUPT_GRACE_S = 5.0  # an interrupted run: "within a few seconds"
_RECORDER_GRACE_S = 60.0  # the recorder rewrites run.mcap as an indexed file on close
_CLEAN_EXIT_GRACE_S = 10.0  # an agent that exited 0 saw the world's last clock; ours may lag that long
_ORPHAN_GRACE_S = 5.0  # lifeline: a child whose supervisor vanished
_ORPHAN_RECORDER_GRACE_S = 15.0

_INTERRUPT_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupted(RuntimeError):
    """The run was interrupted by a signal while it was starting."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def client_bus(endpoints: list[str], keys_dir: Path | None, identity: str) -> BusConfig:
    """How a process of a local swarm connects: a client of the routers at ``endpoints``, as
    ``identity`` (its credential file in ``keys_dir`` when security is on)."""
    cred = str(keys_dir / f"{identity}.json") if keys_dir is not None else None
    return BusConfig(mode="client", connect=list(endpoints), credential_file=cred)


def foreign_agent_env(sc: Scenario, sat: int, run: str, bus: BusConfig, out: Path | None, restart: bool,
                      scenario_json: Path | None = None) -> dict[str, str]:
    """What an agent of another language is given (docs/agent-contract.md, clause 1): its
    satellite, the run, the routers, its credential and the scenario, resolved, as JSON
    (``scenario.json`` in the run folder ``out``, or ``scenario_json`` as written already,
    with the values a scenario implies but does not state: the gate's χ² threshold)."""
    if scenario_json is not None:
        path = scenario_json
    elif out is not None:
        path = out / "scenario.json"
        if not path.exists():
            write_scenario_json(sc, path)
    else:
        raise ValueError("foreign_agent_env: a run folder or a scenario_json")
    return {
        "SWARM_SAT_ID": str(sat),
        "SWARM_RUN": run,
        "SWARM_CONNECT": ",".join(bus.connect),
        "SWARM_CREDENTIAL": bus.credential_file or "",
        "SWARM_SCENARIO_JSON": str(path),
        "SWARM_RESTART": "1" if restart else "0",
    }


def stall_safety_net(pgid: int, down_s: float) -> subprocess.Popen:
    """The safety net of a stall: should the supervisor die meanwhile, nothing would ever
    continue the stopped process group ``pgid`` (its lifeline cannot act while it is stopped,
    and it leads its own session, so no orphaned-group SIGCONT comes from the kernel): a
    shell of its own, in a session of its own, continues the group ``down_s`` later.
    ``kill -s CONT -- -PGID``, the POSIX form: Debian's sh (dash) refuses ``kill -CONT --``
    ("Illegal number"), and the net did nothing (seen: a world left stopped by a campaign
    that was killed during its stall)."""
    return subprocess.Popen(["sh", "-c", f"sleep {down_s:.3f}; kill -s CONT -- -{pgid} 2>/dev/null"], start_new_session=True,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def write_scenario_json(sc: Scenario, path: Path) -> Path:
    """The resolved scenario as JSON, with ``derived``: numbers the scenario implies
    (``gate_threshold``: the χ²(6) quantile of filter.gate, null when the gate is off;
    ``radio_peers``: for each satellite, the peers whose batches the ideal radio sends it on
    its own ``batches/<i>``, or null when every agent hears everyone on ``batches``)."""
    import json

    from swarmcore.graphs import radio_peers, scenario_graph
    from swarmrt.estimators import check_estimator

    hears = None if sc.links.enabled else radio_peers(scenario_graph(sc), check_estimator(sc).radio)
    doc = sc.model_dump(mode="json")
    doc["derived"] = {"gate_threshold": sc.filter.gate.threshold(), "steps": sc.steps,
                      "radio_peers": None if hears is None else [h.tolist() for h in hears]}
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


class LocalSwarm:
    """The processes of one run; :meth:`run` drives it to the end."""

    def __init__(self, sc: Scenario, out: Path, run_id: str | None = None, python: str = sys.executable, log=print,
                 routers: int = 1, live: str | None = None):
        if routers not in (1, 2):
            raise ValueError(f"--routers {routers}: 1 or 2 (two routers in a mesh)")
        if (why := sc.vision.distributed_refusal()) is not None:
            raise ValueError(why)
        self.sc = sc
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "logs").mkdir(exist_ok=True)
        self.run = run_id or f"{_slug(sc.name)}-{uuid.uuid4().hex[:6]}"
        self.keys = Keys(self.run)
        self.python = python
        self.say = log
        self.scenario_file = self.out / "scenario.yaml"
        self.scenario_file.write_text(yaml.safe_dump(sc.model_dump(mode="json"), sort_keys=False))
        # Popen-like: subprocess.Popen, ForkedAgent, or a process on another host (swarm.cluster.swarm.RemoteProc)
        self.procs: dict[str, Any] = {}
        self.endpoint: str | None = None  # router 0's endpoint, once started
        self.n_routers = routers
        self.endpoints: list[str] = []  # router i listens on endpoints[i] (with the gate: its shared "other" port)
        self.gate_endpoints: dict[str, list[str]] = {}  # with the gate: each identity's own port on each router
        self._gate_dir: Path | None = None  # the gate plans and the routers' Unix sockets (a private 0700 directory)
        self._port_reservation = PortReservation()  # the gates' ports, held for the run (released at stop)
        self.router_names = ["router" if i == 0 else f"router-{i}" for i in range(routers)]
        self.broken: str | None = None  # why the run could not go on (bus lost, world gone, an agent gone by itself)
        self.broken_code: int | None = None  # the exit status that says so, when not the world's
        self._faulted: set[int] = set()  # pids this supervisor killed or stopped (a fault): their end is no surprise
        # Processes stopped by a stall fault: (when to continue them, monotonic; process; the command; the
        # safety net that continues it should this supervisor die meanwhile; SIGSTOP's time)
        self._stalled: list[tuple[float, subprocess.Popen | ForkedAgent, Fault, subprocess.Popen | None, float]] = []
        self.world_done = False  # the world's last clock (done) has come: agents may leave
        self._clean_exit_at: dict[int, float] = {}  # pid of an agent that exited 0 → when (monotonic) that was seen
        self._dropped: str | None = None  # a role whose session the router dropped while it ran (see _token_gone)
        self._started_at: dict[str, float] = {}  # process name → when (monotonic) its current process was started
        self.router_faults: list[dict] = []  # router faults executed here (the bus may not have carried the report)
        # Every fault report put here. Those of the last steps are sent again (the same bytes:
        # a recording and the world read each once; _send_reports_again) when this supervisor,
        # the world or the recorder comes back to the bus, and once more after a burst of
        # returns: a report put while a router failed over, or while the recorder was stalled
        # or away, must still reach the recording.
        self._reports: list[Fault] = []
        self._commands_seen: set[bytes] = set()
        self.bus: BusConfig | None = None  # the supervisor's own connection, once started
        self.node: Node | None = None
        self.faults: list[dict] = []
        self.keys_dir: Path | None = None  # the run's credentials (emulator.security)
        self.k = 0
        self._lock = threading.Lock()
        self.interrupted: signal.Signals | None = None  # the signal that interrupted the run
        self._lifeline: tuple[int, int] | None = None  # (read end for children, write end kept here)
        self.live = live  # HOST:PORT of the live 3-D view (swarm.live), None: no view
        self._forkserver: AgentForkServer | None = None  # the Python agents' fork server (emulator.agent_start: fork)

    # -- processes -----------------------------------------------------------------
    def _popen(self, name: str, args: list[str], env_extra: dict[str, str] | None = None, **kw) -> subprocess.Popen:
        """``python -m swarm.supervise.lifeline --fd R MODULE ARGS`` in its own session (see the module
        docstring). Only the read end of the lifeline is passed on; the write end is not
        inheritable (``os.pipe``), so no child can keep its siblings' lifeline open."""
        if self._lifeline is None:
            self._lifeline = os.pipe()
        r = self._lifeline[0]
        grace = _ORPHAN_RECORDER_GRACE_S if name == "recorder" else _ORPHAN_GRACE_S
        # The run's credentials go with it, even when the supervisor is SIGKILLed and cannot
        # delete them itself: its orphaned children do.
        # A supervisor SIGKILLed leaves no credentials nor gate sockets behind: its children remove them.
        cleanup = [a for d in (self.keys_dir, self._gate_dir) if d is not None for a in ("--remove-when-orphaned", str(d))]
        cmd = [self.python, "-m", "swarm.supervise.lifeline", "--fd", str(r), "--grace-s", str(grace), *cleanup, *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, env=env, pass_fds=(r,), start_new_session=True, **kw)

    def _spawn(self, name: str, args: list[str], env_extra: dict[str, str] | None = None) -> subprocess.Popen:
        # A fresh log per run; a restarted process appends to its predecessor's.
        with open(self.out / "logs" / f"{name}.log", "ab" if name in self.procs else "wb") as logf:
            p = self._popen(name, args, env_extra, stdout=logf, stderr=subprocess.STDOUT)
        with self._lock:
            self.procs[name] = p
            self._started_at[name] = time.monotonic()
        return p

    def bus_as(self, identity: str) -> BusConfig:
        """The bus configuration of a process connecting as ``identity`` (its credential
        file when security is on)."""
        return client_bus(self.gate_endpoints.get(identity, self.endpoints), self.keys_dir, identity)

    def gate_counts(self) -> dict[str, dict[str, Any]]:
        """What the routers' ingress gates counted, per identity (``router_gate`` in
        summary.json; empty without the gate)."""
        from swarm.supervise.gate import seen_counts

        return seen_counts(sorted((self.out / "logs").glob("gate-*.json")))

    def _plan_gate(self) -> None:
        """The ingress gate (:mod:`swarm.supervise.gate`): a port per identity on each
        router, each with its bucket; the routers listen on Unix sockets in a private
        directory. Off with ``emulator.gate: false`` (or ``SWARM_ROUTER_GATE=off``, to measure)."""
        from swarm.supervise.gate import plan_entries, write_plan

        for old in (self.out / "logs").glob("gate-*.json"):
            old.unlink()  # a previous run's counts in a reused folder
        entries = plan_entries(self.sc)
        if entries is None:
            self.endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(self.n_routers)]
            return
        self._gate_dir = Path(tempfile.mkdtemp(prefix="swarm-gate-"))
        self.gate_endpoints = {}
        # Each router's ports reserved here for the whole run (PortReservation: below the
        # ephemeral range, claimed against every other swarm process of the machine), so that
        # a router restarted by a fault binds them again whatever ran meanwhile; each router
        # writes back what it bound (_gate_ports). A port none could be reserved for stays 0:
        # the router's gate chooses it (as it did before reservations).
        for i in range(self.n_routers):
            write_plan(self._gate_dir / f"router-{i}.json", self._port_reservation.assign(entries), str(self._gate_dir / f"r{i}.sock"))

    def _gate_ports(self, i: int) -> None:
        """Router ``i``'s ports, as its gate bound them (its plan, written back once it listens)."""
        from swarm.supervise.gate import OTHER, loopback_endpoints, read_plan

        assert self._gate_dir is not None
        entries, _ = read_plan(self._gate_dir / f"router-{i}.json")
        try:
            eps = loopback_endpoints(entries)
        except RuntimeError as exc:
            raise RuntimeError(f"router {i}: {exc}") from None
        for identity, ep in eps.items():
            self.gate_endpoints.setdefault(identity, [""] * self.n_routers)[i] = ep
        self.endpoints = self.gate_endpoints[OTHER]

    def _role_args(self, identity: str) -> list[str]:
        return ["--scenario", str(self.scenario_file), "--run", self.run, *self.bus_as(identity).as_args()]

    def spawn_agent(self, i: int, restart: bool = False) -> None:
        cmd = self.sc.emulator.agent_commands.get(i)
        if cmd is not None:
            env = foreign_agent_env(self.sc, i, self.run, self.bus_as(f"agent-{i}"), self.out, restart)
            self._spawn(f"agent-{i}", ["--exec", *shlex.split(cmd)], env_extra=env)
            return
        args = ["--id", str(i), *(["--restart"] if restart else []), *self._role_args(f"agent-{i}")]
        if self.sc.emulator.agent_start == "fork":
            name = f"agent-{i}"
            if self._forkserver is None:
                self._forkserver = AgentForkServer()
            log = self.out / "logs" / f"{name}.log"
            if name not in self.procs and log.exists():
                log.unlink()  # a fresh log per run; a restarted agent appends to its predecessor's
            cleanup = (str(self.keys_dir),) if self.keys_dir is not None else ()
            p = self._forkserver.spawn(args, log, env={"PYTHONUNBUFFERED": "1"}, grace_s=_ORPHAN_GRACE_S, remove_when_orphaned=cleanup)
            with self._lock:
                self.procs[name] = p
                self._started_at[name] = time.monotonic()
            return
        self._spawn(f"agent-{i}", ["sat_agent", *args])

    def spawn_selector(self) -> None:
        self._spawn("selector", ["selector", *self._role_args("selector")])

    def start(self) -> None:
        """Start every process. Raises :class:`Interrupted` if a signal (see
        :meth:`handling_signals`) arrives meanwhile; call :meth:`stop` in any case."""
        # Compile numba's kernels once, before the agents start: on a fresh checkout (or
        # after a kernel changed) every agent would otherwise compile the same kernels at
        # the same moment (~2.6 s of CPU each: 100 s at n = 40); afterwards each loads them
        # from the cache. Runs while the router and the recorder start.
        # (Short-lived; if it fails, each agent compiles for itself as before.)
        warm = subprocess.Popen([self.python, "-c", _WARM], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self._plan_gate()
        if self.sc.emulator.security:
            from swarmrt.security import make_keys

            # A private temporary directory (0700), never the run folder (which may be in a
            # repository); run.json says where, for `swarm fault --run-dir` and tools.
            self.keys_dir = make_keys(tempfile.mkdtemp(prefix=f"swarm-keys-{self.run}-"), self.sc.n_sats)
        else:
            self.say("[bold red]SECURITY OFF[/bold red] (emulator.security: off): no credentials, no access rules; "
                     "any process on this machine can publish anything on this run's bus, fault commands included")
        for i in range(self.n_routers):
            self._start_router(i, timeout=30.0)
        self.endpoint = self.endpoints[0]
        self.bus = self.bus_as("supervisor")
        self.node = self._open_node()
        self._spawn(
            "recorder",
            [
                "swarm.record.recorder",
                "--run",
                self.run,
                "--out",
                str(self.out / "run.mcap"),
                "--scenario",
                str(self.scenario_file),
                "--flush-every-s",
                str(self.sc.emulator.flush_every_s),
                *self.bus_as("recorder").as_args(),
            ],
        )
        self._wait_alive("recorder", 60.0)
        if self.live is not None:
            self.spawn_live()
        try:
            warm.wait(timeout=300)
        except subprocess.TimeoutExpired:
            warm.kill()
        for i in range(self.sc.n_sats):
            self.spawn_agent(i)
        if self.sc.selection.strategy != "none":
            self.spawn_selector()
        self._spawn("world", ["world_sim", *self._role_args("world")])
        self._write_run_json()
        self._check_interrupted()

    def spawn_live(self) -> None:
        """The live 3-D view (:mod:`swarm.live.server`), a read-only ``viewer`` of the bus:
        it writes ``live.json`` (its address) once it serves; waited for, so that a client can
        connect before the first step. A view that cannot serve (its port taken) is reported
        and the run goes on without it: nothing depends on it."""
        (self.out / "live.json").unlink(missing_ok=True)
        p = self._spawn("live", ["swarm.live.server", "--ws", str(self.live), "--info", str(self.out / "live.json"),
                                 *self._role_args("viewer")])
        up: list[bool] = []

        def on_event(ev) -> None:
            self._handle(ev)
            if ev.kind == "alive" and ev.role == "viewer" and ev.alive:
                up.append(True)

        self._node().wait_for(lambda: bool(up) or p.poll() is not None or self.interrupted is not None, 60.0, on_event,
                              wake=lambda: time.monotonic() + 0.2)
        self._check_interrupted()
        if not up:
            why = f"it exited with status {p.returncode}" if p.poll() is not None else "it did not come up within 60 s"
            self.say(f"[yellow]live view: not serving[/yellow] ({why}; see {self.out / 'logs' / 'live.log'}); the run goes on without it")

    def _start_router(self, i: int, timeout: float) -> None:
        """Start router ``i`` on its endpoint (the same one after a restart), meshed with
        the others, and wait until it says READY. It dials every other router that is
        running: at the start, the ones started before it; after a restart, all the others
        (the mesh is back at once, not at the peers' next retry). Its ``--index`` gives it
        its fixed Zenoh id and its peers' (:func:`swarmrt.security.router_zid`)."""
        name = self.router_names[i]
        running = [j for j in range(self.n_routers) if j != i and (q := self.procs.get(self.router_names[j])) is not None
                   and q.poll() is None]
        gate = self._gate_dir
        # With the gate a router listens on its Unix socket only (the gate owns the ports), and
        # the routers of a run dial each other's sockets: the mesh is not an identity to limit.
        mesh = [a for j in running for a in ("--connect", f"unixsock-stream/{gate / f'r{j}.sock'}" if gate else self.endpoints[j])]
        where = (["--gate", str(gate / f"router-{i}.json"), "--gate-counts", str(self.out / "logs" / f"gate-{name}.json")]
                 if gate else ["--listen", self.endpoints[i]])
        # Security on: the run's keys and rules; a router meshing with another connects as
        # the "mesh" identity (swarmrt/security.py).
        secure = (["--keys", str(self.keys_dir), "--run", self.run, "--scenario", str(self.scenario_file)]
                  if self.keys_dir is not None else [])
        with open(self.out / "logs" / f"{name}.log", "ab" if name in self.procs else "wb") as logf:
            router = self._popen(name, ["swarm.supervise.router", *where, "--index", str(i), *mesh, *secure],
                                 stdout=subprocess.PIPE, stderr=logf)
        with self._lock:
            self.procs[name] = router
        line = _readline(router.stdout, timeout=timeout, cancelled=lambda: self.interrupted is not None)
        self._check_interrupted()
        if not line or b"READY" not in line:
            raise RuntimeError(f"the Zenoh router {name} did not start (see {self.out / 'logs' / (name + '.log')})")
        if gate is not None:
            self._gate_ports(i)

    def _open_node(self) -> Node:
        """The supervisor's own bus node on ``self.bus`` (a local run's and a cluster's): fault
        commands and reports, clocks and liveliness."""
        em = self.sc.emulator
        assert self.bus is not None, "the supervisor's bus is set once the routers are up"
        node = Node("supervisor", 0, self.run, self.sc.n_sats, self.bus)
        node.hold_s = em.liveliness_hold_s
        node.bus_grace_s = em.bus_grace_s  # never gives up on the bus: it owns the router
        # A recorder whose token went is held as long as the roles hold it (Node.set_bus_limits):
        # stalled, or failing over once it resumes. Held only liveliness_hold_s here, a stalled
        # recorder whose router was killed was called gone and the run broken (repeat benchmark
        # seeds 8 and 16).
        node.hold_for["recorder"] = em.bus_lost_after_s
        node.subscribe(self.keys.faults())  # commands to carry out, and every report
        node.subscribe(self.keys.clock())
        node.watch_liveliness()
        return node

    def _node(self) -> Node:
        """The supervisor's own bus node (open from :meth:`start` until :meth:`stop`)."""
        if self.node is None:
            raise RuntimeError("the supervisor's bus node is not open (start() opens it, stop() closes it)")
        return self.node

    def _write_run_json(self) -> None:
        info = {
            "run": self.run,
            "supervisor_pid": os.getpid(),
            "endpoint": self.endpoint,
            "endpoints": self.endpoints,
            "n_sats": self.sc.n_sats,
            "pids": {k: p.pid for k, p in self.procs.items()},
            "scenario": str(self.scenario_file),
            "recording": str(self.out / "run.mcap"),
            "security": "on" if self.keys_dir is not None else "off",
            "keys": str(self.keys_dir) if self.keys_dir is not None else None,
        }
        (self.out / "run.json").write_text(json.dumps(info, indent=2) + "\n")

    def _wait_alive(self, role: str, timeout: float) -> None:
        up: list[bool] = []

        def on_event(ev) -> None:
            self._handle(ev)
            if ev.kind == "alive" and ev.role == role and ev.alive:
                up.append(True)

        # Wake every 0.2 s to notice a signal (the handler only sets a flag).
        self._node().wait_for(lambda: bool(up) or self.interrupted is not None, timeout, on_event,
                           wake=lambda: time.monotonic() + 0.2)
        self._check_interrupted()
        if not up:
            raise RuntimeError(f"{role} did not come up within {timeout:.0f} s (see {self.out / 'logs'})")

    # -- faults ------------------------------------------------------------------------
    def _report(self, f: Fault, phase: str, detail: str) -> Fault:
        # A scheduled command is stamped with the step it opens, whose clock has not come
        # yet: report at that step, not at the last clock seen here.
        k = max(self.k, f.k)
        done = replace(f, phase=phase, sender="supervisor", k=k, t_s=k * self.sc.dt_s, detail=detail)
        self._node().put(self.keys.fault_report("supervisor"), done)
        self._reports.append(done)
        return done

    def _send_reports_again(self) -> None:
        """The reports of the steps a returning world or recorder may lack (the steps every
        role keeps, :func:`swarmrt.protocol.outbox_steps`), put again. All of a run's reports,
        put again on every return of every role, were more messages than the supervisor's
        gate lets through in a burst: its connection was cut, and a command it was sent
        then was lost (the repeat benchmark, issue 35: 19 cuts in 40 runs)."""
        recent = self.k - outbox_steps(self.sc.emulator)
        self._put_again(r for r in self._reports if r.k >= recent)

    def _put_again(self, reports) -> None:
        """Put ``reports`` (made before, kept in ``_reports``) again, the same bytes."""
        for report in reports:
            self._node().put(self.keys.fault_report("supervisor"), report)

    def _handle(self, ev) -> None:
        if (ev.kind == "again" or (ev.kind == "bus" and ev.alive) or (ev.kind == "resync" and ev.role in ("world", "recorder"))
                or (ev.kind == "alive" and ev.alive and ev.role == "recorder")):
            self._send_reports_again()
        if ev.kind == "alive" and not ev.alive:
            self._token_gone(ev)
        if ev.kind == "clock":
            self.k = ev.msg.k
            self.world_done = self.world_done or ev.msg.done
        elif ev.kind == "fault" and ev.msg.phase == "command":
            if first_time(self._commands_seen, ev.msg):  # (a command sent again is carried out once)
                self.execute(ev.msg)
            else:
                # Said again: the world has not seen its outcome (our report may have been put
                # while our router's routes were being rebuilt, and lost): report it again.
                cmd = ev.msg
                self._put_again(r for r in self._reports if r.action == cmd.action and r.target == cmd.target and r.k >= cmd.k)
        elif ev.kind == "fault":
            self.faults.append(as_dict(ev.msg, exclude=("schema_version", "run")))

    def execute(self, f: Fault) -> None:
        if f.action in CLUSTER_FAULTS:
            return self._cluster_fault(f)
        if f.action in ROUTER_FAULTS:
            return self._router_fault(f)
        if f.action in STALL_FAULTS:
            return self._stall(f)
        name = f"agent-{f.target}" if f.action in AGENT_PROCESS_FAULTS else "selector"
        p = self.procs.get(name)
        if p is not None:
            self.continue_stalled(process=p)  # a stopped process would not act on SIGTERM; it is ended now anyway
        if p is not None and p.poll() is not None:
            p = None  # not running
        if f.action in ("kill-agent", "kill-selector"):
            if p is not None:
                # SIGKILL: no goodbye, the liveliness token just vanishes. The whole process
                # group: an agent of another language runs as the lifeline's child.
                self._faulted.add(p.pid)
                _kill_group(p, signal.SIGKILL)
                p.wait()
                self._report(f, "done", f"SIGKILL pid {p.pid}")
            else:
                self._report(f, "failed", f"{name} is not running")
        elif f.action == "stop-agent":
            if p is not None:
                self._faulted.add(p.pid)
                p.terminate()
                how = f"SIGTERM pid {p.pid}"
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    _kill_group(p, signal.SIGKILL)
                    p.wait()
                    how += ", SIGKILL to its process group after 10 s"
                self._report(f, "done", how)
            else:
                self._report(f, "failed", f"{name} is not running")
        elif f.action in ("restart-agent", "restart-selector"):
            if p is not None:
                self._faulted.add(p.pid)
                _kill_group(p, signal.SIGKILL)
                p.wait()
            if f.action == "restart-agent":
                self.spawn_agent(f.target, restart=True)
            else:
                self.spawn_selector()
            self._write_run_json()
            self._report(f, "done", f"started pid {self.procs[name].pid}")

    def _cluster_fault(self, f: Fault) -> None:
        """kill-node, partition-nodes: a cluster run's (swarm.cluster.swarm.RaySwarm)."""
        self._report(f, "failed", f"{f.action} needs a cluster run (swarm run --cluster ...): this run's processes are all local")

    def _stall_net(self, p, down_s: float):
        """The safety net of a stall (:func:`stall_safety_net` on the process's group)."""
        return stall_safety_net(p.pid, down_s)

    def _stall(self, f: Fault) -> None:
        """stall-*: SIGSTOP the role's process group now and SIGCONT it ``down_s`` wall
        seconds later (:meth:`continue_stalled`, from the run's loop: the supervisor goes on
        carrying out other faults meanwhile); reported done once continued. A stall is not
        a death: its end is no fault of ours, and a token lost past the lease still breaks
        the run (:meth:`_token_gone`)."""
        role = f.action.removeprefix("stall-")
        if role == "agent":
            name = f"agent-{f.target}"
        elif role == "router":
            i = int(opt(f, "target") or 0)
            name = self.router_names[i] if 0 <= i < self.n_routers else f"router {i}"
        else:
            name = role
        p = self.procs.get(name)
        if p is None or p.poll() is not None:
            self._report(f, "failed", f"{name} is not running")
            return
        if any(q is p for _t, q, _f, _n, _s in self._stalled):
            # Stopped still by an earlier stall: that one ends now (reported done, cut short),
            # this one starts. Whether the earlier stall was over when this command came is
            # wall time (the world steps on while a router or the recorder is stopped), and
            # "already stopped" made the same campaign's records differ (repeat benchmark,
            # seed 16: two stall-router 2 steps apart).
            self.continue_stalled(process=p)
        down_s = float(opt(f, "down_s") or 0.0)
        net = self._stall_net(p, down_s)
        _kill_group(p, signal.SIGSTOP)
        self._stalled.append((time.monotonic() + down_s, p, f, net, time.time()))
        self.say(f"step {self.k}: {name} (pid {p.pid}) stopped for {down_s:g} s")

    def continue_stalled(self, everyone: bool = False, process=None) -> None:
        """SIGCONT the stalled processes whose time is up (``everyone``: all of them;
        ``process``: that one, at once, before another fault acts on it) and report each
        stall done."""
        now = time.monotonic()
        due = [x for x in self._stalled if everyone or x[0] <= now or x[1] is process]
        if not due:
            return
        self._stalled = [x for x in self._stalled if x not in due]
        for _t, p, f, net, t_stop in due:
            gone = p.poll() is not None
            _kill_group(p, signal.SIGCONT)
            if net is not None and net.poll() is None:
                _kill_group(net, signal.SIGKILL)
                net.wait()
            detail = (f"SIGSTOP pid {p.pid}, " + ("gone since" if gone else f"SIGCONT after {time.time() - t_stop:.2f} s")
                      + (" (cut short by the run's end or another fault)" if _ended_early(t_stop, f) else ""))
            with contextlib.suppress(Exception):  # the bus may be gone at the run's end: the stall still ends
                self._report(f, "done", detail)

    def _router_fault(self, f: Fault) -> None:
        """kill-router / restart-router (target: the router's index, default 0). While no
        router is up nothing can be reported on the bus: the report goes out once this
        node is connected again (and is kept here for the summary in any case)."""
        deferred: list = []  # commands that came meanwhile: carried out after this one, however it ended
        self._carry_out_router_fault(f, deferred)  # (its early returns dropped them: a lost command)
        for ev in deferred:
            self._handle(ev)

    def _carry_out_router_fault(self, f: Fault, deferred: list) -> None:
        i = int(opt(f, "target") or 0)
        if not 0 <= i < self.n_routers:
            self._report(f, "failed", f"no router {i} (this run has {self.n_routers})")
            return
        name = self.router_names[i]
        p = self.procs.get(name)
        # Every event meanwhile is handled as in the run's loop (a recorder whose token comes
        # back gets every report again: the stall reported done while it was failing over
        # would otherwise be lost), but a command is carried out after this one (deferred).

        def on_event(ev) -> None:
            if ev.kind == "fault" and ev.msg.phase == "command":
                deferred.append(ev)
            else:
                self._handle(ev)

        n = self._node()

        # While the bus is down a wait's timeout counts from its return (Node.wait_for), so
        # with every router gone for good it would never end: the run ending (the world
        # exits once it has waited out its own grace) or a signal ends it.
        def over() -> bool:
            world = self.procs.get("world")
            return self.interrupted is not None or (world is not None and world.poll() is not None)

        def tick() -> float:
            self.continue_stalled()  # a stall ends on time even while a router fault is carried out
            return time.monotonic() + 0.1

        waited = ""
        short = [x for x in self._stalled if x[2].action in _SHORT_HOLD_STALLS]
        if p is not None and p.poll() is None and short:
            # A stopped process cannot fail over: a router killed under a stalled agent or
            # selector would turn its stall into a disappearance (its token gone with the
            # router, counted gone after liveliness_hold_s or not, as the wall clock falls),
            # and the same campaign would give other numbers. So the router waits for those
            # stalls to end on time and their tokens to be back (issue 35: a stall and a router
            # fault at one step, seeds 1, 11, 13 of the repeat benchmark). The world's and the
            # recorder's tokens are held bus_lost_after_s: they fail over when they resume.
            who = ", ".join(f"{q.pid}" for _t, q, _f, _n, _s in short)
            t_wait = time.monotonic()
            until = max(t for t, _q, _f, _n, _s in short) - t_wait
            n.wait_for(lambda: not any(x in self._stalled for x in short) or over(), until + 5.0, on_event, wake=tick)
            n.wait_for(lambda: not n._held or over(), self.sc.emulator.bus_grace_s, on_event, wake=tick)
            wait_s = time.monotonic() - t_wait
            waited = f" (carried out once the stall of pid {who} had ended: {wait_s:.2f} s later)"
            self.say(f"step {self.k}: {f.action} {i} waited {wait_s:.2f} s for the stall of pid {who} to end")
        t_down = time.time()
        was_running = p is not None and p.poll() is None
        killed = ""  # "SIGKILL pid <pid>" when it was running
        if p is not None and was_running:
            p.kill()  # SIGKILL: the router's links just close
            p.wait()
            killed = f"SIGKILL pid {p.pid}"
        if f.action == "kill-router":
            detail = killed if was_running else f"{name} is not running"
        else:
            down_s = float(opt(f, "down_s") or 0.0)
            if down_s > 0:
                time.sleep(down_s)  # the fault itself: the router stays down this long (wall time)
            self._start_router(i, timeout=30.0)
            t_up = time.time()
            self._write_run_json()
            detail = (f"{killed}, " if was_running else "") + (
                f"new router pid {self.procs[name].pid} on {self.endpoints[i]} after {time.time() - t_down:.2f} s")
        detail += waited
        self.router_faults.append({"k": max(self.k, f.k), "action": f.action, "target": i, "phase": "done", "sender": "supervisor",
                                   "detail": detail, "t_down_unix_s": t_down,
                                   **({"t_up_unix_s": t_up} if f.action == "restart-router" else {})})
        if not was_running and f.action == "kill-router":
            self._report(f, "failed", detail)
            return
        if f.action == "kill-router" and not any((q := self.procs.get(other)) is not None and q.poll() is None
                                                 for other in self.router_names if other != name):
            # No router left: nothing to reconnect to, and a wait would last as long as the
            # bus is down (waits pause then). The run breaks after bus_lost_after_s; the
            # report is kept for the summary (router_faults).
            return
        # Report once this node is connected again (at once when another router is up)
        # and every liveliness token that went with the router is back: a report put
        # before the others have reconnected would reach nobody.
        n.wait_for(lambda: (n.bus_up and n.router_linked) or over(), 5.0 if f.action == "kill-router" else 30.0, on_event, wake=tick)
        if not over():
            n.wait_for(lambda: not n._held or over(), self.sc.emulator.bus_grace_s, on_event, wake=tick)
        self._report(f, "done", detail)

    # -- signals -------------------------------------------------------------------------
    @contextlib.contextmanager
    def handling_signals(self):
        """While inside, SIGINT, SIGTERM and SIGHUP interrupt the run (see the module
        docstring); a second one kills every process at once and exits 128 + signal.
        Main thread only (Python delivers signals there); the previous handlers come back
        on exit."""

        def on_signal(signum, _frame):
            if self.interrupted is None:
                self.interrupted = signal.Signals(signum)  # the loops notice within 0.2 s
                return
            self.kill_all()
            os._exit(128 + signum)

        old = {s: signal.signal(s, on_signal) for s in _INTERRUPT_SIGNALS}
        try:
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    def _check_interrupted(self) -> None:
        if self.interrupted is not None:
            raise Interrupted(f"interrupted by {self.interrupted.name} while starting")

    def kill_all(self) -> None:
        """SIGKILL every process (and its process group) at once; no clean stop."""
        for p in list(self.procs.values()):
            _kill_group(p, signal.SIGKILL)

    # -- the run ---------------------------------------------------------------------
    def run_to_end(self, progress=None, timeout: float | None = None) -> int | None:
        """Follow the run until the world ends (its exit code) or a signal interrupts it
        (None; :attr:`interrupted` says which, and :meth:`stop` ends the world)."""
        world = self.procs["world"]
        deadline = None if timeout is None else time.monotonic() + timeout
        while world.poll() is None:
            if self.interrupted is not None:
                self.say(f"{self.interrupted.name} at step {self.k}: stopping every process, closing the recording "
                         "(once more to kill them all at once)")
                return None
            if deadline is not None and time.monotonic() > deadline:
                self.say(f"timeout: stopping the run after {timeout:.0f} s")
                self.continue_stalled(everyone=True)  # a stopped world would not act on SIGTERM
                world.terminate()
                break
            self.continue_stalled()
            ev = self._node().next_event(0.1 if self._stalled else 0.2)
            if ev is not None:
                self._handle(ev)
                if ev.kind == "clock" and progress is not None:
                    progress(ev.msg.k + 1, self.sc.steps)
            if (gone := self.agent_gone()) is not None:
                # Never "finished" with an agent gone: a run whose agent left by itself (the
                # world lost from its view, a crash) is broken, and says which and why.
                self.broken, self.broken_code = gone, EXIT_AGENT_LOST
                self.say(f"[bold red]the run is broken[/bold red] at step {self.k}: {gone}; stopping every process")
                return None
        code = world.wait()
        if code != 0 and self.interrupted is None:
            self.broken = _broken_reason(code)
            self.say(f"[bold red]the run is broken[/bold red] at step {self.k}: {self.broken}; stopping every process")
            return code
        # Drain fault reports still in flight.
        while self.interrupted is None and (ev := self._node().next_event(0.3)) is not None:
            self._handle(ev)
        return code

    def _token_gone(self, ev) -> None:
        """An agent's, the selector's or the recorder's liveliness went for good (held past
        liveliness_hold_s, and not with the bus) while its process still runs and no fault
        of ours stopped it: the router dropped its session (a stall past the lease, SIGSTOP or
        docker pause). The world went on without it (the agent counted dead, the selector's
        choice replaced by the fallback, the recorder's messages of the stall lost): not the
        numbers of an unstalled run, so the run is declared broken. (A stalled world is
        waited for by everyone and survived.)"""
        name = {"agent": f"agent-{ev.sat}", "selector": "selector", "recorder": "recorder"}.get(ev.role or "")
        if name is None or self.world_done or self._dropped is not None:
            return
        p = self.procs.get(name)
        # A process started less than a lease ago cannot have lost its session to the lease:
        # the token that went is its predecessor's (stopped, then restarted while its going
        # was held back: liveliness_hold_s, or bus_grace_s after a bus gap).
        em = self.sc.emulator
        young = time.monotonic() - self._started_at.get(name, 0.0) < max(BUS_LEASE_S, em.bus_grace_s + em.liveliness_hold_s)
        if p is not None and p.poll() is None and p.pid not in self._faulted and not young:
            self._dropped = (f"{name} (pid {p.pid}) lost its bus session at step {self.k} while its process ran, not by a fault "
                             "(stalled past the Zenoh lease? SIGSTOP, docker pause, starved of CPU): the run went on without it")

    def agent_gone(self) -> str | None:
        """Why the run cannot be finished: an agent process that ended before the world's
        last clock without this supervisor having killed or stopped it (a fault), or a role
        whose bus session was dropped while it ran (:meth:`_token_gone`); or None."""
        if self.world_done:
            return None
        if self._dropped is not None:
            return self._dropped
        if self.node is not None and not self.node.bus_up:
            return None  # no router: every role is leaving for that (the world's status says so: 3)
        for name, p in list(self.procs.items()):
            if name.startswith("agent-") and p.poll() is not None and p.pid not in self._faulted and p.returncode != EXIT_BUS_LOST:
                code = p.returncode
                if code == 0:
                    # An agent exits 0 only after the world's last clock (done): it saw the end
                    # first, and this supervisor's copy of that clock is still on its way or
                    # queued behind other events. Wait a bounded time for it (or for the world
                    # to exit) before calling the agent's end a surprise.
                    seen = self._clean_exit_at.setdefault(p.pid, time.monotonic())
                    if time.monotonic() - seen < _CLEAN_EXIT_GRACE_S:
                        continue
                how = f"was killed by {signal.Signals(-code).name}" if code is not None and code < 0 else f"exited with status {code}"
                return (f"{name} (pid {p.pid}) {how} at step {self.k} while the world still ran, not by a fault "
                        f"(see {self.out / 'logs' / (name + '.log')})")
        return None

    def stop(self) -> None:
        """Stop every process, in order: the roles that publish (world, selector, agents),
        then the recorder (it closes ``run.mcap``), then the router. After a normal end
        they are finishing by themselves; after an interrupt each gets a few seconds.
        Whatever is still there after its grace period is killed with its process group."""
        interrupted = self.interrupted is not None or self.broken is not None
        self.continue_stalled(everyone=True)  # a stopped process would not act on SIGTERM
        rec = self.procs.get("recorder")
        world = self.procs.get("world")
        if not interrupted and rec is not None and world is not None and world.poll() is not None:
            # The recorder finishes by itself after the world's last clock (once the bus
            # is quiet); give it that chance before anything is stopped.
            with contextlib.suppress(subprocess.TimeoutExpired):
                rec.wait(timeout=_RECORDER_GRACE_S)
        grace = _INTERRUPT_GRACE_S if interrupted else _ROLE_GRACE_S
        producers = ["world", "selector", *(n for n in self.procs if n.startswith("agent-"))]
        self._terminate(producers, grace)
        self._terminate(["live"], _INTERRUPT_GRACE_S)
        self._terminate(["recorder"], _RECORDER_GRACE_S)
        if self.node is not None:
            self.node.close()
            self.node = None
        self._terminate(self.router_names, _INTERRUPT_GRACE_S)
        if self._forkserver is not None:  # every agent it forked is stopped above
            self._forkserver.close()
            self._forkserver = None
        if self.keys_dir is not None:
            # A run's credentials live as long as the run.
            import shutil

            shutil.rmtree(self.keys_dir, ignore_errors=True)
        if self._gate_dir is not None:
            import shutil

            shutil.rmtree(self._gate_dir, ignore_errors=True)
        self._port_reservation.release()  # the routers are gone: their ports with them
        if self._lifeline is not None:
            for fd in self._lifeline:
                os.close(fd)
            self._lifeline = None

    def _terminate(self, names: list[str], grace: float) -> None:
        """SIGTERM to each named running process, then wait at most ``grace`` seconds in
        all; SIGKILL (to the process group) whoever is still running."""
        procs = [p for n in names if (p := self.procs.get(n)) is not None]
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                _kill_group(p, signal.SIGKILL)
                p.wait()


def _ended_early(t_stop_unix_s: float, f: Fault) -> bool:
    """Whether a stall is being ended before its time (``down_s`` after its SIGSTOP)."""
    return time.time() - t_stop_unix_s < float(opt(f, "down_s") or 0.0) - 0.05


#: Stalls a router fault waits for (the stalled role's token is held only liveliness_hold_s).
_SHORT_HOLD_STALLS = ("stall-agent", "stall-selector")


def _broken_reason(code: int) -> str:
    """Why the world ended before the run did, from its exit status."""
    if code == EXIT_BUS_LOST:
        return "bus lost: no Zenoh router reachable within emulator.bus_lost_after_s (see logs/world.log)"
    if code < 0:
        return f"the world died ({signal.Signals(-code).name})"
    return f"the world exited with status {code} (see logs/world.log)"


_WARM = "from swarmcore import kernels; kernels.warm_up(); from swarmrt.bus import fastcheck; fastcheck.warm_up()"


def _slug(name: str) -> str:
    s = "".join(c if c.isalnum() or c in "-_." else "-" for c in name)[:40]
    return s or "run"


def _kill_group(p: subprocess.Popen | ForkedAgent, sig: int) -> None:
    """Signal a running child's process group (each child leads its own session, so its
    group id is its pid). A child already reaped is left alone: its pid is free for reuse.
    A process on another host (swarm.cluster.swarm.RemoteProc) is signalled there."""
    if hasattr(p, "killpg"):
        p.killpg(sig)
        return
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(p.pid, sig)


def _readline(stream, timeout: float, cancelled=lambda: False) -> bytes | None:
    """One line from ``stream`` within ``timeout`` seconds (None if none came, or if
    ``cancelled()`` turned true meanwhile; checked every 0.2 s)."""
    out: list[bytes] = []
    t = threading.Thread(target=lambda: out.append(stream.readline()), daemon=True)
    t.start()
    deadline = time.monotonic() + timeout
    while t.is_alive() and not cancelled() and time.monotonic() < deadline:
        t.join(min(0.2, max(0.0, deadline - time.monotonic())))
    return out[0] if out else None
