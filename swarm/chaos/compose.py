"""A chaos campaign under docker compose (``swarm chaos --compose``).

The swarm is the one of ``docker compose up`` (one container per role, agents as replicas
that claim their satellites); every command of the schedule is sent as ``swarm fault
--compose`` sends it — Docker for processes and networks (kill, stop, restart, pause,
``tc netem``, network disconnect), the bus for cameras, drops and link faults — when the
world's clock reaches its step, watched from the host as the ``cli`` identity. Then
``docker compose down``, and the run folder (``run.mcap`` and ``summary.json`` from the
recorder, ``run.json`` and ``compose.log`` from here) is left for
:func:`swarm.chaos.campaign.check_run`.

Unlike a local campaign, whose world carries out each scheduled fault at the start of its
step and waits for it, these commands come from outside the swarm and land during their step
or a little after (the run is paced, ``emulator.lockstep_max_realtime_factor``, so that a step
is longer than a command's round trip); a campaign's numbers are therefore not reproducible
bit for bit, only its schedule.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import zenoh

from swarm.supervise.faults import send_fault
from swarm.supervise.launch import free_port
from swarmrt.bus.messages import Keys
from swarmrt.bus.session import BusConfig
from swarmrt.node import Node

__all__ = ["compose_command", "run_compose_campaign", "PACE"]

#: How long the campaign's own session waits for the compose router to listen.
ROUTER_UP_TIMEOUT_MS = 60_000

#: The pace of a compose campaign's lockstep run unless the scenario sets one: simulated
#: seconds per wall second at most. Real time: a command through Docker takes a second or
#: more (a netem helper container, several on a loaded machine), and the episodes last 2–6
#: steps.
PACE = 1.0


def compose_command() -> list[str]:
    """``docker compose`` (the plugin) or Debian's ``docker-compose``; RuntimeError if neither."""
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise RuntimeError("neither `docker compose` nor `docker-compose` is installed")


def _container_ids(project: str, service: str | None = None, running_only: bool = False) -> list[str]:
    args = ["docker", "ps", "-q", "--filter", f"label=com.docker.compose.project={project}"]
    if service:
        args += ["--filter", f"label=com.docker.compose.service={service}"]
    if not running_only:
        args.insert(2, "-a")
    p = subprocess.run(args, capture_output=True, text=True, timeout=60)
    return p.stdout.split()


