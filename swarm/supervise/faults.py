"""``swarm fault``: inject a fault into a running swarm, local or under docker compose.

Local (``--run-dir``, or ``--connect`` + ``--run``): the command goes on the bus; the
executor (the supervisor of ``swarm run`` for processes, the world for cameras, the agent
for drops) acts and reports back. Compose (``--compose``): process and network faults are
carried out here with the docker CLI — kill, stop or restart a satellite's container,
disconnect it from the bus network (a partition) and reconnect it (heal), impair its
network with Linux traffic control (netem: delay, jitter, loss, rate; :mod:`swarm.supervise.netem`)
— and reported on the bus so they land in the recording; camera and drop faults go on the
bus as usual.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import zenoh

from swarm.supervise.netem import CLEAR, NO_QDISC, UNKNOWN_QDISC, netemd_args, show_script, tc_script
from swarmcore.scenario import NETWORK_FAULTS, PROCESS_FAULTS, ROUTER_FAULTS, SELECTOR_PROCESS_FAULTS, STALL_FAULTS
from swarmrt.bus.messages import SCHEMA_VERSION, Fault, Keys, MessageError, opt, replace, validate
from swarmrt.bus.session import BusConfig
from swarmrt.node import Node
from swarmrt.protocol import BusLost

__all__ = ["send_fault", "compose_containers", "netem_state", "netem_helper_name"]



def _target(run_dir, connect, run_id, compose) -> tuple[list[str], str, int, str | None]:
    """(endpoints, run id, swarm size, the fault CLI's credential file or None)."""
    if run_dir is not None:
        info_file = Path(run_dir) / "run.json"
        if not info_file.is_file():
            raise FileNotFoundError(f"{info_file}: not found (is `swarm run --out {run_dir}` running?)")
        info = json.loads(info_file.read_text())
        keys = info.get("keys")
        cred = str(Path(keys) / "cli.json") if keys else None
        return info.get("endpoints") or [info["endpoint"]], info["run"], int(info["n_sats"]), cred
    cred = str(Path(os.environ.get("SWARM_KEYS", "keys")) / "cli.json")
    cred = cred if Path(cred).is_file() else None
    if compose:
        ports = [os.environ.get("SWARM_BUS_PORT", "7447"), *([p] if (p := os.environ.get("SWARM_BUS_PORT2")) else [])]
        eps = connect.split(",") if connect else [f"tcp/127.0.0.1:{p}" for p in ports]
        return eps, run_id or os.environ.get("SWARM_RUN", "compose"), 10_000, cred
    if connect and run_id:
        return connect.split(","), run_id, 10_000, cred
    raise ValueError("give --run-dir, or --connect and --run, or --compose")


def _docker(*args: str, check: bool = True) -> str:
    exe = shutil.which("docker")
    if exe is None:
        raise RuntimeError("the docker CLI is not installed")
    p = subprocess.run([exe, *args], capture_output=True, text=True, timeout=120)
    if check and p.returncode != 0:
        raise RuntimeError(f"docker {' '.join(args)}: {p.stderr.strip() or p.stdout.strip()}")
    return p.stdout.strip()


def compose_containers(project: str | None = None) -> list[dict]:
    """Containers of the compose project (labels set by docker compose and docker-compose).

    Asks for the four fields it needs: ``{{json .}}`` makes the daemon compute every
    container's disk usage, which takes minutes on a busy machine.
    """
    flt = ["--filter", "label=com.docker.compose.service"]
    if project:
        flt += ["--filter", f"label=com.docker.compose.project={project}"]
    fmt = '{{.ID}}\t{{.State}}\t{{.Label "com.docker.compose.service"}}\t{{.Label "com.docker.compose.project"}}'
    out = _docker("ps", "-a", "--no-trunc", *flt, "--format", fmt)
    rows = []
    for line in out.splitlines():
        parts = line.split("\t")
        if len(parts) == 4:
            rows.append({"ID": parts[0], "State": parts[1], "service": parts[2], "project": parts[3]})
    return rows


def _agent_hosts(node: Node, want: int | None, timeout: float = 10.0) -> dict[int, str]:
    """Satellite id → host name (container id) from the agents' health reports, until
    satellite ``want`` has reported or ``timeout`` passes."""
    hosts: dict[int, str] = {}
    deadline = time.monotonic() + timeout
    while want not in hosts and time.monotonic() < deadline:
        ev = node.next_event(max(0.0, deadline - time.monotonic()))
        if ev is not None and ev.kind == "health" and ev.msg.host:
            hosts[ev.msg.sat] = ev.msg.host
    return hosts


def _compose_action(node: Node, cmd: Fault, project: str | None, network: str | None) -> str:
    cont = compose_containers(project)
    if cmd.action in ROUTER_FAULTS:
        # Router 0 is service "router", router 1 "router2" (compose.routers2.yaml).
        service = "router" if not opt(cmd, "target") else f"router{cmd.target + 1}"
        ids = [c["ID"] for c in cont if c["service"] == service]
        if not ids:
            raise RuntimeError(f"no container of service {service}")
        _docker("kill", ids[0])
        if cmd.action == "restart-router":
            down = float(opt(cmd, "down_s") or 0.0)
            if down > 0:
                time.sleep(down)  # the fault itself: the router stays down this long
            _docker("start", ids[0])
            return f"docker kill, then start {service} ({ids[0][:12]}) after {down:g} s"
        return f"docker kill {service} ({ids[0][:12]})"
    if cmd.action in STALL_FAULTS and cmd.action != "stall-agent":
        role = cmd.action.removeprefix("stall-")
        # Router 0 is service "router", router 1 "router2" (compose.routers2.yaml).
        service = role if role != "router" or not opt(cmd, "target") else f"router{cmd.target + 1}"
        ids = [c["ID"] for c in cont if c["service"] == service and c["State"] == "running"]
        if not ids:
            raise RuntimeError(f"no running container of service {service}")
        return _pause(ids[0], float(opt(cmd, "down_s") or 0.0), service)
    if cmd.action in SELECTOR_PROCESS_FAULTS:
        ids = [c["ID"] for c in cont if c["service"] == "selector"]
    elif cmd.action == "heal":
        # Off the bus, the agent cannot report: find the agent container that is not on
        # the bus network and whose log names the satellite.
        bus = network or _bus_network(project)
        ids = []
        for c in cont:
            if c["service"] not in ("agent", "remote_agent") or c["State"] != "running":
                continue
            nets = json.loads(_docker("inspect", "--format", "{{json .NetworkSettings.Networks}}", c["ID"])) or {}
            if bus in nets:
                continue
            logs = subprocess.run(["docker", "logs", "--tail", "300", c["ID"]], capture_output=True, text=True, timeout=60)
            if f" agent-{cmd.target} " in logs.stdout + logs.stderr:
                ids.append(c["ID"])
        if not ids:
            raise RuntimeError(f"no partitioned agent container runs satellite {cmd.target}")
    else:
        wait = 3.0 if cmd.action == "restart-agent" else 15.0  # a dead agent never reports
        host = _agent_hosts(node, cmd.target, wait).get(cmd.target)
        if host is None:
            # A dead agent reports nothing: pick a stopped agent container.
            dead = [c["ID"] for c in cont if c["service"] in ("agent", "remote_agent") and c["State"] != "running"]
            if cmd.action == "restart-agent" and dead:
                ids = dead[:1]
            else:
                raise RuntimeError(f"no running agent reports satellite {cmd.target}")
        else:
            ids = [c["ID"] for c in cont if c["ID"].startswith(host)]
            if not ids:
                raise RuntimeError(f"satellite {cmd.target}'s host {host} is not a container of this project")
    if not ids:
        raise RuntimeError(f"no container for {cmd.action}")
    cid = ids[0]
    if cmd.action in ("kill-agent", "kill-selector"):
        _docker("kill", cid)
    elif cmd.action == "stop-agent":
        _docker("stop", cid)
    elif cmd.action in ("restart-agent", "restart-selector"):
        _docker("restart", cid)
    elif cmd.action == "netem":
        return _netem(cid, cmd.netem, project)
    elif cmd.action == "stall-agent":
        return _pause(cid, float(opt(cmd, "down_s") or 0.0), f"satellite {cmd.target}'s agent")
    elif cmd.action in NETWORK_FAULTS:
        nets = json.loads(_docker("inspect", "--format", "{{json .NetworkSettings.Networks}}", cid)) or {}
        net = network or next((n for n in nets if n.endswith("_bus")), None)
        if cmd.action == "partition":
            if net is None:
                raise RuntimeError(f"container {cid[:12]} is on no bus network ({list(nets)})")
            _docker("network", "disconnect", net, cid)
        else:
            net = network or _bus_network(project)
            _docker("network", "connect", net, cid)
    return f"{cmd.action} on container {cid[:12]}"


def _pause(cid: str, down_s: float, what: str) -> str:
    """A stall under compose: ``docker pause`` (the cgroup freezer: every process of the
    container stops, its sockets stay), ``down_s`` wall seconds, ``docker unpause``."""
    t0 = time.monotonic()
    _docker("pause", cid)
    try:
        time.sleep(down_s)  # the fault itself: the container stays frozen this long
    finally:
        try:
            _docker("unpause", cid)
        except RuntimeError:  # once more: a container left frozen is worse than a late unpause
            time.sleep(1.0)
            _docker("unpause", cid)
    return f"docker pause {what} ({cid[:12]}), unpause after {time.monotonic() - t0:.2f} s"


def netem_helper_name(cid: str) -> str:
    """Name of the long-lived helper container of the netem fallback for container ``cid``."""
    return f"swarm-netem-{cid[:12]}"


def _in_namespace(cid: str, script: str, check: bool = True) -> subprocess.CompletedProcess:
    """Run ``sh -c SCRIPT`` in a short-lived helper container of ``cid``'s image that shares
    ``cid``'s network namespace and holds NET_ADMIN (the agent itself has no such right)."""
    image = _docker("inspect", "--format", "{{.Image}}", cid)
    p = subprocess.run(
        [shutil.which("docker") or "docker", "run", "--rm", "--network", f"container:{cid}", "--cap-add", "NET_ADMIN",
         "--entrypoint", "sh", image, "-c", script],
        capture_output=True, text=True, timeout=120,
    )
    if check and p.returncode != 0:
        raise RuntimeError(f"in container {cid[:12]}'s network namespace: {p.stderr.strip() or p.stdout.strip()}")
    return p


def netem_state(cid: str) -> str:
    """``eth0: qdisc ...`` lines (and the fallback's iptables rules) of container ``cid``."""
    return _in_namespace(cid, show_script()).stdout.strip()


def _netem(cid: str, netem: str | None, project: str | None) -> str:
    """Apply (or ``clear``) the impairment in container ``cid``'s network namespace and say
    how: the kernel's netem qdisc, else the :mod:`swarm.supervise.netemd` fallback in a long-lived
    helper container (labelled as an extra container of the compose project, so that
    ``docker compose down --remove-orphans`` removes it with the swarm)."""
    if netem is None:
        raise RuntimeError("netem: no arguments")
    helper = netem_helper_name(cid)
    # A previous fallback helper on this container: SIGTERM lets it remove its own rules.
    _docker("stop", "-t", "5", helper, check=False)  # no such container: a harmless error
    _docker("rm", "-f", helper, check=False)
    if netem == CLEAR:
        state = _in_namespace(cid, tc_script(CLEAR)).stdout.strip()
        return f"netem cleared on container {cid[:12]} ({state})".replace("\n", "; ")
    mech = os.environ.get("SWARM_NETEM_MECHANISM", "auto")
    if mech not in ("auto", "qdisc", "netemd"):
        raise RuntimeError(f"SWARM_NETEM_MECHANISM={mech!r}: use auto, qdisc or netemd")
    if mech != "netemd":
        p = _in_namespace(cid, tc_script(netem), check=False)
        if p.returncode == 0:
            return f"netem {netem} on container {cid[:12]} (kernel qdisc: {p.stdout.strip()})".replace("\n", "; ")
        if mech == "qdisc" or p.returncode != NO_QDISC or UNKNOWN_QDISC not in p.stderr:
            raise RuntimeError(f"tc netem in container {cid[:12]}: {p.stderr.strip() or p.stdout.strip()}")
    # This kernel has no netem qdisc: the same impairment from iptables, NFQUEUE and tbf.
    image = _docker("inspect", "--format", "{{.Image}}", cid)
    proj = project or json.loads(_docker("inspect", "--format", "{{json .Config.Labels}}", cid)).get("com.docker.compose.project", "")
    labels = ["--label", f"org.swarm-coloc.netem-of={cid}"]
    if proj:
        labels += ["--label", f"com.docker.compose.project={proj}", "--label", "com.docker.compose.service=netem",
                   "--label", "com.docker.compose.oneoff=False", "--label", "com.docker.compose.container-number=1"]
    _docker("run", "-d", "--name", helper, *labels, "--network", f"container:{cid}", "--cap-add", "NET_ADMIN",
            "--entrypoint", "python", image, "-m", "swarm.supervise.netemd", *netemd_args(netem))
    _wait_ready(helper, 60.0)
    state = netem_state(cid)
    return f"netem {netem} on container {cid[:12]} (no netem qdisc in this kernel: swarm.supervise.netemd in {helper}: {state})".replace("\n", "; ")


def _wait_ready(container: str, timeout: float) -> None:
    """Block until ``container`` prints READY (following its log), or fail with its log."""
    p = subprocess.Popen([shutil.which("docker") or "docker", "logs", "-f", container], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    assert p.stdout is not None  # stdout=PIPE
    timer = threading.Timer(timeout, p.kill)
    timer.start()
    lines = []
    try:
        for line in p.stdout:
            lines.append(line.rstrip())
            if line.strip() == "READY":
                return
    finally:
        timer.cancel()
        p.kill()
        p.wait()
    _docker("rm", "-f", container, check=False)
    raise RuntimeError(f"{container} did not become ready: {' | '.join(lines[-5:]) or 'no output'}")


def _bus_network(project: str | None) -> str:
    nets = _docker("network", "ls", "--format", "{{.Name}}").split()
    cands = [n for n in nets if n.endswith("_bus") and (project is None or n.startswith(project))]
    if not cands:
        raise RuntimeError("no *_bus network found")
    return cands[0]


def send_fault(*, run_dir=None, connect=None, run_id=None, compose=False, project=None, network=None, timeout: float = 30.0,
               credential: str | None = None, stamp: tuple[int, float] | None = None, **fields) -> str:
    """Send one fault command as the ``cli`` identity (``credential``, or the run's or
    ``$SWARM_KEYS``' cli.json) and wait for whoever carries it out to report. ``stamp``:
    the (step, t_s) to stamp the command with (a campaign that knows the step it sends it
    for); by default the step of the next clock heard."""
    endpoints, run, n, cred = _target(run_dir, connect, run_id, compose)
    cred = credential or cred
    if fields.get("action") in ROUTER_FAULTS and len(endpoints) > 1:
        # Reach the swarm through another router than the one the fault takes down (the
        # endpoints are in router order): a session on that one would lose the report it
        # puts after the kill, or find itself without a bus mid-command.
        r = int(fields.get("target") or 0)
        endpoints = [e for i, e in enumerate(endpoints) if i != r] + [e for i, e in enumerate(endpoints) if i == r]
    endpoint = ",".join(endpoints)
    timeout += float(fields.get("down_s") or 0.0)
    if not compose and fields.get("action") in NETWORK_FAULTS:
        raise ValueError(f"{fields['action']} needs --compose (local processes share one network)")
    try:
        # 15 s to reach a router: on a busy machine (load 20 on 2 cores, routers in containers)
        # a TLS session took longer than 5 s to open (a CI run failed "Timeout!" at 5 s); on a
        # quiet one it takes milliseconds.
        node = Node("cli", "fault", run, n, BusConfig(mode="client", connect=endpoints, connect_timeout_ms=15_000, credential_file=cred))
    except zenoh.ZError as exc:
        if cred is None:
            raise RuntimeError(f"cannot reach the swarm's bus at {endpoint}: {exc}") from None
        # A router with security off refuses a session that offers a credential.
        try:
            node = Node("cli", "fault", run, n, BusConfig(mode="client", connect=endpoints, connect_timeout_ms=5000))
        except zenoh.ZError:
            raise RuntimeError(f"cannot reach the swarm's bus at {endpoint} with the credential {cred} (nor without): {exc}") from None
        node.log.warning("the swarm's router admitted this session only without a credential: its security is off")
    keys = Keys(run)
    try:
        node.subscribe(keys.faults())
        node.subscribe(keys.clock())
        node.subscribe(keys.health())
        k, t = stamp if stamp is not None else (0, 0.0)
        if stamp is None:
            ev = node.next_event(5.0)  # learn the current step (to stamp the command)
            while ev is not None and ev.kind != "clock":
                ev = node.next_event(5.0)
            if ev is not None:
                k, t = ev.msg.k, ev.msg.t_s
        cmd = Fault(schema_version=SCHEMA_VERSION, run=run, sender="cli", k=k, t_s=t, phase="command", **fields)
        try:
            validate(cmd)
        except MessageError as exc:
            raise ValueError(str(exc)) from None
        if compose and cmd.action in PROCESS_FAULTS:
            node.put(keys.fault(), replace(cmd, detail="compose"))
            try:
                detail = _compose_action(node, cmd, project, network)
            except RuntimeError as exc:
                node.put(keys.fault_report("cli"), replace(cmd, phase="failed", sender="cli", detail=str(exc)[:200]))
                raise
            node.put(keys.fault_report("cli"), replace(cmd, phase="done", sender="cli", detail=detail))
            return f"{cmd.action} {cmd.target if cmd.HasField('target') else ''}: done ({detail})"
        if not compose and cmd.action in NETWORK_FAULTS:
            raise ValueError(f"{cmd.action} needs --compose (local processes share one network)")
        node.put(keys.fault(), cmd)
        deadline = time.monotonic() + timeout
        node.bus_lost_after_s = 10.0  # a router killed for good takes the report's way with it
        while time.monotonic() < deadline:
            try:
                ev = node.next_event(deadline - time.monotonic())
            except BusLost:
                return f"{cmd.action}: sent at step {k}; no router reachable since (the bus is gone: the run stops " \
                       "after emulator.bus_lost_after_s)"
            if ev is None:
                break
            if ev.kind == "fault" and ev.msg.phase in ("done", "failed") and ev.msg.action == cmd.action and opt(ev.msg, "target") == opt(cmd, "target"):
                return f"{cmd.action} {cmd.target if cmd.HasField('target') else ''}: {ev.msg.phase} by {ev.msg.sender} at step {ev.msg.k} {ev.msg.detail}".strip()
        return f"{cmd.action}: sent at step {k}; no executor reported back within {timeout:.0f} s"
    finally:
        node.close()
