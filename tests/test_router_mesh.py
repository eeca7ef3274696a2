"""Two routers in a mesh with security on (swarm run --routers 2, compose.routers2.yaml):
clients of either router hear the clients of the other — liveliness and samples — before
and after the first router is killed and restarted.

The bug this holds: user/password authentication is one-way, so the router that dialled
the other saw its link with no user name; with deny-by-default access rules nothing crossed
the mesh. `swarm chaos --routers 2` found it: an agent restarted onto the restarted router
waited 120 s for its peers' liveliness. Each router of a run now has a fixed Zenoh id and
lets its peers' ids through (swarmrt.security.router_zid)."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from swarm.supervise.launch import free_port
from swarmrt.bus import messages as M
from swarmrt.bus.session import BusConfig
from swarmrt.security import MESH_ROUTERS, acl_config, make_keys, router_zid

pytestmark = [pytest.mark.integration]

RUN = "mesh-test"


def _router(tmp: Path, listen: str, index: int, connect: list[str]) -> subprocess.Popen:
    args = [sys.executable, "-m", "swarm.supervise.router", "--listen", listen, "--index", str(index),
            *[a for c in connect for a in ("--connect", c)], "--keys", str(tmp / "keys"), "--run", RUN, "--n-sats", "4"]
    with open(tmp / f"router-{index}.log", "ab") as log:
        p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=log)
    line = p.stdout.readline() if p.stdout else b""
    assert b"READY" in line, (tmp / f"router-{index}.log").read_text()[-2000:]
    return p


def _client(tmp: Path, endpoint: str, identity: str) -> zenoh.Session:
    return zenoh.open(BusConfig(mode="client", connect=[endpoint], credential_file=str(tmp / "keys" / f"{identity}.json")).zenoh_config())


def _stop(p: subprocess.Popen) -> None:
    p.kill()
    p.wait(30)


def _hears_across(tmp: Path, e_world: str, agent: zenoh.Session) -> tuple[bool, bool]:
    """A world on ``e_world``: does it see agent 1's token, and receive agent 1's puts on meas/1?"""
    k = M.Keys(RUN)
    seen, got = threading.Event(), threading.Event()
    with _client(tmp, e_world, "world") as world:
        ls = world.liveliness().declare_subscriber(f"{k.root}/alive/**", lambda s: seen.set(), history=True)
        sub = world.declare_subscriber(k.meas(1), lambda s: got.set())
        try:
            for _ in range(50):  # until it arrives (the mesh may still be linking), at most 5 s
                agent.put(k.meas(1), b"x")
                if got.wait(0.1):
                    break
            return seen.wait(5.0), got.is_set()
        finally:
            ls.undeclare()
            sub.undeclare()


def test_the_mesh_carries_traffic_both_ways_and_after_a_restart(tmp_path):
    make_keys(tmp_path / "keys", 4)
    e0, e1 = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    r0 = _router(tmp_path, e0, 0, [])
    r1 = _router(tmp_path, e1, 1, [e0])
    try:
        with _client(tmp_path, e1, "agent-1") as agent:
            token = agent.liveliness().declare_token(M.Keys(RUN).alive("agent", 1))
            assert _hears_across(tmp_path, e0, agent) == (True, True), "router 1's client unheard on router 0"
            _stop(r0)
            r0 = _router(tmp_path, e0, 0, [e1])  # back, on the same endpoint, dialling router 1
            assert _hears_across(tmp_path, e0, agent) == (True, True), "after router 0's restart: unheard across the mesh"
            token.undeclare()
    finally:
        for p in (r0, r1):
            _stop(p)


def test_router_ids_are_fixed_secret_derived_and_let_through_as_the_mesh():
    a, b = router_zid("s3cret", 0), router_zid("s3cret", 1)
    assert a != b and a == router_zid("s3cret", 0) and a != router_zid("other", 0)
    assert len(a) == 32 and int(a, 16) > 0
    with pytest.raises(ValueError):
        router_zid("s3cret", MESH_ROUTERS)
    acl = acl_config(RUN, 4, peer_zids=[b])
    (mesh,) = [p for p in acl["policies"] if p["id"] == "mesh"]
    assert mesh["subjects"] == ["mesh", "mesh-routers"]
    assert {"id": "mesh-routers", "zids": [b]} in acl["subjects"]
    assert all(p["subjects"] == [p["id"]] for p in acl["policies"] if p["id"] != "mesh"), "only the mesh gets the peers' ids"
