"""`swarm run --cluster`: one swarm over a real 3-node Ray cluster on this machine.

Each node is a real `ray start` in a network namespace of its own (its own address on a
bridge the test makes, in a namespace of its own too; swarm/cluster/netns.py): nothing it
sends can leave the machine. On it, for real: 12 satellites whose numbers equal `swarm sim`'s
bit for bit while two nodes are cut apart for 10 s (iptables) and healed; a node killed
mid-run (every process of its namespace SIGKILLed, the raylet among them) whose agents are
started on the surviving nodes and rejoin, the run completing and its faults table saying
where each went; and Ctrl-C to `swarm run --cluster local-ray:2`, after which no process,
namespace or Ray session of it is left. Needs root (namespaces); slow (a cluster starts in
30-90 s on a loaded 2-core machine).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import zenoh
from test_run_signals import _read_json, _wait_for_step, wait_until

from swarm.api import load_scenario, run, simulate
from swarm.cluster.local import tagged_processes
from swarm.cluster.netns import can_make_hosts, leftovers

pytestmark = [pytest.mark.slow, pytest.mark.integration,
              pytest.mark.skipif(can_make_hosts() is not None, reason=str(can_make_hosts()))]

NUMBERS = ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean", "steps")


def twelve(**extra):
    """12 satellites, the full-swarm filter on the complete graph (every pair tracked, so
    every number of the summary is defined), paced so that a 10 s partition spans steps."""
    doc = {"name": "cluster12", "seed": 12, "n_sats": 12, "duration_s": 30, "graph": {"kind": "complete"},
           "initial": {"layout": "lattice", "spacing_m": 20.0, "position_max_m": 2.0, "drift_free": True},
           "emulator": {"lockstep_max_realtime_factor": 1.5}}
    doc.update(extra)
    return load_scenario(doc)


def test_ctrl_c_to_a_cluster_run_leaves_nothing_behind(tmp_path):
    """SIGINT to `swarm run --cluster local-ray:2` mid-run: exit 130, summary marked
    interrupted, and no process, namespace or Ray folder of it left."""
    scen = tmp_path / "s.yaml"
    scen.write_text(json.dumps({"name": "ctrlc", "seed": 2, "n_sats": 3, "duration_s": 600, "graph": {"kind": "complete"},
                                "emulator": {"lockstep_max_realtime_factor": 5.0}}))
    out = tmp_path / "run"
    before = set(leftovers())
    log = open(tmp_path / "swarm-run.log", "wb")  # noqa: SIM115 - the child writes to it; closed below
    tag = uuid.uuid4().hex  # in the environment of every process of the run (inherited): what to look for afterwards
    proc = subprocess.Popen([sys.executable, "-m", "swarm.cli", "run", str(scen), "--cluster", "local-ray:2", "--out", str(out)],
                            stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, SWARM_TEST_RUN=tag))
    try:
        info = wait_until(lambda: (j := _read_json(out / "run.json")) and "world" in j["pids"] and j, 400, "the run started")
        keys = info["keys"]
        _wait_for_step(info["endpoint"], info["run"], 5, 120, keys=keys)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()
    text = (tmp_path / "swarm-run.log").read_text(errors="replace")
    print(text[-2000:])
    assert proc.returncode == 130, text[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"]["reason"] == "SIGINT"
    assert set(leftovers()) <= before, leftovers()
    assert wait_until(lambda: not tagged_processes("SWARM_TEST_RUN", tag), 30, "every process of the cluster run gone")
    assert not Path(keys).exists()


@pytest.fixture(scope="module")
def cluster():
    from swarm.cluster.local import LocalRayCluster

    t0 = time.time()
    c = LocalRayCluster(3, log=print)
    try:
        c.start()
        print(f"3-node cluster up in {time.time() - t0:.1f} s: {c.node_ips}")
        yield c
    finally:
        c.close()
    assert c.hosts is not None and leftovers(c.hosts.tag) == [], leftovers(c.hosts.tag)
    assert not Path(c.tmp).exists()
    assert wait_until(lambda: not c.processes(), 30, "every process of the cluster gone")


def _faults(summary: dict, action: str) -> list[dict]:
    return [f for f in summary.get("faults", []) if f["action"] == action and f["phase"] == "done"]


def _tls_only(sw) -> dict:
    """While the run flies (on_start): every router of the cluster speaks mutual TLS only on
    its host's address. A session with a valid credential but plain TCP to a router's port is
    refused; so is one over TLS with an agent's credential (a valid password, the run's CA,
    no client certificate: a stolen agent credential used from another host, around the node's
    ingress gate); the driver's credential (its client certificate) over TLS is let in on the
    head's (the control: the refusals are not some other fault)."""
    from forgery import _open

    info = json.loads((sw.out / "run.json").read_text())
    seen = {"tls": info["tls"], "routers": list(info["routers"]), "refused": [], "refused_tls": [], "admitted": []}
    for j, ep in enumerate(info["routers"]):
        # A credential that router knows: one of its node's agents', read from that node's
        # private folder (a test on one machine can; nothing else does).
        agent = next(Path("/tmp").glob(f"swarm-node-{info['run']}-{j}-*/keys/agent-{j}.json"))
        scheme, _, addr = ep.partition("/")
        try:
            _open(f"tcp/{addr}", str(agent), timeout_ms=2000).close()
        except zenoh.ZError:
            seen["refused"].append(f"tcp/{addr}")
        if scheme == "tls":
            try:
                _open(ep, str(agent), timeout_ms=2000).close()
            except zenoh.ZError:
                seen["refused_tls"].append(ep)
            if j == 0:
                with contextlib.suppress(zenoh.ZError):
                    _open(ep, str(Path(info["keys"]) / "observer.json"), timeout_ms=20_000).close()
                    seen["admitted"].append(ep)
    sw.tls_check = seen
    return seen


