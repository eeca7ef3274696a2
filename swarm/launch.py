"""``swarm run``: a whole swarm as local processes on loopback, supervised.

Starts a Zenoh router, the recorder, N agents, the selector (when the scenario selects)
and the world, each its own process (``python -m ...``) connected to the router. The
supervisor (this process) executes the process-level faults — kill, stop or restart an
agent or the selector — whether they come from the scenario (via the world) or from
``swarm fault`` at any time, and reports each on the bus so it lands in the recording.
When the world finishes, every process is stopped cleanly and ``summary.json`` is
computed from the recording.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import yaml

from swarmcore.scenario import Scenario

from .bus.messages import Fault, Keys, as_dict, replace
from .bus.session import BusConfig
from .node import Node

__all__ = ["LocalSwarm", "free_port"]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalSwarm:
    """The processes of one run; :meth:`run` drives it to the end."""

    def __init__(self, sc: Scenario, out: Path, run_id: str | None = None, python: str = sys.executable, log=print):
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
        self.procs: dict[str, subprocess.Popen] = {}
        self.endpoint = None
        self.bus = None
        self.node: Node | None = None
        self.faults: list[dict] = []
        self.k = 0
        self._lock = threading.Lock()

    # -- processes -----------------------------------------------------------------
    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        # A fresh log per run; a restarted process appends to its predecessor's.
        logf = open(self.out / "logs" / f"{name}.log", "ab" if name in self.procs else "wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        p = subprocess.Popen([self.python, "-m", *args], stdout=logf, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        logf.close()
        with self._lock:
            self.procs[name] = p
        return p

    def _role_args(self) -> list[str]:
        return ["--scenario", str(self.scenario_file), "--run", self.run, *self.bus.as_args()]

    def spawn_agent(self, i: int, restart: bool = False) -> None:
        self._spawn(f"agent-{i}", ["sat_agent", "--id", str(i), *(["--restart"] if restart else []), *self._role_args()])

    def spawn_selector(self) -> None:
        self._spawn("selector", ["selector", *self._role_args()])

    def start(self) -> None:
        # Compile numba's kernels once, before the agents start: on a fresh checkout (or
        # after a kernel changed) every agent would otherwise compile the same kernels at
        # the same moment (~2.6 s of CPU each: 100 s at n = 40); afterwards each loads them
        # from the cache. Runs while the router and the recorder start.
        # (Short-lived; if it fails, each agent compiles for itself as before.)
        warm = subprocess.Popen([self.python, "-c", _WARM], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{port}"
        router = subprocess.Popen(
            [self.python, "-m", "swarm.router", "--listen", self.endpoint],
            stdout=subprocess.PIPE,
            stderr=open(self.out / "logs" / "router.log", "ab"),
            start_new_session=True,
        )
        self.procs["router"] = router
        line = _readline(router.stdout, timeout=30.0)
        if not line or b"READY" not in line:
            raise RuntimeError(f"the Zenoh router did not start (see {self.out / 'logs' / 'router.log'})")
        self.bus = BusConfig(mode="client", connect=[self.endpoint])
        self.node = Node("supervisor", 0, self.run, self.sc.n_sats, self.bus)
        self.node.subscribe(self.keys.fault())
        self.node.subscribe(self.keys.clock())
        self.node.watch_liveliness()
        self._spawn(
            "recorder",
            [
                "swarm.recorder",
                "--run",
                self.run,
                "--out",
                str(self.out / "run.mcap"),
                "--scenario",
                str(self.scenario_file),
                "--flush-every-s",
                str(self.sc.emulator.flush_every_s),
                *self.bus.as_args(),
            ],
        )
        self._wait_alive("recorder", 60.0)
        try:
            warm.wait(timeout=300)
        except subprocess.TimeoutExpired:
            warm.kill()
        for i in range(self.sc.n_sats):
            self.spawn_agent(i)
        if self.sc.selection.strategy != "none":
            self.spawn_selector()
        self._spawn("world", ["world_sim", *self._role_args()])
        self._write_run_json()

    def _write_run_json(self) -> None:
        info = {
            "run": self.run,
            "endpoint": self.endpoint,
            "n_sats": self.sc.n_sats,
            "pids": {k: p.pid for k, p in self.procs.items()},
            "scenario": str(self.scenario_file),
            "recording": str(self.out / "run.mcap"),
        }
        (self.out / "run.json").write_text(json.dumps(info, indent=2) + "\n")

    def _wait_alive(self, role: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ev = self.node.next_event(max(0.0, deadline - time.monotonic()))
            if ev is not None:
                self._handle(ev)
                if ev.kind == "alive" and ev.role == role and ev.alive:
                    return
        raise RuntimeError(f"{role} did not come up within {timeout:.0f} s (see {self.out / 'logs'})")

    # -- faults ------------------------------------------------------------------------
    def _report(self, f: Fault, phase: str, detail: str) -> None:
        done = replace(f, phase=phase, sender="supervisor", k=self.k, t_s=self.k * self.sc.dt_s, detail=detail)
        self.node.put(self.keys.fault(), done)

    def _handle(self, ev) -> None:
        if ev.kind == "clock":
            self.k = ev.msg.k
        elif ev.kind == "fault" and ev.msg.phase == "command":
            self.execute(ev.msg)
        elif ev.kind == "fault":
            self.faults.append(as_dict(ev.msg, exclude=("schema_version", "run")))

    def execute(self, f: Fault) -> None:
        name = f"agent-{f.target}" if f.action in ("kill-agent", "restart-agent", "stop-agent") else "selector"
        p = self.procs.get(name)
        running = p is not None and p.poll() is None
        if f.action in ("kill-agent", "kill-selector"):
            if running:
                p.kill()  # SIGKILL: no goodbye, the liveliness token just vanishes
                p.wait()
                self._report(f, "done", f"SIGKILL pid {p.pid}")
            else:
                self._report(f, "failed", f"{name} is not running")
        elif f.action == "stop-agent":
            if running:
                p.terminate()
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
                self._report(f, "done", f"SIGTERM pid {p.pid}")
            else:
                self._report(f, "failed", f"{name} is not running")
        elif f.action in ("restart-agent", "restart-selector"):
            if running:
                p.kill()
                p.wait()
            if f.action == "restart-agent":
                self.spawn_agent(f.target, restart=True)
            else:
                self.spawn_selector()
            self._write_run_json()
            self._report(f, "done", f"started pid {self.procs[name].pid}")

    # -- the run ---------------------------------------------------------------------
    def run_to_end(self, progress=None, timeout: float | None = None) -> int:
        world = self.procs["world"]
        deadline = None if timeout is None else time.monotonic() + timeout
        while world.poll() is None:
            if deadline is not None and time.monotonic() > deadline:
                self.say(f"timeout: stopping the run after {timeout:.0f} s")
                world.terminate()
                break
            ev = self.node.next_event(0.2)
            if ev is not None:
                self._handle(ev)
                if ev.kind == "clock" and progress is not None:
                    progress(ev.msg.k + 1, self.sc.steps)
        # Drain fault reports still in flight.
        while (ev := self.node.next_event(0.3)) is not None:
            self._handle(ev)
        return world.wait()

    def stop(self) -> None:
        # The recorder finishes by itself after the world's last clock (once the bus is
        # quiet); give it that chance before anything is stopped.
        rec = self.procs.get("recorder")
        world = self.procs.get("world")
        if rec is not None and world is not None and world.poll() is not None:
            try:
                rec.wait(timeout=60)
            except subprocess.TimeoutExpired:
                pass
        order = [n for n in self.procs if n.startswith("agent-")] + ["selector", "world", "recorder"]
        for name in order:
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name in order:
            p = self.procs.get(name)
            if p is None:
                continue
            try:
                p.wait(timeout=60 if name == "recorder" else 15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if self.node is not None:
            self.node.close()
            self.node = None
        router = self.procs.get("router")
        if router is not None and router.poll() is None:
            router.terminate()
            try:
                router.wait(timeout=10)
            except subprocess.TimeoutExpired:
                router.kill()


_WARM = "from swarmcore import kernels; kernels.warm_up(); from swarm.bus import fastcheck; fastcheck.warm_up()"


def _slug(name: str) -> str:
    s = "".join(c if c.isalnum() or c in "-_." else "-" for c in name)[:40]
    return s or "run"


def _readline(stream, timeout: float) -> bytes | None:
    out: list[bytes] = []
    t = threading.Thread(target=lambda: out.append(stream.readline()), daemon=True)
    t.start()
    t.join(timeout)
    return out[0] if out else None
