"""``sat_agent``: one satellite's measurement pipeline and full-swarm filter.

Consumes only its own sensors (``sat/<i>/sensors``), its own camera outputs
(``sat/<i>/cam``) and the relative-measurement batches every agent broadcasts; never the
truth. Each step k: turn the camera outputs into relative measurements (covariance
attached) and broadcast them as one batch (empty included); wait for the batch of every
live peer (or the step timeout); run :func:`swarmcore.sim.filter_step` — the same call the
in-process simulator makes — and publish the estimate. Serves its full estimate on
``cov/<i>`` for the selector and for restarting peers.
"""

from __future__ import annotations

import time

import numpy as np

from swarm.bus.convert import (
    absolute_from_sensors,
    batch_msg,
    estimate_from_full,
    estimate_msg,
    full_estimate_msg,
    gyro_from_sensors,
    relative_from_batches,
    views_from_images,
)
from swarm.bus.messages import Fault, Health, codec_cpu_ms, replace
from swarm.node import Node
from swarmcore import kernels
from swarmcore.mekf import RelativeMeasurements, predict, reframe
from swarmcore.scenario import Scenario
from swarmcore.sim import filter_step
from swarmcore.streams import stream
from swarmcore.world import filter_params, relative_noise_cov


class Agent(Node):
    def __init__(self, sc: Scenario, sat: int, run: str, bus, restart: bool = False):
        if not 0 <= sat < sc.n_sats:
            raise SystemExit(f"sat_agent: --id {sat} is not a satellite of this {sc.n_sats}-satellite swarm")
        super().__init__("agent", sat, run, sc.n_sats, bus, announce=False)
        self.sc = sc
        self.i = sat
        self.params = filter_params(sc, sat)
        self.restart = restart
        self.est = None
        self.camera_ok = np.ones(6, dtype=bool)
        self.drop_rate = 0.0
        self.clocks: dict[int, object] = {}
        self.sensors: dict[int, object] = {}
        self.cams: dict[int, object] = {}
        self.batches: dict[int, dict[int, object]] = {}
        self.peers_alive: set[int] = set()
        self.peer_est_steps: dict[int, int] = {}
        self.batches_missing = 0
        self.batches_late = 0
        self.last_step = -1  # the last step this agent has processed (updated at)
        self.done = False
        self.subscribe(self.keys.clock())
        self.subscribe(self.keys.sensors(sat))
        self.subscribe(self.keys.cam(sat))
        self.subscribe(self.keys.meas())
        self.subscribe(self.keys.fault())
        # Peers' progress comes from their health reports, not est/* (40 × 20 KB a step at n = 40).
        self.subscribe(self.keys.health())
        self.watch_liveliness(self.keys.alive("agent"))
        self.finished: dict[int, dict[int, float]] = {}  # step → {peer: when we learnt it is past it}
        self.queryable(self.keys.cov(sat), self._serve_cov)
        self.vision = None
        self.imgs: dict[int, object] = {}
        if sc.vision.pipeline != "none":
            from swarmvision.pipeline import VisionSystem  # the pose pipelines; rendering stays in the world

            self.vision = VisionSystem(sc.vision, sc.n_sats, sc.spacecraft.half_size_m, sc.seed, sc.orbit.mean_motion_rad_s)
            self.subscribe(self.keys.img(sat))
            # Build the pipeline now (tag detector; stereo: the model cloud), not on step 0.
            _ = self.vision.stereo if sc.vision.pipeline == "stereo" else self.vision.mono
        kernels.warm_up()  # compile before the world counts on our step times
        self.announce()

    # -- queries and events -----------------------------------------------------
    def _serve_cov(self, key: str):
        est = self.est  # an immutable value: safe to read from Zenoh's thread
        if est is None:
            return None
        return full_estimate_msg(est, run=self.run, sender=self.name, own=self.i)

    def pump(self, timeout: float) -> bool:
        ev = self.next_event(timeout)
        if ev is None:
            return False
        k = getattr(ev.msg, "k", None)
        cur = self.last_step
        if ev.kind == "alive":
            if ev.sat is not None and ev.sat != self.i:
                (self.peers_alive.add if ev.alive else self.peers_alive.discard)(ev.sat)
        elif ev.kind == "clock":
            if ev.msg.done:
                self.done = True
            else:
                self.clocks[k] = ev.msg
        elif ev.kind == "sensors":
            self.sensors[k] = ev.msg
        elif ev.kind == "cam":
            self.cams[k] = ev.msg
        elif ev.kind == "img":
            self.imgs[k] = ev.msg
        elif ev.kind == "meas":
            if ev.msg.observer != self.i:
                if k <= cur:
                    self.batches_late += 1
                else:
                    self.batches.setdefault(k, {})[ev.msg.observer] = ev.msg
        elif ev.kind == "est":
            if ev.msg.own != self.i and ev.msg.phase == "posterior":
                self.peer_est_steps[ev.msg.own] = max(k, self.peer_est_steps.get(ev.msg.own, -1))
                self.finished.setdefault(k, {}).setdefault(ev.msg.own, time.monotonic())
        elif ev.kind == "health":
            # A peer reports after its update, so its batch for k went out before; each
            # subscription has its own thread, so the batch may still be a moment behind.
            # Past a short grace it is lost, and waiting longer is pointless.
            if ev.msg.sat != self.i:
                self.finished.setdefault(k, {}).setdefault(ev.msg.sat, time.monotonic())
                self.peer_est_steps[ev.msg.sat] = max(k, self.peer_est_steps.get(ev.msg.sat, -1))
        elif ev.kind == "fault":
            self._on_fault(ev.msg)
        return True

    def _on_fault(self, f: Fault) -> None:
        if f.phase != "command" or f.target != self.i:
            return
        if f.action == "camera" and f.camera is not None:
            self.camera_ok[f.camera] = f.state == "on"
            self.log.info("camera %d %s", f.camera, f.state)
        elif f.action == "drop":
            self.drop_rate = float(f.rate or 0.0)
            self.log.info("dropping %.0f%% of outgoing messages", 100 * self.drop_rate)
            k = -1 if self.est is None else self.est.step
            self.put(self.keys.fault(), replace(f, phase="done", sender=self.name, k=max(k, 0)))

    def wait_for(self, cond, timeout: float, wake=None) -> bool:
        """Pump events until ``cond()`` holds or ``timeout`` passes. ``wake()`` may name an
        earlier instant (monotonic) at which ``cond`` can change without a new event."""
        deadline = time.monotonic() + timeout
        while not cond():
            if self.stop.is_set():
                return False
            now = time.monotonic()
            remaining = deadline - now
            if remaining <= 0:
                return False
            w = wake() if wake is not None else None
            self.pump(remaining if w is None else max(0.0, min(remaining, w - now)))
        return True

    # -- start ------------------------------------------------------------------
    def initialise(self) -> None:
        em = self.sc.emulator
        if not self.restart:
            deadline = time.monotonic() + em.startup_timeout_s
            while self.est is None and time.monotonic() < deadline and not self.stop.is_set():
                msg = self.query(self.keys.init(self.i), "full_est", timeout=2.0)
                if msg is not None:
                    self.est = estimate_from_full(msg, self.n)
                    break
                while self.pump(0):
                    pass
                if self.peer_est_steps:
                    # The world serves priors only before the run starts: we are late.
                    self.log.info("the run is under way; initialising from a peer")
                    self.restart = True
                    break
            if self.est is None and not self.restart:
                raise SystemExit(f"agent {self.i}: no prior from the world within {em.startup_timeout_s} s")
            if self.est is not None:
                self.log.info("initialised from the world's prior at step %d", self.est.step)
        if self.restart:
            # A restarted agent borrows a live peer's latest full estimate.
            self.wait_for(lambda: bool(self.peer_est_steps), em.startup_timeout_s)
            while self.est is None and not self.stop.is_set():
                if not self.peer_est_steps:
                    raise SystemExit(f"agent {self.i}: no live peer to initialise from")
                peer = max(self.peer_est_steps, key=lambda j: (self.peer_est_steps[j], -j))
                msg = self.query(self.keys.cov(peer), "full_est", timeout=5.0)
                if msg is None:
                    self.peer_est_steps.pop(peer, None)
                    continue
                s = self.sc.filter.initial_sigma
                self.est = reframe(estimate_from_full(msg, self.n), msg.own, self.i, s.bias_rad_s, s.rate_rad_s)
                self.last_step = self.est.step
                self.log.info("restarted from agent %d's estimate at step %d", msg.own, self.est.step)
        self.put(self.keys.est(self.i), estimate_msg(self.est, run=self.run, sender=self.name, own=self.i, phase="prior"))

    # -- steps --------------------------------------------------------------------
    def _own_batch(self, k: int) -> RelativeMeasurements:
        cam = self.cams.get(k)
        dets = [d for d in (cam.detections if cam else []) if self.camera_ok[d.camera]]
        if not dets:
            return RelativeMeasurements.empty(), np.zeros(0, dtype=int)
        r = np.array([d.r_ij_Bi_m for d in dets], dtype=float)
        rel = RelativeMeasurements(
            observer=np.full(len(dets), self.i, dtype=int),
            target=np.array([d.target for d in dets], dtype=int),
            q_BjBi=np.array([d.q_BjBi for d in dets], dtype=float),
            r_ij_Bi=r,
            R_Bi=relative_noise_cov(self.sc.sensors.relative, r),
        )
        return rel, np.array([d.camera for d in dets], dtype=int)

    def _catch_up(self, k: int) -> None:
        """Predict (only) across steps this agent missed (free-running mode, a stall)."""
        while self.est.step < k - 1:
            s_prev = self.sensors.pop(self.est.step + 1, None)
            self.est = filter_step(self.est, self.params, None if s_prev is None else _gyro(s_prev), None, RelativeMeasurements.empty())[0]

    def _vision_batch(self, k: int):
        """Our relative measurements of step k from our own images (and their cameras)."""
        msg = self.imgs.pop(k, None)
        if msg is None or not msg.views:
            return RelativeMeasurements.empty(), np.zeros(0, dtype=int)
        views = [v for v in views_from_images(msg) if v.camera >= 6 or self.camera_ok[v.camera]]
        rel = self.vision.measure(self.i, views, self.est, k, targets=msg.targets)
        rep = self.vision.last_reports.get(self.i)
        if rep is not None and rep.missed:
            self.log.debug("step %d: no pose of %s from the images", k, rep.missed)
        if self.sc.vision.pipeline == "stereo":
            cams = 6 + rel.target
        else:
            cams = np.array([int(rep.details.get(int(j), {}).get("camera", 0)) for j in rel.target], dtype=int)
        return rel, cams

    def _dropped(self, k: int, what: int) -> bool:
        if self.drop_rate <= 0:
            return False
        return bool(stream(self.sc.seed, "drop", self.i, k, what).random() < self.drop_rate)

    def step(self, k: int) -> None:
        em = self.sc.emulator
        clock = self.clocks.pop(k)
        t = clock.t_s
        timeout = em.step_timeout_s if em.time_mode == "lockstep" else 0.8 * self.sc.dt_s / em.realtime_factor
        if self.i in clock.live_agents:  # otherwise the world sends us nothing this step
            self.wait_for(lambda: k in self.sensors and k in self.cams and (self.vision is None or k in self.imgs), timeout)
        sens = self.sensors.pop(k, None)
        t0 = time.perf_counter()
        if self.vision is not None:
            # The image pipelines start from this step's prediction (tag ambiguity, ICP
            # seed), so predict first, as the in-process simulator does.
            self._catch_up(k)
            if k > 0 and self.est.step < k:
                self.est = predict(self.est, self.params, None if sens is None else _gyro(sens))
            rel_own, cams = self._vision_batch(k)
        else:
            rel_own, cams = self._own_batch(k)
        ms_own = (time.perf_counter() - t0) * 1e3
        self.cams.pop(k, None)
        if not self._dropped(k, 0):
            self.put(self.keys.meas(self.i), batch_msg(rel_own, cams, run=self.run, sender=self.name, k=k, t_s=t, observer=self.i))
        expected = [j for j in clock.live_agents if j != self.i]
        grace = self.sc.emulator.lost_batch_grace_s

        def lost(j):
            t_done = self.finished.get(k, {}).get(j)
            return t_done is not None and time.monotonic() - t_done >= grace

        def next_wake():
            pending = [self.finished.get(k, {}).get(j) for j in expected if j not in self.batches.get(k, {})]
            times = [t + grace for t in pending if t is not None]
            return min(times) if times else None

        self.wait_for(
            lambda: all(j in self.batches.get(k, {}) or j not in self.peers_alive or lost(j) for j in expected),
            timeout,
            wake=next_wake,
        )
        got = self.batches.pop(k, {})
        missing = [j for j in expected if j not in got]
        self.batches_missing += len(missing)
        batches = [got[j] for j in sorted(got)]
        rel = RelativeMeasurements.concat([rel_own, relative_from_batches(batches)])
        t0, c0 = time.perf_counter(), time.thread_time()
        self._catch_up(k)
        gyro = None if sens is None else _gyro(sens)
        absm = None if sens is None else absolute_from_sensors(sens)
        self.est, report = filter_step(self.est, self.params, gyro, absm, rel, self.sc.filter.mode, propagate=k > 0 and self.est.step < k)
        self.last_step = k
        ms = (time.perf_counter() - t0) * 1e3 + (ms_own if self.vision is not None else 0.0)
        cpu_ms = (time.thread_time() - c0) * 1e3
        msg = estimate_msg(
            self.est,
            run=self.run,
            sender=self.name,
            own=self.i,
            report=report,
            step_ms=ms,
            step_cpu_ms=cpu_ms,
            codec_cpu_ms=codec_cpu_ms(),
            batches_used=sorted(got),
            batches_missing=missing,
            batches_late=self.batches_late,
        )
        if not self._dropped(k, 1):
            self.put(self.keys.est(self.i), msg)
        self.put(
            self.keys.health(self.i),
            Health(
                run=self.run,
                sender=self.name,
                k=k,
                t_s=t,
                sat=self.i,
                camera_ok=[bool(c) for c in self.camera_ok],
                malformed=self.malformed,
                batches_missing=self.batches_missing,
                batches_late=self.batches_late,
                drop_rate=self.drop_rate,
                host=_HOST,
            ),
        )
        for store in (self.sensors, self.cams, self.imgs, self.batches, self.clocks, self.finished):
            for old in [s for s in store if s < k - 2]:
                store.pop(old, None)

    def run_loop(self) -> None:
        self.initialise()
        while not self.stop.is_set() and not self.done:
            nxt = sorted(s for s in self.clocks if s > self.last_step)
            if nxt:
                # The newest step: in lockstep there is only ever one ahead, unless this
                # agent fell behind (cut off the bus, stalled); then it predicts across the
                # gap and rejoins the swarm's present rather than replaying stale steps.
                k = nxt[-1]
                for s in [s for s in self.clocks if s < k]:
                    self.clocks.pop(s, None)
                self.step(k)
                continue
            self.pump(0.5)
        self.log.info("done at step %d; %d malformed, %d missing, %d late batches", self.est.step, self.malformed, self.batches_missing, self.batches_late)



_HOST = __import__("socket").gethostname()


def claim_id(sc: Scenario, run: str, bus, timeout: float | None = None) -> tuple[int, bool]:
    """Ask the world for a satellite id (``--id auto``); returns (id, run already under way)."""
    import uuid

    from swarm.node import Node

    node = Node("claimant", uuid.uuid4().hex[:12], run, sc.n_sats, bus)
    token = str(node.ident)
    deadline = time.monotonic() + (timeout or sc.emulator.startup_timeout_s)
    try:
        while time.monotonic() < deadline:
            msg = node.query(node.keys.claim(token), "claim", timeout=2.0)
            if msg is not None:
                node.log.info("world gave satellite %d (run under way: %s)", msg.sat, msg.running)
                return msg.sat, msg.running
        raise SystemExit(f"no satellite id from the world within {timeout or sc.emulator.startup_timeout_s:.0f} s")
    finally:
        node.close()


def _gyro(sens):
    return gyro_from_sensors(sens)
