"""Benchmarks of the distributed emulator: bus latency and the real-time factor of runs.

Latency: a ping process and an echo process, each a Zenoh client of a router process on
loopback (the topology of ``swarm run``), each connected with the bus configuration a
swarm's processes have (:func:`swarm.supervise.launch.client_bus`, opened by
:func:`swarmrt.bus.session.open_session`); one-way latency is half the measured round trip.
Real-time factor: simulated seconds per wall second of ``swarm run`` in lockstep, from the
recorded clock messages (start-up excluded).

Both measure with the bus's security on (the default of every run: each client
authenticated, the router checking every message against the run's access rules) and,
given ``security=(True, False)``, off, side by side: the cost of authentication and access
control. The latency bench then runs on swarm keys (agent 0 pings on ``meas/0``, agent 1
echoes on ``meas/1``), so the router checks exactly the rules a run's batches meet.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from swarmrt.bus.messages import Keys

__all__ = ["bench_latency", "bench_realtime"]

# The echo reads its bus flags as a role process does (BusConfig.as_args on the way in).
_ECHO = """
import argparse, threading, zenoh
from swarmrt.bus.session import add_bus_args, bus_config_from_args, open_session
p = argparse.ArgumentParser()
add_bus_args(p)
bus = bus_config_from_args(p.parse_args())
stop = threading.Event()
with open_session(bus) as s:
    pub = s.declare_publisher(_PONG, congestion_control=zenoh.CongestionControl.BLOCK)
    def cb(sample):
        if sample.payload.to_bytes() == b"stop":
            stop.set()
        else:
            pub.put(sample.payload)
    sub = s.declare_subscriber(_PING, cb)
    print("READY", flush=True)
    stop.wait()
