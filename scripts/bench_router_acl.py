#!/usr/bin/env python3
"""The router's CPU time per measurement batch with the bus's security on and off.

    python scripts/bench_router_acl.py [--batches 100000] [--rounds 2]

A router process (``python -m swarm.supervise.router``; with security: the keys of a 2-satellite run
and its access rules), agent 0 putting n = 10 measurement batches on ``meas/0`` as fast as
the bus takes them (congestion control BLOCK) and agent 1 subscribed: each batch is one
ingress and one egress check of the rules. The router's user + system CPU time (psutil)
over the burst, divided by the batches, is the figure; rounds alternate on and off so
that a loaded machine's noise falls on both. (`swarm bench bus` gives the latencies.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import zenoh

from swarm.bench.bus import _batch_payload
from swarm.supervise.launch import free_port
from swarmrt.security import load_credential, make_keys


def _client(endpoint: str, cred: Path | None):
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled", "false")
    if cred is not None:
        load_credential(cred).apply(c)
    return zenoh.open(c)


def one(on: bool, n: int, payload: bytes) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        keys = Path(tmp)
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        args = [sys.executable, "-m", "swarm.supervise.router", "--listen", endpoint]
        if on:
            make_keys(keys, 2)
            args += ["--keys", str(keys), "--run", "bench", "--n-sats", "2"]
        router = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        try:
            assert b"READY" in router.stdout.readline()
            proc = psutil.Process(router.pid)
            with _client(endpoint, keys / "agent-0.json" if on else None) as a, \
                    _client(endpoint, keys / "agent-1.json" if on else None) as b:
                got = [0]
                done = threading.Event()

                def cb(_s):
                    got[0] += 1
                    if got[0] >= n:
                        done.set()

                sub = b.declare_subscriber("swarm/bench/meas/*", cb)
                pub = a.declare_publisher("swarm/bench/meas/0", congestion_control=zenoh.CongestionControl.BLOCK)
                for _ in range(1000):  # until the subscription has reached the publisher
                    pub.put(payload)
                    if done.wait(0.01) or got[0]:
                        break
                got[0] = 0
                c0, t0 = sum(proc.cpu_times()[:2]), time.perf_counter()
                for _ in range(n):
                    pub.put(payload)
                assert done.wait(300), f"{got[0]} of {n} batches arrived"
                c1, t1 = sum(proc.cpu_times()[:2]), time.perf_counter()
                sub.undeclare()
        finally:
            router.terminate()
            router.wait(10)
    return {"security": "on" if on else "off", "batches": n, "bytes": len(payload),
            "router_cpu_us_per_batch": (c1 - c0) / n * 1e6, "batches_per_s": n / (t1 - t0)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=100_000)
    p.add_argument("--rounds", type=int, default=2)
    a = p.parse_args()
    payload = _batch_payload(10)
    for _ in range(a.rounds):
        for on in (True, False):
            r = one(on, a.batches, payload)
            print(f"security {r['security']:3s}: router CPU {r['router_cpu_us_per_batch']:.1f} µs per batch "
                  f"({r['batches']} batches of {r['bytes']} B; {r['batches_per_s']:.0f} batches/s end to end)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