def test_twelve_satellites_over_three_nodes_equal_swarm_sim_through_a_partition(cluster, tmp_path):
    """Bit for bit `swarm sim` through a 10 s partition of nodes 1 and 2; the routers' mesh is
    mutual TLS (a plain-TCP peer and an agent's credential over TLS are refused by every
    router), every process reaches its node's router through the node's ingress gate."""
    sc = twelve(faults=[{"at_step": 4, "action": "partition-nodes", "target": 1, "peer": 2, "down_s": 10.0}])
    t0 = time.monotonic()
    checked: dict = {}
    res = run(sc, out=tmp_path / "run", cluster=cluster, log=print, on_start=lambda sw: checked.update(_tls_only(sw)))
    wall = time.monotonic() - t0
    assert res.outcome.exit_code == 0, res.outcome
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    print(f"TLS: {checked}")
    assert checked["tls"] and all(ep.startswith("tls/") for ep in info["routers"]), checked
    assert checked["refused"] == [f"tcp/{ep.split('/', 1)[1]}" for ep in info["routers"]], checked
    assert checked["refused_tls"] == info["routers"] and checked["admitted"] == info["routers"][:1], checked
    # Every process of a node reached its router through the node's ingress gate (each identity
    # at its own loopback port), and the gates held, cut and refused nothing of an honest run.
    gate = res.summary["router_gate"]
    print(f"gate: { {k: (c['connections'], c['messages_in']) for k, c in gate.items()} }")
    for name in ("world", "recorder", *(f"agent-{i}" for i in range(12))):  # (no selector: the graph is complete)
        assert gate[name]["connections"] >= 1, (name, gate.get(name))
    assert not [k for k, c in gate.items() if c["held"] or c["cut"] or c["refused"]], gate
    logs = tmp_path / "run" / "logs"
    for name in ("router", "router-1", "router-2"):  # each router loaded its own node's certificate
        assert "TLS certificate loaded" in (logs / f"{name}.log").read_text(errors="replace"), name
    print(f"12 satellites over 3 nodes: {wall:.1f} s wall; start-up {info['startup_s']}")
    # Every node took part, each with the address of its own namespace, agents spread over all.
    assert [n["ip"] for n in info["nodes"]] == cluster.node_ips
    assert {info["placement"][f"agent-{i}"] for i in range(12)} == {0, 1, 2}
    assert info["placement"]["world"] == info["placement"]["recorder"] == 0
    # The partition was made and healed after its 10 s.
    done = _faults(res.summary, "partition-nodes")
    assert len(done) == 2 and "cut apart" in done[0]["detail"] and "healed after" in done[1]["detail"], done
    healed_s = float(done[1]["detail"].split("healed after ")[1].split(" s")[0])
    assert 10.0 <= healed_s < 20.0, healed_s
    # Bit for bit the in-process simulator's numbers.
    ref = simulate(sc).summary
    for key in NUMBERS:
        assert res.summary[key] == ref[key], key
    assert res.recording.alive.all()
    # Nothing of the run left: its nodes' folders (credentials) and its keys are gone.
    assert not list(Path("/tmp").glob(f"swarm-node-{info['run']}-*"))
    assert info["keys"] and not Path(info["keys"]).exists()


