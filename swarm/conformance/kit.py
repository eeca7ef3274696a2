"""Run the conformance cases: a whole local swarm per case (``swarm run``'s supervisor,
:class:`swarm.supervise.launch.LocalSwarm`), the agent under test flying satellite i as
``emulator.agent_commands`` says (so it is started, faulted and restarted exactly as in
``swarm run --agent i=COMMAND``), the Python ``sat_agent`` flying the others.

Faults are the emulator's own: scheduled in the case's scenario (camera, drop,
kill/restart/stop-agent, kill/restart-router), carried out by the world, the supervisor
or the agent as in any run. The kit itself only (a) watches the bus as the read-only
``observer``, (b) puts the malformed and forged messages of :mod:`.inputs` with the
world's credential, (c) queries ``cov/<i>`` with the selector's, and (d) SIGKILLs the
world (the case "world gone", as ``tests/test_router_faults.py`` does). Every wait is on an
event (a clock on the bus, a process ending, a report) with a bound, never a sleep.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import signal
import subprocess
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from swarm.conformance.evidence import Evidence, load_evidence
from swarm.supervise.launch import LocalSwarm
from swarmcore.graphs import radio_peers, scenario_graph
from swarmcore.scenario import Scenario
from swarmrt.bus.messages import Keys, MessageError
from swarmrt.bus.receive import receive
from swarmrt.bus.session import BusConfig
from swarmrt.estimators import check_estimator

__all__ = ["Kit", "CaseRun", "CASES", "CASE_NAMES", "kit_scenario", "DEFAULT_SCENARIO"]

#: The kit's swarm when none is given: 4 satellites, 20 s of 1 s steps, lockstep, the
#: full-swarm estimator; paced at 5x wall time so the kit can act mid-run.
DEFAULT_SCENARIO = {
    "name": "conformance",
    "seed": 3,
    "n_sats": 4,
    "duration_s": 20.0,
    "emulator": {"step_timeout_s": 5.0, "startup_timeout_s": 60.0, "shutdown_linger_s": 10.0, "lockstep_max_realtime_factor": 5.0},
}
MIN_STEPS = 15  # the fault cases need room: camera off, drops, kill and restart


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def kit_scenario(sc: Scenario | None, sat: int, command: str) -> Scenario:
    """The swarm every case starts from: ``sc`` (or :data:`DEFAULT_SCENARIO`) in lockstep
    with the ideal radio, no faults, synthetic cameras, satellite ``sat`` flown by
    ``command``. ValueError if it cannot serve."""
    doc = sc.model_dump(mode="json") if sc is not None else Scenario.model_validate(DEFAULT_SCENARIO).model_dump(mode="json")
    if doc["vision"]["pipeline"] != "none":
        raise ValueError("the kit runs synthetic cameras (sat/<i>/cam): give a scenario with vision.pipeline: none")
    em = doc["emulator"]
    doc = _merge(doc, {"emulator": {"time_mode": "lockstep", "agent_commands": {sat: command},
                                    "lockstep_max_realtime_factor": em.get("lockstep_max_realtime_factor") or 5.0},
                       "links": {"enabled": False}})
    doc["faults"] = []
    out = Scenario.model_validate(doc)
    if not 0 <= sat < out.n_sats:
        raise ValueError(f"--id {sat}: not a satellite of this {out.n_sats}-satellite swarm")
    if out.n_sats < 3:
        raise ValueError("the kit needs at least 3 satellites (a peer to fault, a peer to rejoin from)")
    if out.steps < MIN_STEPS:
        raise ValueError(f"the kit needs at least {MIN_STEPS} steps (duration_s / dt_s ≥ {MIN_STEPS - 1}); this scenario has {out.steps}")
    return out


def with_changes(sc: Scenario, changes: dict, faults: list[dict] | None = None) -> Scenario:
    doc = _merge(sc.model_dump(mode="json"), changes)
    if faults is not None:
        doc["faults"] = faults
    return Scenario.model_validate(doc)


# -- the swarm of one case ------------------------------------------------------------------
class KitSwarm(LocalSwarm):
    """``swarm run``'s supervisor, keeping every process it ever started for satellite i
    (a restart replaces it in ``procs``) and when each ended (wall clock)."""

    def __init__(self, *a, watch: str, **kw):
        super().__init__(*a, **kw)
        self.watch = watch
        self.watched: list[subprocess.Popen] = []
        self.ended_at: dict[int, float] = {}

    def _spawn(self, name, args, env_extra=None):
        p = super()._spawn(name, args, env_extra)
        if name == self.watch:
            self.watched.append(p)
            threading.Thread(target=self._await, args=(p,), daemon=True).start()
        return p

    def _await(self, p: subprocess.Popen) -> None:
        p.wait()
        self.ended_at[p.pid] = time.time()


class Probe:
    """A session of the kit on the case's bus as one of the run's identities."""

    def __init__(self, sw: LocalSwarm, identity: str):
        cred = str(sw.keys_dir / f"{identity}.json") if sw.keys_dir is not None else None
        self.session = zenoh.open(BusConfig(mode="client", connect=list(sw.endpoints), credential_file=cred).zenoh_config())
        self._subs: list = []

    def subscribe(self, key: str, cb) -> None:
        self._subs.append(self.session.declare_subscriber(key, cb))

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        with contextlib.suppress(Exception):
            self.session.close()


class StepWatch:
    """The world's clock as the observer hears it (valid clocks of the world only)."""

    def __init__(self, probe: Probe, run: str, alive: Callable[[], bool]):
        self.k = -1
        self.done = False
        self.run = run
        self.alive = alive
        self.cv = threading.Condition()
        probe.subscribe(Keys(run).clock(), self._cb)

    def _cb(self, s) -> None:
        try:
            m = receive(str(s.key_expr), s.payload.to_bytes(), self.run, expect="clock").msg
        except MessageError:
            return
        with self.cv:
            if m.done:
                self.done = True
            else:
                self.k = max(self.k, int(m.k))
            self.cv.notify_all()

    def wait(self, k: int, timeout: float) -> bool:
        """Until the run is at step ``k`` (True), or it ended, the world died or
        ``timeout`` passed (False). Wakes every 0.2 s to look at the world's process."""
        deadline = time.monotonic() + timeout
        with self.cv:
            while self.k < k and not self.done and self.alive():
                rem = deadline - time.monotonic()
                if rem <= 0:
                    break
                self.cv.wait(min(0.2, rem))
            return self.k >= k