"""
_RUN = "bench"
# A batch's path in a swarm: agent 0 puts it on meas/0 to the radio (the world), the world
# passes batches on to every agent on batches (the echo plays the world).
_PING, _PONG = Keys(_RUN).meas(0), Keys(_RUN).batches()
_ECHO = f"_PING, _PONG = {_PING!r}, {_PONG!r}\n" + _ECHO


def _percentiles(x):
    a = np.asarray(x) * 1e3
    return {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)), "mean_ms": float(a.mean()), "samples": int(a.size)}


def _batch(n: int, observer: int = 0):
    """A realistic measurement batch: the observer's relative poses of the n−1 others, with
    the covariances the sensor model reports (what one agent transmits at n satellites)."""
    from swarmcore.agent import SyntheticPoseEstimator
    from swarmcore.scenario import Scenario
    from swarmcore.world import SyntheticCameras, initial_truth, world_params

    sc = Scenario(name=f"bench-n{n}", seed=1, n_sats=n, duration_s=10.0)
    wp = world_params(sc)
    tr = initial_truth(sc)
    tgt = np.array([j for j in range(n) if j != observer])
    obs = np.full(n - 1, observer)
    seen = SyntheticCameras(wp).observe(tr, obs, tgt)
    return SyntheticPoseEstimator(sc).measure(observer, seen[observer])


def _median_us(f, repeat: int) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.thread_time_ns()
        f()
        ts.append((time.thread_time_ns() - t0) / 1e3)
    return float(np.median(ts))


def codec_cost(n: int, repeat: int = 200) -> dict:
    """CPU time (µs, median) to turn one agent's batch at swarm size n into bytes (message
    construction + encoding) and back into the filter's arrays (decoding, validation,
    conversion): what an agent does once a step, and what the world (the radio) does for
    each agent's batch. Then the step's every batch in one message: the world's cost to
    build and encode it, and each agent's to decode, check and convert its peers' rows
    (once a step, in place of a decode per peer)."""
    from swarmrt.bus.convert import batch_msg, relative_from_batches, relative_from_step, step_batches_msg
    from swarmrt.bus.messages import decode, encode

    rel, cams = _batch(n)

    def enc():
        return encode(batch_msg(rel, cams, run="bench", sender="agent-0", k=1, t_s=1.0, observer=0))

    raw = enc()

    def dec():
        return relative_from_batches([decode("meas", raw)])

    back = dec()
    assert np.array_equal(back.R_Bi, rel.R_Bi) and np.array_equal(back.q_BjBi, rel.q_BjBi), "the batch did not round-trip"
    out: dict[str, Any] = {"bytes": len(raw)}
    for name, f in (("encode_us", enc), ("decode_us", dec)):
        out[name] = _median_us(f, repeat)
    out["decode_all_peers_ms"] = out["decode_us"] * (n - 1) / 1e3  # what an agent did when it heard every peer's batch
    batches = [decode("meas", encode(batch_msg(*_batch(n, i), run="bench", sender=f"agent-{i}", k=1, t_s=1.0, observer=i)))
               for i in range(n)]

    def build():
        return encode(step_batches_msg(batches, run="bench", k=1, t_s=1.0))

    step_raw = build()
    want = relative_from_batches(batches[1:])

    def step_dec():
        return relative_from_step(decode("batches", step_raw), skip=0)

    got = step_dec()
    assert np.array_equal(got.R_Bi, want.R_Bi) and np.array_equal(got.target, want.target), "the step's batches did not round-trip"
    out["step_batches"] = {"bytes": len(step_raw), "build_us": _median_us(build, max(10, repeat // 10)),
                           "decode_us": _median_us(step_dec, max(10, repeat // 10))}
    return out


def _batch_payload(n: int = 10) -> bytes:
    from swarmrt.bus.convert import batch_msg
    from swarmrt.bus.messages import encode

    rel, cams = _batch(n)
    return encode(batch_msg(rel, cams, run="bench", sender="agent-0", k=1, t_s=1.0, observer=0))


def bench_latency(samples: int = 400, big_samples: int = 60, log=print, batch_sizes=(10, 40), security=(True,)) -> list[dict]:
    """Rows of every payload for each security setting in ``security`` (True: on)."""
    rows = []
    for on in security:
        log(f"security {'on' if on else 'off'}:")
        with tempfile.TemporaryDirectory(prefix="swarm-bench-keys-") as tmp:
            rows += _bench_latency(samples, big_samples, log, batch_sizes, Path(tmp) if on else None)
    return rows


def _bench_latency(samples: int, big_samples: int, log, batch_sizes, keys_dir: Path | None) -> list[dict]:
    import zenoh

    from swarm.supervise.launch import client_bus, free_port
    from swarmrt.bus.session import open_session
    from swarmrt.security import make_keys

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    secure = []
    if keys_dir is not None:
        make_keys(keys_dir, 2)
        secure = ["--keys", str(keys_dir), "--run", _RUN, "--n-sats", "2"]
    router = subprocess.Popen([sys.executable, "-m", "swarm.supervise.router", "--listen", endpoint, *secure], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL)
    echo = None
    try:
        _wait_ready(router, "router")
        # The echo plays the world, the ping agent 0 (their credentials when security is on).
        # Its bus is what the flags say, whatever bus variables this shell has (SWARM_CREDENTIAL...).
        echo_bus = client_bus([endpoint], keys_dir, "world")
        env = {k: v for k, v in os.environ.items() if k not in ("SWARM_CREDENTIAL", "SWARM_ZENOH_CONNECT", "SWARM_ZENOH_MODE")}
        echo = subprocess.Popen([sys.executable, "-c", _ECHO, *echo_bus.as_args()], stdout=subprocess.PIPE, env=env)
        _wait_ready(echo, "echo")
        rows = []
        with open_session(client_bus([endpoint], keys_dir, "agent-0")) as s:
            got = threading.Event()
            want = {"seq": -1}

            def on_pong(smp):
                # Count only the echo of the ping in flight (late warm-up echoes must not).
                if int.from_bytes(smp.payload.to_bytes()[:8], "little") == want["seq"]:
                    got.set()

            sub = s.declare_subscriber(_PONG, on_pong)
            pub = s.declare_publisher(_PING, congestion_control=zenoh.CongestionControl.BLOCK)
            # Wait until the echo's subscription has reached us through the router.
            seq = 0
            for _ in range(200):
                seq += 1
                want["seq"] = seq
                got.clear()
                pub.put(seq.to_bytes(8, "little") + b"warmup")
                if got.wait(0.05):
                    break
            cases = [(f"measurement batch (n={n})", _batch_payload(n), samples, n) for n in batch_sizes]
            cases.append(("1 MB payload", bytes(np.random.default_rng(0).integers(0, 256, 1 << 20, dtype=np.uint8)), big_samples, None))
            for name, payload, count, n_batch in cases:
                rtt = []
                for _ in range(count + 5):
                    seq += 1
                    want["seq"] = seq
                    msg = seq.to_bytes(8, "little") + payload
                    got.clear()
                    t0 = time.perf_counter()
                    pub.put(msg)
                    if not got.wait(5.0):
                        raise RuntimeError(f"no echo for {name}")
                    rtt.append(time.perf_counter() - t0)
                rtt = rtt[5:]
                one_way = [r / 2 for r in rtt]
                row = {"payload": name, "bytes": len(payload), "path": "client → router → client (loopback)", "one_way": _percentiles(one_way), "round_trip": _percentiles(rtt),
                       "security": "on" if keys_dir is not None else "off"}
                line = f"{name:26s} {len(payload):8d} B  one-way p50 {row['one_way']['p50_ms']:.3f} ms  p99 {row['one_way']['p99_ms']:.3f} ms"
                if n_batch is not None:
                    row["n"] = n_batch
                    row["codec"] = codec_cost(n_batch)
                    c = row["codec"]
                    sb = c["step_batches"]
                    line += (f"  encode {c['encode_us']:.0f} µs  decode {c['decode_us']:.0f} µs; the step's {n_batch} batches in one message "
                             f"({sb['bytes']} B): built by the world in {sb['build_us'] / 1e3:.2f} ms, decoded by an agent in "
                             f"{sb['decode_us'] / 1e3:.2f} ms (a decode per peer: {c['decode_all_peers_ms']:.2f} ms)")
                log(line)
                rows.append(row)
            pub.put(b"stop")
            sub.undeclare()
        return rows
    finally:
        for p in (echo, router):
            if p is not None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()


def _wait_ready(p: subprocess.Popen, name: str) -> None:
    """Block until ``p`` (stdout piped) prints its READY line; fail if it prints anything else or ends."""
    line = p.stdout.readline() if p.stdout is not None else b""
    if b"READY" not in line:
        raise RuntimeError(f"the bench's {name} process did not start (it printed {line[:200]!r})")


def _ms(x: float | None, scale: float = 1.0, spec: str = ".2f") -> str:
    """``x · scale`` formatted, or ``n/a`` when there is no value (no steady-state estimate recorded)."""
    return "n/a" if x is None else format(x * scale, spec)


def bench_realtime(sats: list[int], duration_s: float = 60.0, log=print, workdir: Path | None = None, security=(True,),
                   estimator: str = "full", graph: str | None = None, agent_start: str = "fork") -> list[dict]:
    """Real-time factor, start-up and memory of ``swarm run`` (lockstep, synthetic
    measurements), for each swarm size and each security setting (True: on).

    ``estimator``: every agent's estimator kind. ``graph``: ``complete`` (every pair), or
    ``nearest`` (a lattice 20 m apart, each satellite measuring its 3 nearest: the
    100-satellite swarm's geometry); default complete for ``full``, nearest for the others.
    ``agent_start``: fork (the fork server) or spawn (a cold interpreter per agent)."""
    graph = graph or ("complete" if estimator == "full" else "nearest")
    return [row for n in sats for on in security
            for row in _bench_realtime([n], duration_s, log, workdir, on, estimator, graph, agent_start)]


def bench_scenario(n: int, duration_s: float, security: bool, estimator: str, graph: str, agent_start: str):
    """The benchmark's swarm of ``n`` (see :func:`bench_realtime`)."""
    from swarmcore.scenario import Scenario

    extra: dict[str, Any] = {}
    if graph == "nearest":
        extra = {"initial": {"layout": "lattice", "spacing_m": 20.0, "position_max_m": 2.0, "drift_free": True},
                 "graph": {"kind": "nearest", "neighbors": 3}}
    elif graph != "complete":
        raise ValueError(f"graph {graph!r}: complete or nearest")
    return Scenario(name=f"bench-n{n}", seed=1, n_sats=n, duration_s=duration_s, estimator={"kind": estimator},
                    emulator={"security": security, "agent_start": agent_start, "startup_timeout_s": max(120.0, 3.0 * n)}, **extra)


def process_tree_memory(root_pid: int) -> dict:
    """Resident (RSS) and proportional (PSS: shared pages split between their users) memory
    of ``root_pid``'s descendants, summed, from /proc (psutil)."""
    import psutil

    rss = pss = 0
    count = 0
    for p in psutil.Process(root_pid).children(recursive=True):
        try:
            mi = p.memory_full_info()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        rss += mi.rss
        pss += getattr(mi, "pss", 0)
        count += 1
    return {"processes": count, "rss_bytes": rss, "pss_bytes": pss}


def role_cpu_seconds(root_pid: int, procs: dict) -> dict[str, float]:
    """CPU seconds (user + system) so far of every live process under ``root_pid``, summed by
    role: a process of ``procs`` (``LocalSwarm.procs``: name → process) counts under its name
    less its index (``agent-3`` → ``agent``), its descendants under the same; anything else
    (the agents' fork server) under ``other``."""
    import psutil

    owner = {p.pid: name.rsplit("-", 1)[0] if name.rsplit("-", 1)[-1].isdigit() else name
             for name, p in procs.items() if p is not None}
    out: dict[str, float] = {}
    for p in psutil.Process(root_pid).children(recursive=True):
        try:
            role = None
            q: psutil.Process | None = p
            while q is not None and q.pid != root_pid:
                if q.pid in owner:
                    role = owner[q.pid]
                    break
                q = q.parent()
            t = p.cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        role = role or "other"
        out[role] = out.get(role, 0.0) + t.user + t.system
    return out


def _bench_realtime(sats: list[int], duration_s: float, log, workdir: Path | None, security: bool, estimator: str = "full",
                    graph: str = "complete", agent_start: str = "fork") -> list[dict]:
    import os
    import threading

    from swarm.record.mcaplog import iter_messages
    from swarm.supervise.launch import LocalSwarm

    rows = []
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="swarm-bench-"))
    for n in sats:
        sc = bench_scenario(n, duration_s, security, estimator, graph, agent_start)
        out = base / f"n{n}-{estimator}-{graph}-security-{'on' if security else 'off'}"
        sw = LocalSwarm(sc, out, log=lambda s: None)
        peak = {"pss_bytes": 0, "rss_bytes": 0, "processes": 0}
        stop = threading.Event()

        def sample(peak=peak, stop=stop) -> None:
            # Memory of every process of the run, every 2 s; the peak of the sum is kept.
            while not stop.wait(2.0):
                m = process_tree_memory(os.getpid())
                if m["pss_bytes"] > peak["pss_bytes"]:
                    peak.update(m)

        sampler = threading.Thread(target=sample, name="memory", daemon=True)
        # CPU by role over the steady stepping: a snapshot at the clock of step 2 and at the
        # last step (the clock is heard here, on the supervisor's thread).
        cpu_marks: dict[int, dict[str, float]] = {}
        last_k = sc.steps - 1

        def progress(k_plus_1: int, _steps: int, marks=cpu_marks, sw=sw, last=last_k) -> None:
            k = k_plus_1 - 1
            if (k == 2 or k == last) and k not in marks:
                marks[k] = role_cpu_seconds(os.getpid(), sw.procs)

        t_start, t_start_ns = time.perf_counter(), time.time_ns()
        try:
            sw.start()
            sampler.start()
            code = sw.run_to_end(progress=progress)
        finally:
            stop.set()
            sw.stop()
        role_ms: dict[str, float] = {}
        if 2 in cpu_marks and last_k in cpu_marks and last_k > 2:
            a, b = cpu_marks[2], cpu_marks[last_k]
            role_ms = {r: 1e3 * (b.get(r, 0.0) - a.get(r, 0.0)) / (last_k - 2) for r in sorted(set(a) | set(b))}
        total = time.perf_counter() - t_start
        from swarmrt.bus.convert import step_batches_msg
        from swarmrt.bus.messages import MessageError, decode, encode, parse_key

        clocks, est = [], []
        est_bytes: list[int] = []
        est_prefix = f"{sw.keys.root}/est/"  # the agents' own channels, not the derived /foxglove/est/<i>
        # What the agents' subscriptions brought them (payload bytes): the clock and fault
        # commands (every agent), its own sensors and cameras, and the radio (batches: every
        # agent; batches/<i>, rx/<i>: agent i). And each step's batches as the one-message
        # ideal radio would have sent them to every agent (the whole swarm's).
        agent_in = radio_in = 0
        meas_of: dict[int, list] = {}
        recorder_waits = (0, 0.0)  # the bounded recorder lag's cost: steps the world waited for the recorder, wall s
        for topic, _s, data, lt, _p in iter_messages(out / "run.mcap"):
            try:
                _run, kind, ident = parse_key(topic)
            except MessageError:
                kind, ident = "", None
            size = len(data)
            if kind in ("clock", "fault") and topic.endswith(f"/{kind}"):
                agent_in += size * n
            elif kind in ("batches", "rx"):
                agent_in += size * (n if ident is None else 1)
                radio_in += size * (n if ident is None else 1)
            elif kind in ("sensors", "cam", "img"):
                agent_in += size
            elif kind == "meas":
                try:
                    b = decode("meas", data)
                except MessageError:
                    continue
                meas_of.setdefault(int(b.k), []).append(b)
            if topic.endswith("/clock"):
                clocks.append(lt)
                with contextlib.suppress(MessageError):
                    c = decode("clock", data)
                    recorder_waits = max(recorder_waits, (int(c.recorder_waited_steps), float(c.recorder_waited_s)))
            elif topic.startswith(est_prefix):
                try:
                    m = decode("est", data)
                except MessageError:
                    continue
                if m.phase == "posterior" and m.k >= 2:  # steady state: past the first update
                    est.append((m.step_ms, m.step_cpu_ms, m.codec_cpu_ms))
                    est_bytes.append(m.bytes_sent)
        wall = (max(clocks) - min(clocks)) / 1e9
        startup = (min(clocks) - t_start_ns) / 1e9
        e = np.array(est, dtype=float).reshape(-1, 3)
        filt_cpu = float(np.median(e[:, 1])) if len(e) else None
        codec_cpu = float(np.median(e[:, 2])) if len(e) else None
        share = codec_cpu / filt_cpu if codec_cpu is not None and filt_cpu else None
        traffic = [r for r in est_bytes if r > 0]
        whole = [len(encode(step_batches_msg(sorted(ms, key=lambda b: b.observer), run=sw.run, k=k, t_s=k * sc.dt_s)))
                 for k, ms in meas_of.items()]
        row: dict[str, Any] = {
            "n": n,
            "estimator": estimator,
            "graph": graph,
            "agent_start": agent_start,
            "security": "on" if security else "off",
            "time_mode": "lockstep",
            "pss_peak_gib": peak["pss_bytes"] / 2**30,
            "rss_peak_gib": peak["rss_bytes"] / 2**30,
            "processes": peak["processes"],
            "bytes_per_sat_per_s": float(np.mean(traffic)) / sc.dt_s if traffic else None,
            # Received bytes per agent and step: everything its subscriptions bring, and the
            # radio's part (its peers' batches); and the whole swarm's batches of a step in one
            # message, which the one-message ideal radio delivers to every agent.
            "agent_rx_bytes_per_step": agent_in / (n * sc.steps),
            "agent_radio_rx_bytes_per_step": radio_in / (n * sc.steps),
            "whole_swarm_batches_bytes_per_step": float(np.mean(whole)) if whole else None,
            "sim_seconds": duration_s,
            "stepping_wall_s": wall,
            "realtime_factor": duration_s / wall if wall > 0 else None,
            "startup_s": startup,
            "total_wall_s_with_startup": total,
            "agent_filter_ms_median": float(np.median(e[:, 0])) if len(e) else None,
            "agent_filter_cpu_ms_median": filt_cpu,
            "agent_codec_cpu_ms_median": codec_cpu,
            # CPU an agent spends on messages per step, over its filter step's CPU (same run).
            "codec_share_of_filter": share,
            "codec_share_of_filter_mean": float(e[:, 2].sum() / e[:, 1].sum()) if len(e) and e[:, 1].sum() > 0 else None,
            "world_exit_code": code,
            # The bounded recorder lag (emulator.recorder_max_lag_steps): what waiting for the recorder cost.
            "recorder_max_lag_steps": sc.emulator.recorder_max_lag_steps,
            "recorder_steps_waited": recorder_waits[0],
            "recorder_wait_s": recorder_waits[1],
            # CPU (ms) per simulated step of every process of the run, summed by role (agent:
            # all of them), between the clocks of step 2 and of the last step.
            "cpu_ms_per_step_by_role": role_ms,
            "cpu_ms_per_step_total": sum(role_ms.values()) if role_ms else None,
        }
        log(
            f"n={n:3d} {estimator}/{graph} ({agent_start}) security {row['security']:3s}: PSS peak {row['pss_peak_gib']:.2f} GiB "
            f"(RSS {row['rss_peak_gib']:.2f} GiB, {row['processes']} processes), {_ms(row['bytes_per_sat_per_s'], spec='.0f')} B/s per "
            f"satellite; {duration_s:.0f} sim s in {wall:.1f} wall s → real-time factor "
            f"{_ms(row['realtime_factor'], spec='.1f')}×, start-up {startup:.1f} s (total {total:.1f} s); agent per step: filter "
            f"{_ms(filt_cpu)} ms CPU, messages {_ms(codec_cpu)} ms CPU ({_ms(share, 100, '.0f')} % of the filter)"
        )
        log(f"  waited for the recorder (at most {sc.emulator.recorder_max_lag_steps} steps behind): "
            f"{recorder_waits[0]} steps, {recorder_waits[1]:.2f} s")
        log(f"  received per agent and step: {row['agent_rx_bytes_per_step']:.0f} B, of which the radio (peers' batches) "
            f"{row['agent_radio_rx_bytes_per_step']:.0f} B (the whole swarm's batches in one message: "
            f"{_ms(row['whole_swarm_batches_bytes_per_step'], spec='.0f')} B)")
        if role_ms:
            log("  CPU per step by role: " + ", ".join(f"{r} {v:.0f} ms" for r, v in sorted(role_ms.items(), key=lambda kv: -kv[1]))
                + f" (total {sum(role_ms.values()):.0f} ms)")
        rows.append(row)
    return rows
