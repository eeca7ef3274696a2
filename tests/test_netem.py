"""`swarm fault --compose netem`: its arguments, its message, and the fallback delayer for
kernels without netem, run for real in two network namespaces joined by a veth pair.

The container test (a compose swarm with one satellite impaired) is in test_compose.py.
"""

import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from swarm.record.recording import BusTimes
from swarm.supervise.netem import netemd_args, tc_script
from swarm.supervise.netemd import Delayer
from swarmcore.scenario import NETWORK_FAULTS, FaultSpec
from swarmrt.bus import messages as M
from swarmrt.netem import CLEAR, Netem, NetemError, parse_percent, parse_rate_bit_s, parse_time_s

ROOT = Path(__file__).resolve().parents[1]
H = dict(run="t-1", sender="cli", k=3, t_s=3.0)


@pytest.mark.parametrize(
    "text,value",
    [("200ms", 0.2), ("0.2s", 0.2), ("200 msec", 0.2), ("500us", 5e-4), ("1.5s", 1.5), ("0ms", 0.0), ("60s", 60.0)],
)
def test_times_take_tc_units(text, value):
    assert parse_time_s("--delay", text) == pytest.approx(value, abs=1e-12)


@pytest.mark.parametrize(
    "text,value", [("1mbit", 10**6), ("500kbit", 500_000), ("2gbit", 2 * 10**9), ("100kbps", 800_000), ("1000bit", 1000)]
)
def test_rates_take_tc_units_and_bps_means_bytes(text, value):
    assert parse_rate_bit_s("--rate", text) == value


@pytest.mark.parametrize(
    "fn,name,text,reason",
    [
        (parse_time_s, "--delay", "200", "give a time with a unit"),
        (parse_time_s, "--delay", "200 minutes", "give a time with a unit"),
        (parse_time_s, "--jitter", "-5ms", "give a time with a unit"),
        (parse_time_s, "--delay", "61s", "between 0 and 60 s"),
        (parse_percent, "--loss", "10", "with %"),
        (parse_percent, "--loss", "0.1", "with %"),
        (parse_percent, "--loss", "101%", "between 0% and 100%"),
        (parse_rate_bit_s, "--rate", "1mb", "give a rate with a unit"),
        (parse_rate_bit_s, "--rate", "10bit", "between 1kbit and 100gbit"),
        (parse_rate_bit_s, "--rate", "200gbit", "between 1kbit and 100gbit"),
    ],
)
def test_bad_arguments_fail_naming_the_argument(fn, name, text, reason):
    with pytest.raises(NetemError) as e:
        fn(name, text)
    assert name in str(e.value) and repr(text) in str(e.value) and reason in str(e.value)


def test_canonical_arguments_round_trip():
    n = Netem.from_cli("0.2s", "50ms", "10%", "1000kbit")
    assert n.args() == "delay 200ms 50ms loss 10% rate 1mbit"
    assert Netem.parse(n.args()) == n
    for cli in [("250us", None, None, None), (None, None, "0.5%", None), (None, None, None, "1500bit"), ("1s", "0ms", "100%", "3gbit")]:
        n = Netem.from_cli(*cli)
        assert Netem.parse(n.args()).args() == n.args()
    assert Netem.from_cli("250us").args() == "delay 250us"
    assert Netem.from_cli(rate="1500bit").args() == "rate 1500bit"


def test_incomplete_impairments_are_refused():
    with pytest.raises(NetemError, match="at least one of --delay, --loss, --rate"):
        Netem.from_cli()
    with pytest.raises(NetemError, match="--jitter needs --delay"):
        Netem.from_cli(jitter="5ms", loss="1%")


def test_the_fault_message_carries_canonical_netem_arguments():
    from swarmrt.netem import validate_field

    args = validate_field("delay 0.2s 50ms loss 10% rate 1000kbit")
    assert args == "delay 200ms 50ms loss 10% rate 1mbit"
    f = M.Fault(**H, action="netem", phase="command", target=3, netem=args)
    assert M.decode("fault", M.encode(f)) == f
    c = M.Fault(**H, action="netem", phase="command", target=3, netem=CLEAR)
    assert M.decode("fault", M.encode(c)) == c
    for fields, reason in [
        ({}, "action netem needs netem"),
        ({"netem": "loss 200%"}, "netem: .*loss '200%'"),
        ({"netem": "loss 1% ; rm -rf /"}, "netem: .*unexpected ';'"),
        ({"netem": "delay 0.2s"}, "not in canonical form"),
    ]:
        raw = M.encode(M.Fault(**H, action="netem", phase="command", target=3, **fields))
        with pytest.raises(M.MessageError, match=reason):
            M.decode("fault", raw)


