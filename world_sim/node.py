"""``world_sim``: owns truth and time; publishes each satellite's own sensors and camera
outputs, truth (for the recorder only), and the clock. A thin shell over
:mod:`swarmcore.world`: the same calls, in the same order, as :func:`swarmcore.sim.simulate`.

Lockstep step k: apply the faults due; advance the truth (k > 0); publish truth, clock,
sensors; take the selector's choice for k (or fall back when it is dead or late); publish
each live agent's camera outputs; wait until every live agent has published its estimate
for k (or the step timeout passes). Free-running mode paces the clock at
``realtime_factor`` × wall time instead of waiting.
"""

from __future__ import annotations

import time

import numpy as np

from swarm.bus.convert import detections, full_estimate_msg, images_msg, pairs_from_select, select_msg, sensors_msg, truth_msg
from swarm.bus.messages import CameraOutput, Claim, Clock, Fault, Select, replace
from swarm.node import Node
from swarmcore import graphs
from swarmcore.cameras import best_camera
from swarmcore.mekf import RelativeMeasurements
from swarmcore.scenario import Scenario
from swarmcore.sim import scenario_graph
from swarmcore.world import (
    absolute_measurements,
    initial_estimate,
    initial_truth,
    relative_measurements,
    relative_truth,
    step_truth,
    world_params,
)

AGENT_FAULTS = ("kill-agent", "restart-agent", "stop-agent")