def test_a_node_killed_mid_run_its_agents_restart_elsewhere_and_the_run_completes(cluster, tmp_path):
    sc = twelve(duration_s=20, faults=[{"at_step": 6, "action": "kill-node", "target": 2}])
    try:
        res = run(sc, out=tmp_path / "run", cluster=cluster, log=print)
    finally:  # the host comes back for the module's other tests (whatever their order)
        if 2 in cluster.down:
            cluster.restart(2)
    assert res.outcome.exit_code == 0 and not res.summary.get("interrupted"), res.outcome
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert [n["alive"] for n in info["nodes"]] == [True, True, False]
    lost = [i for i in range(12) if i % 3 == 2]  # spread: satellite i on node i mod 3
    moves = _faults(res.summary, "kill-node")
    print("\n".join(f["detail"] for f in moves))
    assert moves[-1]["detail"].startswith(f"node 2 ({cluster.node_ips[2]}) killed") and f"{len(lost)} agent(s)" in moves[-1]["detail"]
    for i in lost:  # the table names each agent's new place
        line = next(f["detail"] for f in moves if f["detail"].startswith(f"node 2: agent {i} → node "))
        j = int(line.split("→ node ")[1].split()[0])
        assert j in (0, 1) and info["placement"][f"agent-{i}"] == j and cluster.node_ips[j] in line
    # Each moved agent flew again: every satellite has its estimate at the last step.
    alive = res.recording.alive
    assert alive[-1].all(), alive.sum(axis=1)
    # The world waited for them at the fault's step; a scheduled kill is reproducible in count.
    assert res.summary["steps"] == sc.steps


def test_without_the_gate_every_process_connects_on_its_hosts_loopback(cluster, tmp_path):
    """`emulator.gate: false` on a TLS cluster: the routers' TLS listeners take only the mesh
    and the driver (mutual TLS), so each router also listens on its host's loopback (which no
    other host reaches) and every process of the node connects there, a program of another
    language (`--agent I=COMMAND`: the contract's Python agent, `python -m
    sat_agent.from_env`, run by the host actor under the lifeline) as a native agent; every
    satellite flies every step and the run equals `swarm sim` bit for bit. (With the gate,
    the default, the other tests of this module: every process through its node's gate.)"""
    sc = twelve(n_sats=4, duration_s=12, emulator={"lockstep_max_realtime_factor": 1.5, "gate": False})
    res = run(sc, out=tmp_path / "run", cluster=cluster, agents={1: f"{sys.executable} -m sat_agent.from_env"}, log=print)
    assert res.outcome.exit_code == 0, res.outcome
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["tls"] and all(ep.startswith("tls/") for ep in info["routers"])
    assert info["placement"]["agent-1"] == 1 and res.recording.alive.all()
    assert "router_gate" not in res.summary
    for name in ("agent-1", "agent-2"):  # the foreign one and a native one
        log = (tmp_path / "run" / "logs" / f"{name}.log").read_text(errors="replace")
        assert "tcp/127.0.0.1:" in log and "tls/" not in log, log[-2000:]
    ref = simulate(sc).summary
    for key in NUMBERS:
        assert res.summary[key] == ref[key], key