def test_netem_is_a_compose_only_network_fault():
    assert "netem" in NETWORK_FAULTS
    with pytest.raises(ValueError, match="swarm fault --compose"):
        FaultSpec(at_step=3, action="netem", target=1)


def test_helper_scripts_are_the_tc_commands():
    s = tc_script("delay 200ms 50ms loss 10% rate 1mbit")
    assert "tc qdisc replace dev $d root netem delay 200ms 50ms loss 10% rate 1mbit" in s
    c = tc_script(CLEAR)
    assert "tc qdisc del dev $d root" in c and "iptables -w -X SWARM_NETEM" in c
    assert netemd_args("delay 200ms 50ms loss 10% rate 1mbit") == [
        "--delay-s", "0.2", "--jitter-s", "0.05", "--loss-pct", "10.0", "--rate-bit-s", "1000000"]
    with pytest.raises(NetemError):
        tc_script("delay 200ms; reboot")


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "swarm.cli", "fault", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    "args,reason",
    [
        (("netem", "3", "--delay", "200"), "--delay '200': give a time with a unit"),
        (("netem", "3", "--loss", "10"), "--loss '10': give a percentage with %"),
        (("netem", "3", "clean"), "the only word after SAT is 'clear'"),
        (("netem", "3", "clear", "--delay", "1ms"), "'clear' takes no"),
        (("netem", "3", "--delay", "200ms"), "netem needs --compose"),
    ],
)
def test_cli_refuses_bad_netem_arguments(tmp_path, args, reason):
    (tmp_path / "run.json").write_text('{"endpoint": "tcp/127.0.0.1:9", "run": "x", "n_sats": 4}')
    p = _cli("--run-dir", str(tmp_path), *args)
    out = " ".join((p.stdout + p.stderr).split())
    assert p.returncode == 2 and reason in out, out


def test_the_delayer_is_a_fifo_link_with_bounded_jitter():
    d = Delayer(0.2, 0.05, seed=1)
    arrivals = np.cumsum(np.full(2000, 0.003))
    out = np.array([d.release_at(a) for a in arrivals])
    wait = out - arrivals
    assert np.all(np.diff(out) >= 0)  # never reorders
    assert wait.min() >= 0.15 - 1e-12 and wait.max() <= 0.25 + 1e-12
    spaced = Delayer(0.2, 0.05, seed=1)
    w = np.array([spaced.release_at(a) - a for a in np.arange(500) * 1.0])  # far apart: no queueing
    assert abs(w.mean() - 0.2) < 0.005 and w.min() >= 0.15 and w.max() <= 0.25
    again = Delayer(0.2, 0.05, seed=1)
    assert [again.release_at(a) for a in arrivals[:50]] == list(out[:50])


def test_bus_latency_statistics_per_sender():
    t0 = 1_800_000_000_000_000_000
    pub = np.array([0, 10, 20, 30, 40, 50]) * 1_000_000 + t0
    lat = np.array([1, 2, 3, 200, 210, 0]) * 1_000_000
    b = BusTimes(np.array(["world", "world", "world", "agent-3", "agent-3", "agent-3"]), np.array(["clock"] * 6),
                 np.arange(6), pub, pub + lat)
    s = b.latency_stats()
    assert s["world"] == {"n": 3, "min": 1.0, "p50": 2.0, "p95": 2.9, "max": 3.0}
    assert s["agent-3"]["n"] == 2 and s["agent-3"]["min"] == 200.0 and s["agent-3"]["unstamped"] == 1
    assert b.latency_stats(published_from_ns=t0 + 25_000_000) == {"agent-3": {"n": 2, "min": 200.0, "p50": 205.0, "p95": 209.5, "max": 210.0, "unstamped": 1}}


# -- the fallback delayer, for real ----------------------------------------------------------

def _ip(*args, check=True):
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