@dataclass
class CaseRun:
    name: str
    out: Path
    run: str = ""
    sc: Scenario | None = None
    ev: Evidence | None = None
    world_code: int | None = None
    agent_code: int | None = None  # the last process of satellite i
    agent_codes: list[int | None] = field(default_factory=list)  # every process of satellite i, in order
    left_by_itself_s: float | None = None  # after the world ended, when the agent left (None: it did not)
    agent_ended_at: float | None = None  # wall clock (s) the last process of satellite i ended
    survivors: list[int] = field(default_factory=list)  # processes left in satellite i's process groups
    router_faults: list[dict] = field(default_factory=list)
    notes: dict = field(default_factory=dict)
    wall_s: float = 0.0
    error: str | None = None

    def summary(self) -> dict:
        return {"run_dir": str(self.out), "run": self.run, "wall_s": round(self.wall_s, 1), "world_exit": self.world_code,
                "agent_exits": self.agent_codes, "left_by_itself_s": self.left_by_itself_s,
                "survivors": self.survivors, "error": self.error,
                "notes": {k: v for k, v in self.notes.items() if isinstance(v, (int, float, str, bool, list, dict, type(None)))}}


@dataclass
class Case:
    name: str
    what: str
    scenario: Callable[[Kit], Scenario]
    driver: Callable[[Kit, KitSwarm, dict], None] | None = None
    leave_s: Callable[[Scenario], float] = lambda sc: sc.emulator.shutdown_linger_s + 10.0