class World(Node):
    def __init__(self, sc: Scenario, run: str, bus, expect_recorder: bool = True, expect_selector: bool | None = None):
        if (why := sc.vision.distributed_refusal()) is not None:
            raise SystemExit(f"world_sim: {why}")
        super().__init__("world", 0, run, sc.n_sats, bus, announce=False)
        self.vision = None
        if sc.vision.pipeline != "none":
            from swarmvision.pipeline import VisionSystem  # rendering only when asked for

            self.vision = VisionSystem(sc.vision, sc.n_sats, sc.spacecraft.half_size_m, sc.seed, sc.orbit.mean_motion_rad_s)
        self.sc = sc
        self.wp = world_params(sc)
        self.G = scenario_graph(sc)
        self.truth = initial_truth(sc)
        self._priors = {i: initial_estimate(sc, self.truth, i) for i in range(sc.n_sats)}
        self.expect_recorder = expect_recorder
        self.use_selector = sc.selection.strategy != "none" if expect_selector is None else expect_selector
        self.alive_agents: set[int] = set()
        self.ready: set[int] = set()  # agents with an estimate for the current step
        self.alive_roles: set[str] = set()
        self.camera_ok = np.ones((sc.n_sats, 6), dtype=bool)
        self.selections: dict[int, Select] = {}
        self.est_seen: dict[int, set[int]] = {}
        self.fault_done: list[Fault] = []
        self.k = 0
        self.fallback_active = False
        self.subscribe(self.keys.est(), shallow=True)  # who, which step, which phase: not the arrays
        self.subscribe(self.keys.health())
        self.subscribe(self.keys.select())
        self.subscribe(self.keys.fault())
        self.watch_liveliness()
        self._claims: dict[str, int] = {}
        self._claimed_at: dict[int, float] = {}
        self.started = False
        self.queryable(self.keys.init(), self._serve_prior)
        self.queryable(self.keys.claim(), self._serve_claim)
        self.announce()

    # -- queries ------------------------------------------------------------------
    def _serve_prior(self, key: str):
        i = int(key.rsplit("/", 1)[1])
        if not 0 <= i < self.n or self.started:
            return None  # once the run is under way, a (re)starting agent asks a peer
        return full_estimate_msg(self._priors[i], run=self.run, sender="world", own=i)

    def _serve_claim(self, key: str):
        """Give an agent started with ``--id auto`` a satellite: the lowest one with no
        live agent and no recent claim (so scaled or restarted containers need no ids)."""
        token = key.rsplit("/", 1)[1]
        now = time.monotonic()
        sat = self._claims.get(token)
        if sat is None:
            alive = set(self.alive_agents)
            free = [i for i in range(self.n) if i not in alive and now - self._claimed_at.get(i, -1e9) > 30.0]
            if not free:
                return None
            sat = free[0]
            self._claims[token] = sat
            self._claimed_at[sat] = now
        return Claim(run=self.run, sender="world", k=self.k, t_s=self.k * self.sc.dt_s, sat=sat, token=token, running=self.started)

    # -- events -------------------------------------------------------------------
    def pump(self, timeout: float) -> bool:
        ev = self.next_event(timeout)
        if ev is None:
            return False
        if ev.kind == "alive":
            if ev.role == "agent" and ev.sat is not None:
                if ev.alive:
                    self.alive_agents.add(ev.sat)
                else:
                    self.alive_agents.discard(ev.sat)
                    self.ready.discard(ev.sat)
                    self._claimed_at.pop(ev.sat, None)  # its satellite may be claimed again at once
            elif ev.role:
                (self.alive_roles.add if ev.alive else self.alive_roles.discard)(ev.role)
        elif ev.kind == "est":
            m = ev.msg
            self.est_seen.setdefault(m.k, set()).add(m.own)
            self.ready.add(m.own)
        elif ev.kind == "health":
            # An agent's health report follows its update: it has finished step k even
            # when its estimate was lost (the drop fault).
            self.est_seen.setdefault(ev.msg.k, set()).add(ev.msg.sat)
        elif ev.kind == "select":
            if ev.msg.sender != "world":
                self.selections[ev.msg.k] = ev.msg
        elif ev.kind == "fault":
            self._on_fault(ev.msg)
        return True

    def _on_fault(self, f: Fault) -> None:
        if f.phase != "command":
            self.fault_done.append(f)
            return
        if f.action == "camera" and f.target is not None and f.camera is not None:
            self.camera_ok[f.target, f.camera] = f.state == "on"
            self.put(self.keys.fault(), replace(f, phase="done", sender="world", k=self.k, t_s=self.k * self.sc.dt_s))
            self.log.info("camera %d of satellite %d %s", f.camera, f.target, f.state)

    def wait_for(self, cond, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self.pump(remaining)
        return True

    # -- the run -----------------------------------------------------------------
    def startup(self) -> None:
        em = self.sc.emulator
        need_roles = set()
        if self.expect_recorder:
            need_roles.add("recorder")
        if self.use_selector:
            need_roles.add("selector")
        ok = self.wait_for(
            lambda: len(self.ready) == self.n and need_roles <= self.alive_roles and self.alive_agents >= self.ready,
            em.startup_timeout_s,
        )
        if not ok:
            self.log.warning(
                "startup: ready agents %s, alive roles %s after %.0f s; starting anyway",
                sorted(self.ready),
                sorted(self.alive_roles),
                em.startup_timeout_s,
            )
        if self.use_selector:
            # The selector plans step 0 from agent 0's prior: give a live selector the
            # start-up allowance (a loaded machine starts processes slowly), not the step one.
            self.wait_for(lambda: 0 in self.selections or "selector" not in self.alive_roles, em.startup_timeout_s)

    def live(self) -> list[int]:
        return sorted(self.alive_agents & self.ready)

    def apply_scheduled_faults(self, k: int) -> None:
        em = self.sc.emulator
        for spec in [f for f in self.sc.faults if f.at_step == k]:
            cmd = Fault(
                run=self.run,
                sender="world",
                k=k,
                t_s=k * self.sc.dt_s,
                action=spec.action,
                phase="command",
                target=spec.target,
                camera=spec.camera,
                state=spec.state,
                rate=spec.rate,
                detail="scheduled",
            )
            self.log.info("step %d: fault %s target=%s", k, spec.action, spec.target)
            self.put(self.keys.fault(), cmd)
            if spec.action == "camera":
                self._on_fault(cmd)
            elif spec.action in ("kill-agent", "stop-agent"):
                self.wait_for(lambda t=spec.target: t not in self.alive_agents, em.step_timeout_s)
            elif spec.action == "restart-agent":
                self.ready.discard(spec.target)
                self.wait_for(lambda t=spec.target: t in self.alive_agents and t in self.ready, em.startup_timeout_s)
            elif spec.action == "kill-selector":
                self.wait_for(lambda: "selector" not in self.alive_roles, em.step_timeout_s)
            elif spec.action == "restart-selector":
                self.wait_for(lambda: "selector" in self.alive_roles, em.startup_timeout_s)
            elif spec.action == "drop":
                self.wait_for(
                    lambda t=spec.target: any(f.action == "drop" and f.target == t and f.k >= k for f in self.fault_done)
                    or t not in self.alive_agents,
                    em.step_timeout_s,
                )

    def selection(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if not self.use_selector:
            return graphs.edges(self.G)
        em = self.sc.emulator
        if "selector" in self.alive_roles:
            self.wait_for(lambda: k in self.selections or "selector" not in self.alive_roles, em.select_timeout_s)
        sel = self.selections.pop(k, None)
        if sel is not None:
            if self.fallback_active:
                self.log.info("step %d: selector is back", k)
            self.fallback_active = False
            return pairs_from_select(sel)
        # Fallback: a strategy that needs no state, chosen by the world itself.
        from swarmcore.selection import select_for_scenario

        if not self.fallback_active:
            self.log.warning("step %d: no selection from the selector; falling back to %s", k, self.sc.selection.fallback)
        self.fallback_active = True
        fb = self.sc.model_copy(update={"selection": self.sc.selection.model_copy(update={"strategy": self.sc.selection.fallback})})
        cam_ok = self.camera_ok.copy()
        for i in range(self.n):
            if i not in self.live():
                cam_ok[i] = False
        t0 = time.perf_counter()
        obs, tgt = select_for_scenario(fb, k, self.G, None, None, cam_ok)
        self.put(
            self.keys.select(),
            select_msg(
                obs,
                tgt,
                run=self.run,
                sender="world",
                k=k,
                t_s=k * self.sc.dt_s,
                strategy=self.sc.selection.fallback,
                fallback=True,
                select_ms=(time.perf_counter() - t0) * 1e3,
            ),
        )
        return obs, tgt

    def publish_images(self, k: int, t: float, live: list[int], obs: np.ndarray, tgt: np.ndarray) -> None:
        """Render what each live observer's scheduled cameras see and send it to that agent
        (an empty message when it has nothing scheduled: it waits for one every step)."""
        keep = np.isin(obs, live)
        obs, tgt = obs[keep], tgt[keep]
        views = self.vision.render_views(k, t, self.truth.q_BI, self.truth.r_H, (obs, tgt), camera_ok=self.camera_ok)
        for i in live:
            mine = [v for (o, _c), v in sorted(views.items()) if o == i]
            self.put(self.keys.img(i), images_msg(mine, run=self.run, k=k, t_s=t, sat=i, targets=tgt[obs == i]))

    def close(self) -> None:
        if self.vision is not None:
            self.vision.close()
        super().close()

    def run_steps(self, progress=None) -> None:
        sc, em = self.sc, self.sc.emulator
        self.startup()
        self.started = True
        t_wall0 = time.monotonic()
        gyro = None
        for k in range(sc.steps):
            if self.stop.is_set():
                break
            self.k = k
            self.apply_scheduled_faults(k)
            if k > 0:
                self.truth, gyro = step_truth(self.wp, self.truth)
            tr = self.truth
            t = tr.t
            self.put(self.keys.truth(), truth_msg(tr, run=self.run, k=k))
            # Drain pending events so the live set reflects deaths up to now.
            while self.pump(0):
                pass
            live = self.live()
            self.put(self.keys.clock(), Clock(run=self.run, sender="world", k=k, t_s=t, live_agents=live, mode=em.time_mode))
            absm = absolute_measurements(self.wp, tr)
            for i in live:
                self.put(
                    self.keys.sensors(i),
                    sensors_msg(
                        run=self.run,
                        k=k,
                        t_s=t,
                        sat=i,
                        gyro=None if gyro is None else gyro[i],
                        absm=absm[i] if self.G[i, i] else None,
                        sigma_star=self.wp.star_sigma,
                        sigma_gps=self.wp.gps_sigma,
                    ),
                )
            obs, tgt = self.selection(k)
            if self.vision is not None:
                self.publish_images(k, t, live, obs, tgt)
                rel = RelativeMeasurements.empty()  # agents measure from the images
            else:
                rel = relative_measurements(self.wp, tr, obs, tgt)
            # The camera that truly sees the target must be healthy to produce anything.
            cams = np.zeros(0, dtype=int)
            if len(rel):
                _q, r_true = relative_truth(self.wp.mean_motion, t, tr.q_BI, tr.r_H, rel.observer, rel.target)
                cams = best_camera(r_true)
            for i in live:
                rows = np.flatnonzero((rel.observer == i) & self.camera_ok[i, cams]) if len(rel) else np.zeros(0, dtype=int)
                sub = rel.subset(rows)
                off = [int(c) for c in np.flatnonzero(~self.camera_ok[i])]
                self.put(
                    self.keys.cam(i),
                    CameraOutput(run=self.run, sender="world", k=k, t_s=t, sat=i, detections=detections(sub, cams[rows]), cameras_off=off),
                )
            if em.time_mode == "lockstep":
                ok = self.wait_for(
                    lambda: all(i in self.est_seen.get(k, set()) or i not in self.alive_agents for i in live),
                    em.step_timeout_s,
                )
                if not ok:
                    missing = [i for i in live if i not in self.est_seen.get(k, set())]
                    self.log.warning("step %d: no estimate from %s within %.1f s", k, missing, em.step_timeout_s)
                if em.lockstep_max_realtime_factor:
                    deadline = t_wall0 + (k + 1) * sc.dt_s / em.lockstep_max_realtime_factor
                    while (rem := deadline - time.monotonic()) > 0:
                        self.pump(rem)
            else:
                deadline = t_wall0 + (k + 1) * sc.dt_s / em.realtime_factor
                while (rem := deadline - time.monotonic()) > 0:
                    self.pump(rem)
            self.est_seen.pop(k - 2, None)
            if progress is not None:
                progress(k + 1, sc.steps)
        self.put(
            self.keys.clock(),
            Clock(run=self.run, sender="world", k=self.k, t_s=self.truth.t, live_agents=self.live(), mode=em.time_mode, done=True),
        )
        self.log.info("run finished at step %d (t = %.1f s), %d malformed messages dropped", self.k, self.truth.t, self.malformed)