def test_a_foreign_agent_is_owned_by_its_nodes_host(cluster, tmp_path):
    """`--agent I=COMMAND` over the cluster: satellite 1 flown by the Rust agent, started by
    node 1's host actor under the lifeline (it owns it), its credential only there; it flies
    every step and is gone with the run."""
    from rust_build import build

    agent = build("rust-agent", "swarm-rust-agent")
    sc = load_scenario(Path(__file__).resolve().parents[1] / "scenarios" / "demo.yaml", overrides=["estimator.kind=ci", "duration_s=15"])
    res = run(sc, out=tmp_path / "run", cluster=cluster, agents={1: str(agent)}, log=print)
    assert res.outcome.exit_code == 0, res.outcome
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["placement"]["agent-1"] == 1
    assert res.recording.alive[:, 1].all()
    log = (tmp_path / "run" / "logs" / "agent-1.log").read_text(errors="replace")
    assert log.strip(), "the Rust agent's log came back from node 1"


def test_a_chaos_campaign_over_the_cluster_kills_a_node_and_holds_its_invariants(cluster, tmp_path):
    """`swarm chaos --cluster ray://HEAD:10001` (the module's cluster, as real hosts are
    reached: kill-node is its host actor's SIGKILL of the run's processes and of its raylet):
    seed 2 draws a camera episode, node 2 killed at step 13 (its agents 2, 5, 8, 11 moved to
    the survivors) and agent 9 killed and restarted after it. The campaign's invariants hold,
    the exit status is 0, and the node-faults table names each agent's new node."""
    from swarm.cluster.swarm import cluster_shape

    # The module's earlier tests may have just started node 2 again: wait until Ray has it.
    wait_until(lambda: cluster_shape(cluster.address)[0] == 3, 120, "the cluster's 3 nodes alive")
    scen = tmp_path / "cluster12.yaml"
    scen.write_text(json.dumps(twelve().model_dump(mode="json")))
    out = tmp_path / "chaos"
    cmd = [sys.executable, "-m", "swarm.cli", "chaos", str(scen), "--cluster", cluster.address, "--faults", "3", "--seed", "2",
           "--kind", "kill-node", "--kind", "kill-agent", "--kind", "camera", "--out", str(out)]
    t0 = time.monotonic()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=1200, env=dict(os.environ, COLUMNS="200"))
    finally:  # a node killed by the campaign comes back for the module's other tests
        info = json.loads((out / "run" / "run.json").read_text()) if (out / "run" / "run.json").exists() else {"nodes": []}
        for nd in info["nodes"]:
            if not nd["alive"]:
                cluster.kill(nd["index"])  # whatever its death left in its namespace
                cluster.restart(nd["index"])
    print(p.stdout[-3000:], p.stderr[-8000:])
    print(f"campaign: {time.monotonic() - t0:.1f} s wall")
    doc = json.loads((out / "chaos.json").read_text())
    assert p.returncode == 0 and doc["ok"], [i for i in doc["invariants"] if not i["ok"]]
    assert [i["name"][0] for i in doc["invariants"]] == ["a", "b", "c", "d", "e"]
    assert doc["extra"]["cluster"]["nodes"] == 3
    kills = [e for e in doc["schedule"] if e["kind"] == "kill-node"]
    assert [(e["start"], e["target"], e["sats"]) for e in kills] == [(13, 2, [2, 5, 8, 11])]
    assert doc["fired"]["kill-node"] == {"scheduled": 1, "fired": 1} and doc["recovery"]["kill-node"]["n"] == 1
    # The node-faults table (chaos.json and the terminal) names the node and each agent's new place.
    lines = [f["detail"] for f in doc["extra"]["cluster"]["node_faults"] if f["action"] == "kill-node"]
    assert lines[-1].startswith(f"node 2 ({cluster.node_ips[2]}) killed") and "4 agent(s)" in lines[-1], lines
    for i in (2, 5, 8, 11):
        line = next(x for x in lines if x.startswith(f"node 2: agent {i} → node "))
        j = int(line.split("→ node ")[1].split()[0])
        assert j in (0, 1) and info["placement"][f"agent-{i}"] == j and cluster.node_ips[j] in line
        assert f"agent {i} → node {j}" in p.stderr  # (the CLI writes to stderr)
    assert [nd["alive"] for nd in info["nodes"]] == [True, True, False]
    assert info.get("left_on_nodes") == {}
    assert not list(Path("/tmp").glob(f"swarm-node-{info['run']}-*")) and not Path(info["keys"]).exists()