@pytest.fixture
def two_namespaces():
    """Namespaces A (10.201.0.1) and B (10.201.0.2) joined by a veth pair: traffic that
    never leaves this machine, on an interface that is not lo (the delayer leaves lo alone)."""
    if os.geteuid() != 0 or not all(shutil.which(x) for x in ("ip", "iptables", "tc")):
        pytest.skip("needs root, ip, iptables and tc")
    tag = uuid.uuid4().hex[:6]
    a, b = f"swa{tag}", f"swb{tag}"
    if _ip("netns", "add", a, check=False).returncode != 0:
        pytest.skip("cannot create network namespaces here")
    try:
        _ip("netns", "add", b)
        _ip("link", "add", "va", "netns", a, "type", "veth", "peer", "name", "vb", "netns", b)
        for ns, dev, addr in ((a, "va", "10.201.0.1/24"), (b, "vb", "10.201.0.2/24")):
            _ip("-n", ns, "addr", "add", addr, "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield a, b
    finally:
        _ip("netns", "del", a, check=False)
        _ip("netns", "del", b, check=False)


_ECHO = r"""
import socket, sys, time
if sys.argv[1] == "serve":
    s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1); s.bind(("10.201.0.2", 9000)); s.listen()
    print("LISTENING", flush=True)
    while True:
        c, _ = s.accept(); c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while (d := c.recv(1 << 16)):
            c.sendall(d)
else:
    c = socket.create_connection(("10.201.0.2", 9000), timeout=30); c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    for size in map(int, sys.argv[2:]):
        t = time.monotonic(); c.sendall(b"x" * size); got = 0
        while got < size:
            got += len(c.recv(1 << 16))
        print(size, (time.monotonic() - t) * 1e3, flush=True)
"""


def _echo(ns, *sizes) -> list[tuple[int, float]]:
    p = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", _ECHO, "ask", *map(str, sizes)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return [(int(a), float(b)) for a, b in (ln.split() for ln in p.stdout.split("\n") if ln.strip())]


def _start_netemd(ns, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "swarm.supervise.netemd", *args], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=env)
    line = p.stdout.readline()  # blocks until READY (or the process ends)
    assert line.strip() == "READY", p.stderr.read() if p.poll() is not None else line
    return p


@pytest.mark.integration
def test_netemd_delays_what_a_namespace_sends_and_leaves_no_trace(two_namespaces):
    """Round trips A → B → A over TCP: with 200 ± 20 ms on A's egress every small round
    trip takes 180–260 ms; 200 kB still flows at TCP's pace (not ~2 packets per delay,
    which is what holding the kernel's packets would give, see swarm.supervise.netemd); after SIGTERM
    the rules are gone and round trips are fast again."""
    a, b = two_namespaces
    server = subprocess.Popen(["ip", "netns", "exec", b, sys.executable, "-c", _ECHO, "serve"], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "LISTENING"
        base = [ms for _s, ms in _echo(a, *[100] * 5)]
        d = _start_netemd(a, "--delay-s", "0.2", "--jitter-s", "0.02")
        try:
            rules = subprocess.run(["ip", "netns", "exec", a, "iptables", "-S", "SWARM_NETEM"], capture_output=True, text=True).stdout
            assert "NFQUEUE" in rules, rules
            small = [ms for _s, ms in _echo(a, *[100] * 20)]
            bulk = [ms for _s, ms in _echo(a, 200_000, 200_000, 200_000)]
        finally:
            d.terminate()
            d.wait(10)
        after = [ms for _s, ms in _echo(a, *[100] * 5)]
        rules_after = subprocess.run(["ip", "netns", "exec", a, "iptables", "-S"], capture_output=True, text=True).stdout
    finally:
        server.kill()
        server.wait()
    print(f"round trip ms: before {np.median(base):.1f}, delayed small min {min(small):.1f} p50 {np.median(small):.1f} "
          f"max {max(small):.1f}, 200 kB {[round(x) for x in bulk]}, after {np.median(after):.1f}")
    assert min(small) >= 180.0 and np.median(small) < 350.0, small
    assert min(bulk) < 4000.0, bulk  # a few round trips (TCP's window), not ~65 (13 s)
    assert "SWARM_NETEM" not in rules_after and np.median(after) < 100.0, (rules_after, after)


@pytest.mark.integration
def test_netemd_loss_and_rate_are_the_kernels(two_namespaces):
    a, _b = two_namespaces
    d = _start_netemd(a, "--loss-pct", "10", "--rate-bit-s", "1000000")
    try:
        rules = subprocess.run(["ip", "netns", "exec", a, "iptables", "-S", "SWARM_NETEM"], capture_output=True, text=True).stdout
        qdisc = subprocess.run(["ip", "netns", "exec", a, "tc", "qdisc", "show", "dev", "va"], capture_output=True, text=True).stdout
    finally:
        d.terminate()
        d.wait(10)
    assert "--mode random --probability 0.1" in rules and "NFQUEUE" not in rules, rules
    assert "tbf" in qdisc and "rate 1Mbit" in qdisc, qdisc
    left = subprocess.run(["ip", "netns", "exec", a, "tc", "qdisc", "show", "dev", "va"], capture_output=True, text=True).stdout
    assert "tbf" not in left, left