# -- the kit ---------------------------------------------------------------------------------
class Kit:
    def __init__(self, command: str, sat: int, base: Scenario, out: Path, claims: set[str], log=print):
        if not shlex.split(command):
            raise ValueError("--agent: an empty command")
        self.command = command
        self.sat = sat
        self.base = base
        self.n = base.n_sats
        self.K = base.steps
        self.peer = (sat + 1) % base.n_sats
        self.out = Path(out)
        self.claims = claims
        self.say = log
        self.runs: dict[str, CaseRun] = {}
        self.name = f"agent-{sat}"
        K = self.K
        # The steps the fault cases act at (a 21-step run: 4, 9, 6, 12; 5, 8; 6).
        self.cam_off = max(2, K // 5)
        self.cam_on = self.cam_off + max(3, K // 4)
        self.drop_peer = self.cam_off + 2
        self.drop_self = min(K - 4, max(self.cam_on + 2, K // 2 + 2))
        self.kill_at = max(3, K // 4)
        self.restart_at = self.kill_at + 3
        self.mid = max(3, K // 4) + 1  # router faults, stop-agent, the world killed

    def run_case(self, case: Case) -> CaseRun:
        sc = case.scenario(self)
        out = self.out / case.name
        cr = CaseRun(case.name, out, sc=sc)
        sw = KitSwarm(sc, out, run_id=f"cf-{case.name}-{uuid.uuid4().hex[:6]}", log=lambda s: None, watch=self.name)
        cr.run = sw.run
        th = None
        t0 = time.monotonic()
        try:
            with sw.handling_signals():
                try:
                    sw.start()
                    if case.driver is not None:
                        th = threading.Thread(target=self._drive, args=(case, sw, cr.notes), daemon=True)
                        th.start()
                    cr.world_code = sw.run_to_end(timeout=sc.emulator.startup_timeout_s * 3 + sc.steps * sc.emulator.step_timeout_s)
                    if sw.interrupted is None:
                        t_end = time.monotonic()
                        p = sw.procs.get(self.name)
                        if p is not None:
                            with contextlib.suppress(subprocess.TimeoutExpired):
                                p.wait(timeout=case.leave_s(sc))
                                cr.left_by_itself_s = time.monotonic() - t_end
                except Exception as exc:  # the swarm did not start (a role's log says why)
                    if sw.interrupted is None:
                        cr.error = f"{type(exc).__name__}: {exc}"
                finally:
                    sw.stop()
        finally:
            if th is not None:
                th.join(30)
            cr.survivors = _survivors(sw.watched)
            cr.agent_codes = [p.returncode for p in sw.watched]
            cr.agent_code = cr.agent_codes[-1] if cr.agent_codes else None
            if sw.watched:
                cr.agent_ended_at = sw.ended_at.get(sw.watched[-1].pid)
            cr.router_faults = list(sw.router_faults)
            cr.wall_s = time.monotonic() - t0
        if sw.interrupted is not None:
            raise KeyboardInterrupt(f"interrupted by {sw.interrupted.name}")
        cr.ev = load_evidence(out / "run.mcap", sw.run, self.sat, self.n)
        self.runs[case.name] = cr
        return cr

    def _drive(self, case: Case, sw: KitSwarm, notes: dict) -> None:
        try:
            assert case.driver is not None
            case.driver(self, sw, notes)
        except Exception as exc:  # recorded: the verdicts say the kit could not do its part
            notes["driver_error"] = f"{type(exc).__name__}: {exc}"


def _survivors(procs: list[subprocess.Popen]) -> list[int]:
    """Processes still in the process groups of ``procs`` (each leads its own: the
    supervisor starts every child in a new session); SIGKILLed here, after noting them."""
    left: list[int] = []
    for g in {p.pid for p in procs}:
        try:
            os.killpg(g, 0)  # any process left in the group?
        except (ProcessLookupError, PermissionError):
            continue
        members = _group_members(g)
        if not members and Path("/proc").is_dir():
            continue  # only zombies, about to be reaped
        left.extend(members or [-g])
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(g, signal.SIGKILL)
    return sorted(left)


def _group_members(pgid: int) -> list[int]:
    """The pids of process group ``pgid`` (Linux /proc; empty elsewhere)."""
    out = []
    with contextlib.suppress(OSError):
        for d in os.listdir("/proc"):
            if d.isdigit():
                with contextlib.suppress(OSError, ValueError, IndexError):
                    stat = Path(f"/proc/{d}/stat").read_text()
                    fields = stat.rsplit(")", 1)[1].split()
                    if int(fields[2]) == pgid and fields[0] != "Z":
                        out.append(int(d))
    return out


# -- the drivers (what the kit does during a run) --------------------------------------------
def _world_alive(sw: LocalSwarm) -> Callable[[], bool]:
    return lambda: (p := sw.procs.get("world")) is not None and p.poll() is None


def drive_clean(kit: Kit, sw: KitSwarm, notes: dict) -> None:
    """Ask agent i for cov/<i> (as the selector does) once the run is at step 3."""
    if "warm-rejoin" not in kit.claims:
        return
    obs, sel = Probe(sw, "observer"), Probe(sw, "selector")
    try:
        steps = StepWatch(obs, sw.run, _world_alive(sw))
        if not steps.wait(3, sw.sc.emulator.startup_timeout_s * 2):
            notes["cov"] = {"error": f"the run never reached step 3 (last clock seen: {steps.k})"}
            return
        key = Keys(sw.run).cov(kit.sat)
        k_at = steps.k
        t0 = time.monotonic()
        got: dict = {"asked_at_k": k_at}
        try:
            for reply in sel.session.get(key, timeout=sw.sc.emulator.step_timeout_s):
                if reply.ok is None:
                    continue
                rkey = str(reply.ok.key_expr)
                try:
                    m = receive(rkey, reply.ok.payload.to_bytes(), sw.run, n_sats=kit.n, expect="full_est").msg
                    got.update(k=int(m.k), own=int(m.own), sender=m.sender, run=m.run, rows=len(m.q_BI) // 4,
                               q=list(m.q_BI), r=list(m.r_H_m), ms=round((time.monotonic() - t0) * 1e3, 1))
                except MessageError as exc:
                    got["error"] = f"a reply that fails the checks: {exc}"
                break
            else:
                got["error"] = f"no reply within {sw.sc.emulator.step_timeout_s:g} s"
        except zenoh.ZError as exc:
            got["error"] = f"query failed: {exc}"
        notes["cov"] = got
    finally:
        obs.close()
        sel.close()


def drive_inputs(kit: Kit, sw: KitSwarm, notes: dict) -> None:
    """At step 2: the malformed and forged messages of :mod:`.inputs` on agent i's inputs;
    then wait (bounded) until its health report counts them."""
    from swarm.conformance.inputs import injections, self_check

    obs, world = Probe(sw, "observer"), Probe(sw, "world")
    counted = {"malformed": 0, "key_mismatch": 0}
    cv = threading.Condition()

    def on_health(s) -> None:
        try:
            h = receive(str(s.key_expr), s.payload.to_bytes(), sw.run, n_sats=kit.n, expect="health").msg
        except MessageError:
            return
        with cv:
            counted.update(malformed=int(h.malformed), key_mismatch=int(h.key_mismatch))
            cv.notify_all()

    try:
        steps = StepWatch(obs, sw.run, _world_alive(sw))
        obs.subscribe(Keys(sw.run).health(kit.sat), on_health)
        if not steps.wait(2, sw.sc.emulator.startup_timeout_s * 2):
            notes["inject"] = {"error": f"the run never reached step 2 (last clock seen: {steps.k})"}
            return
        k = steps.k
        hears = radio_peers(scenario_graph(sw.sc), check_estimator(sw.sc).radio)  # its radio: batches or batches/<sat>
        items = injections(sw.run, kit.sat, kit.n, k, Keys(sw.run).batches(None if hears is None else kit.sat))
        self_check(items, kit.n)
        for it in items:
            world.session.put(it.key, it.payload)
        notes["inject"] = {"at_k": k, "malformed": sum(not i.forged for i in items), "forged": sum(i.forged for i in items),
                           "what": [f"{i.name} on {i.key.split('/', 2)[2]}" for i in items]}
        need = len(items)
        deadline = time.monotonic() + 10.0
        with cv:
            while counted["malformed"] < need and steps.alive() and not steps.done:
                rem = deadline - time.monotonic()
                if rem <= 0:
                    break
                cv.wait(min(0.2, rem))
        notes["inject"]["health_after"] = dict(counted)
    finally:
        obs.close()
        world.close()


def drive_world_gone(kit: Kit, sw: KitSwarm, notes: dict) -> None:
    """SIGKILL the world once the run is at the middle step."""
    obs = Probe(sw, "observer")
    try:
        steps = StepWatch(obs, sw.run, _world_alive(sw))
        if not steps.wait(kit.mid, sw.sc.emulator.startup_timeout_s * 2):
            notes["world_killed"] = {"error": f"the run never reached step {kit.mid} (last clock seen: {steps.k})"}
            return
        w = sw.procs["world"]
        w.send_signal(signal.SIGKILL)
        notes["world_killed"] = {"at_k": steps.k, "t": time.time(), "pid": w.pid}
    finally:
        obs.close()


# -- the cases -------------------------------------------------------------------------------
def _faults_scenario(kit: Kit) -> Scenario:
    i, j = kit.sat, kit.peer
    faults = [{"at_step": kit.cam_off, "action": "camera", "target": i, "camera": c, "state": "off"} for c in range(6)]
    faults += [{"at_step": kit.cam_on, "action": "camera", "target": i, "camera": c, "state": "on"} for c in range(6)]
    faults += [{"at_step": kit.drop_peer, "action": "drop", "target": j, "rate": 1.0},
               {"at_step": kit.drop_self, "action": "drop", "target": i, "rate": 0.5}]
    return with_changes(kit.base, {}, faults)


def _links_scenario(kit: Kit) -> Scenario:
    """Late batches replayed when the agent claims it (C22), else dropped: C10 asks an agent
    to apply or drop a late batch as ``filter.late`` says, and replaying is optional."""
    dt = kit.base.dt_s
    late = "replay" if "late-replay" in kit.claims else "drop"
    return with_changes(kit.base, {
        "links": {"enabled": True, "latency": {"fixed_s": 1.5 * dt, "speed_of_light": False},
                  "loss": {"model": "bernoulli", "rate": 0.25}},
        "filter": {"late": late, "history_s": 6 * dt},
    })


CASES: tuple[Case, ...] = (
    Case("clean", "a normal run: the reference numbers; cov/<i> asked at step 3 (claim warm-rejoin)",
         lambda kit: kit.base, drive_clean),
    Case("inputs", "malformed and forged messages on the agent's inputs at step 2", lambda kit: kit.base, drive_inputs),
    Case("faults", "all its cameras off then on; a peer drops every message; then it drops half of its own",
         _faults_scenario),
    Case("links", "links: 1.5-step latency, 25 % loss: batches come late or never", _links_scenario),
    Case("restart", "SIGKILL, then a restart with SWARM_RESTART=1",
         lambda kit: with_changes(kit.base, {}, [{"at_step": kit.kill_at, "action": "kill-agent", "target": kit.sat},
                                                 {"at_step": kit.restart_at, "action": "restart-agent", "target": kit.sat}])),
    Case("router", "the router killed and restarted 1 s later",
         lambda kit: with_changes(kit.base, {}, [{"at_step": kit.mid, "action": "restart-router", "target": 0, "down_s": 1.0}])),
    Case("bus-lost", "the router killed for good (emulator.bus_lost_after_s: 4)",
         lambda kit: with_changes(kit.base, {"emulator": {"bus_lost_after_s": 4.0, "bus_grace_s": 2.0}},
                                  [{"at_step": kit.mid, "action": "kill-router", "target": 0}]),
         leave_s=lambda sc: 20.0),
    Case("world-gone", "the world SIGKILLed mid-run (emulator.bus_lost_after_s: 4)",
         lambda kit: with_changes(kit.base, {"emulator": {"bus_lost_after_s": 4.0}}), drive_world_gone,
         leave_s=lambda sc: 20.0),
    Case("sigterm", "stop-agent: SIGTERM mid-run",
         lambda kit: with_changes(kit.base, {}, [{"at_step": kit.mid, "action": "stop-agent", "target": kit.sat}])),
)
CASE_NAMES = tuple(c.name for c in CASES)