def run_compose_campaign(root: Path, scenario: Path, sets: list[str], commands: list, n: int, steps: int, dt_s: float,
                         out: Path, log: Callable[[str], None] = print, progress: Callable[[int, int], None] | None = None,
                         timeout_s: float | None = None) -> int | None:
    """Run the compose swarm of checkout ``root`` on ``scenario`` (a file of its
    ``scenarios/``, which compose mounts) with ``sets``, sending each of ``commands``
    (:class:`swarm.chaos.campaign.Command`, in step order) at its step. Leaves the run in
    ``out/run``; returns the world container's exit status (None: it did not end)."""
    scen_dir = (root / "scenarios").resolve()
    scenario = Path(scenario).resolve()
    if scenario.parent != scen_dir:
        raise ValueError(f"{scenario}: under compose the scenario must be a file of {scen_dir} (compose mounts that folder)")
    compose = [*compose_command(), "-f", str(root / "compose.yaml")]
    project = f"swchaos{uuid.uuid4().hex[:8]}"
    run_id = f"chaos-{uuid.uuid4().hex[:6]}"
    run_dir, keys = out / "run", out / "keys"
    run_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    env = dict(os.environ, COMPOSE_PROJECT_NAME=project, SWARM_OUT=str(run_dir.resolve()), SWARM_SCENARIO=scenario.name,
               SWARM_N=str(n), SWARM_SET_EXTRA=" ".join(sets), SWARM_BUS_PORT=str(port), SWARM_TLS_PORT=str(free_port()),
               SWARM_KEYS=str(keys.resolve()), SWARM_RUN=run_id)

    def dc(*args: str, timeout: float = 600, check: bool = True) -> subprocess.CompletedProcess:
        p = subprocess.run([*compose, "-p", project, *args], cwd=root, env=env, capture_output=True, text=True, timeout=timeout)
        if check and p.returncode != 0:
            raise RuntimeError(f"docker compose {' '.join(args)} failed: {(p.stderr or p.stdout)[-2000:]}")
        return p

    endpoint = f"tcp/127.0.0.1:{port}"
    pending = list(commands)
    fired: list[dict] = []
    code: int | None = None
    containers = 0
    node: Node | None = None
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        log(f"compose project {project}: docker compose up (run {run_id}, {n} agents, bus on {endpoint})")
        dc("up", "-d")
        world = _container_ids(project, "world")
        if not world:
            raise RuntimeError("no world container came up")
        cred = keys / "cli.json"
        # `docker compose up -d` returns once the containers are started, not once the router
        # listens: on CI's loaded machine the default 10 s was once too short ("Unable to
        # connect ... Timeout!"). The compose tests' own observers wait up to 60 s as well.
        try:
            node = Node("cli", "chaos", run_id, n,
                        BusConfig(mode="client", connect=[endpoint], credential_file=str(cred),
                                  connect_timeout_ms=ROUTER_UP_TIMEOUT_MS),
                        announce=False)
        except zenoh.ZError as exc:
            raise RuntimeError(f"the compose router on {endpoint} did not accept the campaign's session within "
                               f"{ROUTER_UP_TIMEOUT_MS / 1e3:.0f} s of docker compose up: {exc}") from None
        node.subscribe(Keys(run_id).clock())
        k = -1
        while True:
            state = subprocess.run(["docker", "inspect", "-f", "{{.State.Running}}", world[0]], capture_output=True, text=True,
                                   timeout=60).stdout.strip()
            if state != "true":
                break
            if deadline is not None and time.monotonic() > deadline:
                log(f"timeout: stopping the campaign after {timeout_s:.0f} s")
                break
            ev = node.next_event(0.5)
            if ev is not None and ev.kind == "clock" and not ev.msg.done:
                k = max(k, int(ev.msg.k))
                if progress is not None:
                    progress(k + 1, steps)
            while pending and pending[0].at_step <= k:
                cmd = pending.pop(0)
                t0 = time.monotonic()
                try:
                    # Stamped with the step it is for, or the step it is late for: the reports say when it went out.
                    at = max(k, cmd.at_step)
                    result = send_fault(compose=True, project=project, connect=endpoint, run_id=run_id, credential=str(cred),
                                        stamp=(at, at * dt_s), **cmd.fields())
                except (RuntimeError, ValueError) as exc:
                    result = f"FAILED: {exc}"
                fired.append({"at_step": cmd.at_step, "sent_at_step": k, "command": cmd.fields(), "result": result,
                              "wall_s": round(time.monotonic() - t0, 2)})
                log(f"step {k}: {cmd.action} {cmd.fields().get('target', '')} -> {result}")
        # The world's exit status, if it ran and ended (a container that never started says 0).
        status = subprocess.run(["docker", "inspect", "-f", "{{.State.Status}} {{.State.ExitCode}}", world[0]],
                                capture_output=True, text=True, timeout=60).stdout.split()
        if len(status) == 2 and status[0] == "exited" and status[1].lstrip("-").isdigit():
            code = int(status[1])
            # The recorder writes summary.json after the world's last clock: wait for it to leave.
            rec = _container_ids(project, "recorder")
            if rec:
                subprocess.run(["docker", "wait", *rec], capture_output=True, text=True, timeout=300)
    finally:
        # Each step on its own: whatever fails, the project goes down and run.json says what is left.
        if node is not None:
            with contextlib.suppress(Exception):
                node.close()
        with contextlib.suppress(Exception):
            containers = len(_container_ids(project))
        with contextlib.suppress(Exception):
            (run_dir / "compose.log").write_text(dc("logs", "--no-color", "-t", check=False, timeout=300).stdout)
        with contextlib.suppress(Exception):
            dc("down", "-v", "--remove-orphans", "-t", "5", check=False, timeout=300)
        left: list[str]
        try:
            left = _container_ids(project)
        except Exception as exc:  # the invariant then fails, saying why
            left = [f"unknown: {exc}"]
        (run_dir / "run.json").write_text(json.dumps({
            "run": run_id, "compose_project": project, "containers": containers, "containers_left": left, "n_sats": n,
            "endpoints": [endpoint], "world_exit_code": code, "fired": fired}, indent=1) + "\n")
        shutil.rmtree(keys, ignore_errors=True)  # a run's credentials live as long as the run
    return code
