"""docker compose for real: a swarm of containers, faults from the CLI, a second site.

Needs the image (``make image``; these tests build it when missing, which takes minutes
the first time). Marked ``docker``: ``pytest -m docker`` runs them alone.
"""

import json
import os
import shutil
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.docker, pytest.mark.integration]


def _compose_cmd() -> list[str]:
    if shutil.which("docker") is None:
        pytest.skip("no docker CLI on this machine")
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    pytest.skip("neither `docker compose` nor `docker-compose` is installed")


@pytest.fixture(scope="module")
def image():
    if subprocess.run(["docker", "info"], capture_output=True).returncode != 0:
        pytest.skip("the docker daemon is not running")
    p = subprocess.run([str(ROOT / "scripts" / "docker-build.sh")], capture_output=True, text=True, timeout=3600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return "swarm-coloc:latest"


class Compose:
    def __init__(self, out: Path, env: dict, files=("compose.yaml",)):
        from swarm.launch import free_port
        from swarm.security import make_keys

        self.cmd = _compose_cmd()
        self.project = f"swt{uuid.uuid4().hex[:8]}"
        self.files = [a for f in files for a in ("-f", str(ROOT / f))]
        # The swarm's credentials, as `swarm keys` makes them (TLS for router, localhost, 127.0.0.1).
        self.keys = make_keys(out.parent / "keys", 16, tls_hosts=["router", "localhost", "127.0.0.1"])
        env = {"SWARM_TLS_PORT": str(free_port()), **env}
        self.env = dict(os.environ, SWARM_OUT=str(out), COMPOSE_PROJECT_NAME=self.project, SWARM_KEYS=str(self.keys), **env)
        self.out = out
        out.mkdir(parents=True, exist_ok=True)

    def __call__(self, *args, timeout=900, check=True):
        p = subprocess.run([*self.cmd, *self.files, "-p", self.project, *args], cwd=ROOT, env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and p.returncode != 0:
            raise AssertionError(f"{' '.join(args)}: {p.stdout[-3000:]}\n{p.stderr[-3000:]}")
        return p

    def down(self):
        self("down", "-v", "--remove-orphans", "-t", "5", check=False, timeout=300)


def _summary(out):
    return json.loads((out / "summary.json").read_text())


def _sim(n, sets):
    from swarm.models import measurement_model
    from swarm.scenario_files import load_scenario
    from swarmcore.sim import simulate

    sc = load_scenario(ROOT / "scenarios" / "demo.yaml", [f"n_sats={n}", *sets])
    return simulate(sc, measurement_model(sc)).summary()


def test_compose_up_runs_the_default_scenario_to_the_end(image, tmp_path):
    """...with every role on its own credential, and forgeries mid-run (tests/forgery.py:
    a stranger, agent 3's and the recorder's credentials) changing nothing."""
    from forgery import check_forgeries, forge

    from swarm.launch import free_port
    from swarm.scenario_files import load_scenario

    port = str(free_port())
    sets = "duration_s=20 emulator.lockstep_max_realtime_factor=2"
    c = Compose(tmp_path / "out", {"SWARM_N": "4", "SWARM_SET_EXTRA": sets, "SWARM_BUS_PORT": port})
    done: dict = {}
    try:
        c("up", "-d", timeout=900)
        forge(f"tcp/127.0.0.1:{port}", "compose", c.keys, done, from_step=2)
        rid = c("ps", "-q", "recorder").stdout.split()
        r = subprocess.run(["docker", "wait", *rid], capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr
    finally:
        (tmp_path / "compose.log").write_text(c("logs", "--no-color", "-t", check=False).stdout)
        c.down()
    s = _summary(c.out)
    check_forgeries(done, s, load_scenario(ROOT / "scenarios" / "demo.yaml", ["n_sats=4", *sets.split()]), "compose")
    assert s["n_sats"] == 4 and s["steps"] == 21
    # The recording holds the run, not just bytes: truth and every agent's posterior at
    # every step, one measurement batch per satellite and step.
    from swarm.recording import load_recording

    rec = load_recording(c.out / "run.mcap", 4, 21)
    assert np.isfinite(rec.t).all() and rec.alive.all()
    # (+ 1 batch: the forgeries' control, agent 3's own batch at a step no run reaches)
    assert rec.counts["truth"] == 21 and rec.counts["meas"] == 4 * 21 + 1 and rec.counts["sensors"] == 4 * 21, rec.counts
    ref = _sim(4, sets.split())
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate"):
        assert s[key] == ref[key], f"{key}: containers and in-process differ"


def _fault(c: Compose, *args):
    import time as _t

    t0 = _t.monotonic()
    p = subprocess.run(
        [sys.executable, "-m", "swarm.cli", "fault", "--compose", "--project", c.project, *args],
        cwd=ROOT,
        env=dict(os.environ, SWARM_BUS_PORT=c.env["SWARM_BUS_PORT"], SWARM_KEYS=c.env["SWARM_KEYS"]),
        capture_output=True,
        text=True,
        timeout=300,
    )
    print(f"fault {args}: {_t.monotonic() - t0:.1f} s: {p.stdout.strip()} {p.stderr.strip()[-300:]}", flush=True)
    assert p.returncode == 0 and "done" in p.stdout, p.stdout + p.stderr
    return p.stdout


def _wait_step(c: Compose, k: int, timeout=300):
    """Block until the world has reached step k (watching the bus from the host)."""
    import zenoh

    from swarm.bus.messages import Clock
    from swarm.bus.session import BusConfig

    seen = threading.Event()
    cfg = BusConfig(mode="client", connect=[f"tcp/127.0.0.1:{c.env['SWARM_BUS_PORT']}"], connect_timeout_ms=60_000,
                    credential_file=str(c.keys / "observer.json"))
    with zenoh.open(cfg.zenoh_config()) as s:
        sub = s.declare_subscriber("swarm/compose/clock", lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= k and seen.set())
        ok = seen.wait(timeout)
        sub.undeclare()
    assert ok, f"the swarm never reached step {k}"


@pytest.mark.slow
def test_container_faults_kill_restart_camera_partition(image, tmp_path):
    from swarm.launch import free_port
    from swarm.recording import load_recording
    from swarmcore.scenario import Scenario

    port = str(free_port())
    n, dur = 4, 300
    sets = f"duration_s={dur} emulator.lockstep_max_realtime_factor=3 emulator.step_timeout_s=15"
    c = Compose(tmp_path / "out", {"SWARM_N": str(n), "SWARM_SET_EXTRA": sets, "SWARM_BUS_PORT": port})
    log = []
    try:
        c("up", "-d", timeout=600)
        _wait_step(c, 10)
        log.append(_fault(c, "kill-agent", "2"))
        _wait_step(c, 35)
        log.append(_fault(c, "restart-agent", "2"))
        _wait_step(c, 55)
        log.append(_fault(c, "camera", "1", "0", "off"))
        _wait_step(c, 70)
        log.append(_fault(c, "partition", "3"))
        _wait_step(c, 95)
        log.append(_fault(c, "heal", "3"))
        # The run ends by itself: wait for the recorder to write the summary and leave.
        rid = c("ps", "-q", "recorder").stdout.split()
        r = subprocess.run(["docker", "wait", *rid], capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr
    finally:
        (tmp_path / "compose.log").write_text(c("logs", "--no-color", "-t", check=False).stdout)
        c.down()
    sc = Scenario(n_sats=n, duration_s=dur)
    rec = load_recording(c.out / "run.mcap", n, sc.steps)
    s = _summary(c.out)
    done = {f["action"]: f["k"] for f in s["faults"] if f["phase"] == "done"}
    assert set(done) >= {"kill-agent", "restart-agent", "camera", "partition", "heal"}, (s["faults"], log)
    from swarm_harness import within_3sigma_fraction

    # Survivors keep estimating the killed satellite within 3σ while it is dead.
    k0, k1 = done["kill-agent"], done["restart-agent"]
    dead = slice(k0 + 2, k1)
    assert not rec.alive[dead, 2].any()
    frac, cnt = within_3sigma_fraction(rec, [0, 1, 3], 2, k_from=k0 + 2, k_to=k1)
    assert cnt > 0 and frac >= 0.97, frac
    # The restarted agent is back.
    assert rec.alive[k1 + 5 :, 2].mean() > 0.9
    # Camera 0 of satellite 1 produced nothing after the fault.
    from swarm.bus.messages import decode
    from swarm.mcaplog import iter_messages

    after = sum(
        sum(1 for cam in m.camera if cam == 0)
        for t, _s, d, _l, _p in iter_messages(c.out / "run.mcap")
        if t.endswith("/meas/1") and (m := decode("meas", d)).k > done["camera"]
    )
    assert after == 0
    # Partitioned satellite 3: the others keep estimating it within 3σ, and it comes back.
    kp, kh = done["partition"], done["heal"]
    frac3, cnt3 = within_3sigma_fraction(rec, [0, 1], 3, k_from=kp)
    assert cnt3 > 0 and frac3 >= 0.97, frac3
    back = np.flatnonzero(rec.alive[kh:, 3])
    assert back.size and back[0] <= 40, f"satellite 3's agent not back within 40 steps of the heal: {back[:5]}"
    assert rec.alive[kh + back[0] + 5 :, 3].mean() > 0.9, rec.alive[:, 3].astype(int)
    # The recording is complete for the processes that were up: every live survivor, every step.
    assert rec.alive[:, [0, 1]].all()
    assert np.isfinite(rec.t).all()


def test_agent_on_another_site_joins_through_the_router(image, tmp_path):
    """Two Docker networks joined only by the router: the stand-in for an agent on another
    machine pointing at the router's endpoint."""
    c = Compose(tmp_path / "out", {"SWARM_N": "4", "SWARM_N_LOCAL": "3", "SWARM_SET_EXTRA": "duration_s=15"}, files=("compose.yaml", "compose.remote.yaml"))
    try:
        c("up", timeout=900)
        logs = c("logs", "--no-color", "remote_agent", check=False).stdout
        nets = subprocess.run(["docker", "network", "ls", "--format", "{{.Name}}"], capture_output=True, text=True).stdout.split()
    finally:
        c.down()
    assert f"{c.project}_site_b" in nets and f"{c.project}_bus" in nets
    assert "initialised from the world's prior" in logs and "done at step 15" in logs, logs[-2000:]
    # Over TLS with the claimant's credential, then as its satellite's agent.
    assert "on the bus at ['tls/router:7449'] as claimant" in logs and "on the bus at ['tls/router:7449'] as agent-" in logs, logs[-2000:]
    assert "with its credential" in logs, logs[-2000:]
    s = _summary(c.out)
    assert s["steps"] == 16
    ref = _sim(4, ["duration_s=15"])
    assert s["rms"] == ref["rms"] and s["per_pair"] == ref["per_pair"]


@pytest.mark.slow
def test_netem_delay_and_loss_on_one_satellite(image, tmp_path):
    """Linux traffic control on satellite 3's container (200 ± 20 ms, 10 % loss) mid-run,
    then cleared: both recorded as fault events; every agent keeps every satellite within
    3σ; satellite 3's recorded bus latencies while impaired are at least the delay while
    everyone else's stay small; the namespace is clean afterwards; and, lockstep, the
    numbers are exactly the undisturbed run's (TCP resends what netem drops; the delay only
    slows the run)."""
    from swarm_harness import within_3sigma_fraction

    from swarm.faults import netem_state
    from swarm.launch import free_port
    from swarm.recording import load_recording
    from swarmcore.scenario import Scenario

    port = str(free_port())
    # Long enough that the run is still going when the clear comes (a fault takes tens of
    # seconds on a loaded machine: CLI start, docker run of the helper).
    n, dur = 4, 300
    delay_ms, jitter_ms = 200.0, 20.0
    sets = f"duration_s={dur} emulator.lockstep_max_realtime_factor=3 emulator.step_timeout_s=15"
    c = Compose(tmp_path / "out", {"SWARM_N": str(n), "SWARM_SET_EXTRA": sets, "SWARM_BUS_PORT": port})
    log, states = [], {}
    try:
        c("up", "-d", timeout=600)
        _wait_step(c, 20)
        log.append(_fault(c, "netem", "3", "--delay", f"{delay_ms:g}ms", "--jitter", f"{jitter_ms:g}ms", "--loss", "10%"))
        cid = log[-1].split("on container ")[1].split()[0]
        states["applied"] = netem_state(cid)
        _wait_step(c, 120)
        log.append(_fault(c, "netem", "3", "clear"))
        states["cleared"] = netem_state(cid)
        rid = c("ps", "-q", "recorder").stdout.split()
        r = subprocess.run(["docker", "wait", *rid], capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr
    finally:
        (tmp_path / "compose.log").write_text(c("logs", "--no-color", "-t", check=False).stdout)
        c.down()
    print("netem state:", states, flush=True)
    sc = Scenario(n_sats=n, duration_s=dur)
    rec = load_recording(c.out / "run.mcap", n, sc.steps)
    s = _summary(c.out)
    netem = [f for f in rec.faults if f["action"] == "netem"]
    done = [f for f in netem if f["phase"] == "done"]
    cmds = [f for f in netem if f["phase"] == "command"]
    assert [f["netem"] for f in done] == [f"delay {delay_ms:g}ms {jitter_ms:g}ms loss 10%", "clear"], (netem, log)
    assert all(f["target"] == 3 and f["sender"] == "cli" for f in netem) and len(cmds) == 2
    # Applied in satellite 3's namespace, then gone (kernel netem, or the netemd fallback).
    assert "netem" in states["applied"] or "NFQUEUE" in states["applied"], states
    assert not any(w in states["cleared"] for w in ("netem", "tbf", "iptables")), states
    # Survivors (here: everyone, no one died) keep every satellite within 3σ, and no agent missed a step.
    assert rec.alive.all() and np.isfinite(rec.t).all()
    fracs = {j: within_3sigma_fraction(rec, list(range(n)), j) for j in range(n)}
    print("within 3σ (fraction, count) per target:", fracs, flush=True)
    assert all(cnt > 0 and frac >= 0.97 for frac, cnt in fracs.values()), fracs
    # The delay shows in the recorded one-way latencies (publisher's Zenoh timestamp → recorder).
    t_on, t_off, t_clear = done[0]["log_time_ns"], cmds[1]["log_time_ns"], done[1]["log_time_ns"]
    during = rec.bus_latency_ms(t_on, t_off)
    after = rec.bus_latency_ms(t_clear)
    print("bus latency ms while impaired:", during, "\nafter clear:", after, "\nwhole run:", s["bus_latency_ms"], flush=True)
    sat3 = during["agent-3"]
    assert sat3["n"] >= 50 and sat3["min"] >= delay_ms - jitter_ms and sat3["p50"] >= delay_ms - jitter_ms, sat3
    for sender in ("world", "agent-0", "agent-1", "agent-2"):
        assert during[sender]["n"] >= 50 and during[sender]["p50"] < delay_ms / 4, (sender, during[sender])
    assert after["agent-3"]["p50"] < delay_ms / 4, after["agent-3"]
    # Lockstep: the impairment slowed the run; it did not change a number.
    ref = _sim(n, [f"duration_s={dur}"])
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate"):
        assert s[key] == ref[key], f"{key}: netem changed the numbers"


def _fault_both(c: Compose, *args) -> str:
    """`swarm fault --compose ...` from the host, given both routers' ports."""
    p = subprocess.run([sys.executable, "-m", "swarm.cli", "fault", "--compose", "--project", c.project, *args], cwd=ROOT,
                       env=dict(os.environ, SWARM_BUS_PORT=c.env["SWARM_BUS_PORT"], SWARM_BUS_PORT2=c.env.get("SWARM_BUS_PORT2", ""),
                                SWARM_KEYS=c.env["SWARM_KEYS"]),
                       capture_output=True, text=True, timeout=300)
    print(f"fault {args}: {p.stdout.strip()} {p.stderr.strip()[-300:]}", flush=True)
    assert p.returncode == 0 and "done" in p.stdout, p.stdout + p.stderr
    return p.stdout


def _docker_wait(c: Compose, service: str) -> int:
    ids = c("ps", "-q", service).stdout.split()
    r = subprocess.run(["docker", "wait", *ids], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    return int(r.stdout.split()[0])


@pytest.mark.slow
def test_two_meshed_routers_one_killed_the_run_completes(image, tmp_path):
    """compose.routers2.yaml: two meshed routers, every role given both endpoints; router 0
    (the one every role connected to first) is killed mid-run: the roles fail over to
    router 1, the run completes with the numbers of the in-process run."""
    from swarm.launch import free_port
    from swarm.recording import load_recording

    n, dur = 4, 30
    sets = f"duration_s={dur} emulator.lockstep_max_realtime_factor=3"
    env = {"SWARM_N": str(n), "SWARM_SET_EXTRA": sets, "SWARM_BUS_PORT": str(free_port()), "SWARM_BUS_PORT2": str(free_port())}
    c = Compose(tmp_path / "out", env, files=("compose.yaml", "compose.routers2.yaml"))
    try:
        c("up", "-d", timeout=600)
        _wait_step(c, 10)
        _fault_both(c, "kill-router", "0")
        assert _docker_wait(c, "world") == 0
        assert _docker_wait(c, "recorder") == 0
    finally:
        (tmp_path / "compose.log").write_text(c("logs", "--no-color", "-t", check=False).stdout)
        c.down()
    s = _summary(c.out)
    assert "interrupted" not in s and s["steps"] == dur + 1, s.get("interrupted")
    rec = load_recording(c.out / "run.mcap", n, dur + 1)
    assert rec.alive.all() and np.isfinite(rec.t).all()
    ref = _sim(n, sets.split())
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate"):
        assert s[key] == ref[key], f"{key}: the run with a router killed differs from the in-process run"


@pytest.mark.slow
def test_one_router_killed_the_world_exits_non_zero_and_the_summary_says_so(image, tmp_path):
    """One router, killed for good: every container ends within the bound, the world with
    status 3 (what `docker compose up --exit-code-from world` returns), and the recorder's
    summary.json is marked interrupted (bus lost) at the last step it recorded."""
    from swarm.launch import free_port

    sets = "duration_s=300 emulator.lockstep_max_realtime_factor=3 emulator.bus_lost_after_s=5"
    c = Compose(tmp_path / "out", {"SWARM_N": "3", "SWARM_SET_EXTRA": sets, "SWARM_BUS_PORT": str(free_port())})
    try:
        c("up", "-d", timeout=600)
        _wait_step(c, 8)
        _fault_both(c, "kill-router", "0")
        assert _docker_wait(c, "world") == 3
        assert _docker_wait(c, "recorder") == 3
        for svc in ("agent", "selector"):
            assert _docker_wait(c, svc) != 0
    finally:
        (tmp_path / "compose.log").write_text(c("logs", "--no-color", "-t", check=False).stdout)
        c.down()
    s = _summary(c.out)
    intr = s["interrupted"]
    assert intr["reason"].startswith("bus lost") and 8 <= intr["last_step"] < 300, intr
