"""TLS between the routers of a cluster run (swarm run --cluster over several hosts): the
head's host actor makes a CA and one certificate per node's router, valid for that node's
address, and hands each node its own router's key only; the routers mesh over ``tls/``
endpoints with mutual TLS (each shows its certificate to the other, the driver shows its
client certificate), and a peer speaking plain TCP to them is refused, as is one whose
credential has no client certificate of the run's CA (an agent's password alone: a node's
own processes reach its router on that host's loopback, through its ingress gate).

Two routers on this machine's loopback (127.0.0.1 and 127.0.0.2, each with its own
certificate), with the shares :class:`swarm.cluster.host.NodeHost` hands out, for real."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from forgery import Witness, _open

from swarm.cluster.host import NodeHost
from swarm.supervise.launch import free_port
from swarmrt.bus import messages as M

pytestmark = pytest.mark.integration

RUN = "tls-mesh-1"
IPS = ("127.0.0.1", "127.0.0.2")


def _x509(pem: str, tmp: Path) -> str:
    f = tmp / "c.pem"
    f.write_text(pem)
    return subprocess.run(["openssl", "x509", "-in", str(f), "-noout", "-text"], capture_output=True, text=True, check=True).stdout


@pytest.fixture
def shares(tmp_path):
    head = NodeHost(RUN, 0, IPS[0])
    try:
        files = head.make_keys(4, [["supervisor.json", "observer.json", "ca.pem", "driver.pem", "driver.key"],
                                   ["router.json", "mesh.json", "passwords", "ca.pem", "router-tls:0", "world.json"],
                                   ["router.json", "mesh.json", "passwords:agents", "ca.pem", "router-tls:1", "agent-1.json"]],
                               [[IPS[0], "head"], [IPS[1]]])
        kept = sorted(head._all_keys)
    finally:
        head.shutdown(0.0)
    dirs = []
    for i, share in enumerate(files):
        d = tmp_path / f"node{i}"
        d.mkdir(mode=0o700)
        for name, text in share.items():
            (d / name).write_text(text)
        dirs.append(d)
    return files, dirs, kept


def test_each_node_gets_its_own_routers_certificate_and_key_only(shares, tmp_path):
    files, _dirs, kept = shares
    driver, node0, node1 = files
    assert sorted(driver) == ["ca.pem", "driver.key", "driver.pem", "observer.json", "supervisor.json"]
    assert json.loads(driver["supervisor.json"])["certificate"] == "driver.pem"  # the driver's client certificate
    assert "TLS Web Client Authentication" in _x509(driver["driver.pem"], tmp_path)
    assert "TLS Web Server Authentication" not in _x509(driver["driver.pem"], tmp_path)  # it can serve as no router
    for share in (node0, node1):
        assert {"router.pem", "router.key", "ca.pem"} <= set(share) and "ca.key" not in share and "driver.key" not in share
        assert not [n for n in share if n.startswith("router-")]
        meta = json.loads(share["router.json"])
        assert meta["certificate"] == "router.pem" and meta["mtls"] is True
        # A router's certificate serves both ends of a mesh link (it dials its peers with it).
        assert "TLS Web Server Authentication, TLS Web Client Authentication" in _x509(share["router.pem"], tmp_path)
    assert "certificate" not in json.loads(node1["agent-1.json"])  # an agent has no client certificate
    assert node0["router.key"] != node1["router.key"] and node0["router.pem"] != node1["router.pem"]
    # Each certificate is valid for its own node's address only.
    assert "IP Address:127.0.0.1" in _x509(node0["router.pem"], tmp_path) and "DNS:head" in _x509(node0["router.pem"], tmp_path)
    assert "IP Address:127.0.0.2" in _x509(node1["router.pem"], tmp_path) and "127.0.0.1" not in _x509(node1["router.pem"], tmp_path)
    # Every credential names the CA; the head keeps no router's key and never the CA's.
    assert json.loads(node1["agent-1.json"])["ca"] == "ca.pem"
    assert "ca.key" not in kept and not [n for n in kept if n.endswith(".key")], kept


@pytest.fixture
def mesh(shares, tmp_path):
    _files, dirs, _kept = shares
    ports = [free_port(), free_port()]
    eps = [f"tls/{ip}:{p}" for ip, p in zip(IPS, ports, strict=True)]
    # Each node's own processes: plain TCP on its host's loopback (a cluster's node puts its
    # ingress gate there); here the port alone, on each router's own address.
    local = [f"tcp/{ip}:{free_port()}" for ip in IPS]
    procs = []
    try:
        for i in (0, 1):
            log = (tmp_path / f"router{i}.log").open("wb")
            procs.append(subprocess.Popen([sys.executable, "-m", "swarm.supervise.router", "--listen", eps[i], "--listen", local[i],
                                           "--index", str(i),
                                           "--connect", eps[1 - i], "--keys", str(dirs[i + 1]), "--run", RUN, "--n-sats", "4"],
                                          stdout=subprocess.PIPE, stderr=log))
            log.close()
        for i, p in enumerate(procs):
            assert b"READY" in p.stdout.readline(), (tmp_path / f"router{i}.log").read_text()
        logs = [(tmp_path / f"router{i}.log").read_text() for i in (0, 1)]
        assert all("TLS certificate loaded" in x for x in logs), logs
        yield eps, ports, dirs, local
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_the_routers_mesh_over_mutual_tls_and_refuse_plain_tcp_and_passwords_alone(mesh):
    eps, ports, dirs, local = mesh
    driver, node0, node1 = dirs
    k = M.Keys(RUN)
    # The mesh carries a put on router 0 to a subscriber on router 1 (over mutual TLS between
    # them; each node's processes on its own router's local port).
    with _open(local[0], str(node0 / "world.json")) as world, _open(local[1], str(node1 / "agent-1.json")) as agent:
        witness = Witness(agent, k.clock())
        clock = M.encode(M.Clock(run=RUN, sender="world", k=1, t_s=1.0, live_agents=[1], mode="lockstep"))
        heard = False
        for _ in range(100):  # a subscription just declared takes a moment to cross the mesh
            world.put(k.clock(), clock)
            if witness.wait_for(lambda key, p: key == k.clock(), 0.1):
                heard = True
                break
        assert heard, "a clock put on router 0 never reached agent 1 on router 1"
    # A peer speaking plain TCP to a router's port, with a valid credential, is refused: the
    # port speaks TLS only. So is TLS without the run's CA (the certificate is not trusted).
    for ip, port, cred in ((IPS[0], ports[0], node0 / "world.json"), (IPS[1], ports[1], node1 / "agent-1.json")):
        with pytest.raises(zenoh.ZError):
            _open(f"tcp/{ip}:{port}", str(cred), timeout_ms=2000)
    bare = driver / "no-ca.json"
    bare.write_text(json.dumps({k2: v for k2, v in json.loads((driver / "observer.json").read_text()).items() if k2 != "ca"}))
    with pytest.raises(zenoh.ZError):
        _open(eps[0], str(bare), timeout_ms=2000)
    # A valid password and the run's CA but no client certificate (a stolen agent credential,
    # used from another host, around the node's gate): refused at the TLS handshake.
    for ep, cred in ((eps[0], node0 / "world.json"), (eps[1], node1 / "agent-1.json")):
        with pytest.raises(zenoh.ZError):
            _open(ep, str(cred), timeout_ms=2000)
    # The driver's certificate (public) shown with a key that is not its own (here router 1's):
    # refused; the key is what proves the certificate.
    forged = driver / "forged.json"
    forged.write_text(json.dumps({**json.loads((driver / "observer.json").read_text()), "private_key": "../node2/router.key"}))
    with pytest.raises(zenoh.ZError):
        _open(eps[0], str(forged), timeout_ms=2000)
    # The controls: the driver's credential (its client certificate) over TLS is let in; the
    # agent's on its node's local port too.
    _open(eps[0], str(driver / "observer.json"), timeout_ms=10_000).close()
    _open(local[1], str(node1 / "agent-1.json"), timeout_ms=10_000).close()
