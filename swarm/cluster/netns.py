"""Several "hosts" on one machine: a network namespace each, joined by a bridge.

A Ray cluster on one machine whose nodes each have an address of their own (what
``--cluster local-ray`` and the cluster tests make): the head node in the root network
namespace advertises the machine's interface address and its GCS listens on every
interface whatever ``--node-ip-address`` says (measured with ray 2.60: it replaces a
loopback address by the interface's), so each node, the head included, lives in a
network namespace of its own, where the only interfaces are its loopback and one end of a
veth pair; it advertises that address, and nothing it sends can leave the machine (the
namespaces have no default route: only the bridge's subnet is reachable)::

      root namespace (the driver: swarm run)      switch namespace         node namespaces
      <prefix>r0  10.A.B.1/24  ---veth--->   bridge <prefix>br  <---veth---  <prefix>n<i>  10.A.B.(10+i)

The bridge lives in a namespace of its own too, not in the root one: there Docker's
``FORWARD DROP`` policy (with ``bridge-nf-call-iptables``) would drop what crosses it,
and a rule to let it through would change the machine's firewall. A fresh namespace has
no rules. The subnet is one of 10.200.0.0–10.254.255.0/24 that no route of the root
namespace covers.

Faults act inside the namespaces: :meth:`Hosts.partition` cuts two hosts apart with
iptables (DROP both ways, in each host's own namespace; the kernel here has no netem),
:meth:`Hosts.kill` SIGKILLs every process in a host's namespace (a host that died: the
raylet and everything on it).

Ownership: :meth:`Hosts.close` SIGKILLs every process left in the namespaces and deletes
them (the veth pairs go with them). Should the process that made them die without
calling it (SIGKILL), a reaper process does it: ``python -m swarm.cluster.netns --reap``,
holding the read end of a pipe whose write end only the owner holds (the lifeline of
:mod:`swarm.supervise.lifeline`); it reads EOF when the owner is gone however it went,
and then cleans up. Needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN) and the ``ip`` command
(iproute2); ``iptables`` for partitions. Written by hand: no packaged library makes
throw-away namespaces with a bridge and cleans them up when its owner dies (pyroute2 is not
a dependency, and it would be the same calls).
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

__all__ = ["Host", "Hosts", "NetnsError", "can_make_hosts", "leftovers"]

#: Every name this module makes starts with it (namespaces, interfaces): what
#: :func:`leftovers` looks for.
PREFIX = "swr"


class NetnsError(RuntimeError):
    """Namespaces cannot be made here (not root, no ``ip``), or a command failed."""


def can_make_hosts() -> str | None:
    """None when this process can make namespaced hosts, else why not (one line)."""
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_NET_ADMIN): run as root, or join an existing cluster with --cluster ray://HOST:PORT"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is missing: apt-get install iproute2"
    return None


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    """``ip ARGS`` in the root namespace."""
    p = subprocess.run(["ip", *args], capture_output=True, text=True)
    if check and p.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {p.stderr.strip()}")
    return p


def _run_in(ns: str, *cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run(["ip", "netns", "exec", ns, *cmd], capture_output=True, text=True)
    if check and p.returncode != 0:
        raise NetnsError(f"in {ns}: {' '.join(cmd)}: {p.stderr.strip()}")
    return p


def _free_subnet() -> ipaddress.IPv4Network:
    """A /24 of 10.200.0.0/13.. that overlaps no route of the root namespace (nor a
    namespace of another run of this module: each has its own switch)."""
    used = []
    for line in subprocess.run(["ip", "-4", "route", "show", "table", "all"], capture_output=True, text=True).stdout.splitlines():
        word = line.split()[0] if line.split() else ""
        with contextlib.suppress(ValueError):
            if word not in ("default", "broadcast", "local") and "/" in word:
                used.append(ipaddress.ip_network(word, strict=False))
    for _ in range(200):
        net = ipaddress.IPv4Network(f"10.{200 + secrets.randbelow(55)}.{secrets.randbelow(256)}.0/24")
        if not any(net.overlaps(u) for u in used):
            return net
    raise NetnsError("no free 10.200-254.x.0/24 subnet for the namespaces")


@dataclass
class Host:
    """One namespaced host: its namespace, its address on the bridge."""

    index: int
    ns: str
    ip: str

    def cmd(self, *argv: str) -> list[str]:
        """``argv`` run inside this host's namespace."""
        return ["ip", "netns", "exec", self.ns, *argv]


@dataclass
class Hosts:
    """``n`` namespaced hosts on one bridge, the driver's side at :attr:`gateway`."""

    n: int
    tag: str = field(default_factory=lambda: secrets.token_hex(3))
    hosts: list[Host] = field(default_factory=list)
    gateway: str = ""  # the root namespace's address on the bridge
    subnet: str = ""
    _reaper: subprocess.Popen | None = None
    _lifeline_w: int | None = None
    _partitions: set[tuple[int, int]] = field(default_factory=set)
    _closed: bool = False

    @property
    def switch(self) -> str:
        return f"{PREFIX}{self.tag}sw"

    def names(self) -> list[str]:
        """Every namespace this makes (the switch last)."""
        return [h.ns for h in self.hosts] + [self.switch]

    def up(self) -> Hosts:
        """Make the namespaces, the bridge and the links; start the reaper first, so that
        whatever is made is deleted even if this process dies half-way."""
        if (why := can_make_hosts()) is not None:
            raise NetnsError(why)
        net = _free_subnet()
        self.subnet = str(net)
        addrs = list(net.hosts())
        self.gateway = str(addrs[0])
        self.hosts = [Host(i, f"{PREFIX}{self.tag}n{i}", str(addrs[9 + i])) for i in range(self.n)]
        self._start_reaper()
        try:
            sw = self.switch
            _ip("netns", "add", sw)
            _run_in(sw, "ip", "link", "set", "lo", "up")
            _run_in(sw, "ip", "link", "add", "br0", "type", "bridge")
            _run_in(sw, "ip", "link", "set", "br0", "up")
            # The driver's side: a veth from the root namespace to the bridge.
            root_if, peer = f"{PREFIX}{self.tag}r0", f"{PREFIX}{self.tag}r1"
            _ip("link", "add", root_if, "type", "veth", "peer", "name", peer, "netns", sw)
            _run_in(sw, "ip", "link", "set", peer, "master", "br0")
            _run_in(sw, "ip", "link", "set", peer, "up")
            _ip("addr", "add", f"{self.gateway}/{net.prefixlen}", "dev", root_if)
            _ip("link", "set", root_if, "up")
            for h in self.hosts:
                _ip("netns", "add", h.ns)
                _run_in(h.ns, "ip", "link", "set", "lo", "up")
                a, b = f"{PREFIX}{self.tag}h{h.index}", "eth0"
                _run_in(sw, "ip", "link", "add", a, "type", "veth", "peer", "name", b, "netns", h.ns)
                _run_in(sw, "ip", "link", "set", a, "master", "br0")
                _run_in(sw, "ip", "link", "set", a, "up")
                _run_in(h.ns, "ip", "addr", "add", f"{h.ip}/{net.prefixlen}", "dev", "eth0")
                _run_in(h.ns, "ip", "link", "set", "eth0", "up")
        except BaseException:
            self.close()
            raise
        return self

    def _start_reaper(self) -> None:
        r, w = os.pipe()
        os.set_inheritable(w, False)
        cmd = [sys.executable, "-m", "swarm.cluster.netns", "--reap", "--fd", str(r), "--tag", self.tag,
               "--namespaces", ",".join([f"{PREFIX}{self.tag}n{i}" for i in range(self.n)] + [self.switch]),
               "--interface", f"{PREFIX}{self.tag}r0"]
        self._reaper = subprocess.Popen(cmd, pass_fds=(r,), stdin=subprocess.DEVNULL, start_new_session=True)
        os.close(r)
        self._lifeline_w = w

    # -- faults -----------------------------------------------------------------------
    def partition(self, a: int, b: int) -> None:
        """Cut hosts a and b apart: every packet between their addresses dropped, both ways,
        in each one's namespace (iptables; TCP connections stall, as over a dead link)."""
        for x, y in ((a, b), (b, a)):
            hx, hy = self.hosts[x], self.hosts[y]
            for chain, flag in (("OUTPUT", "-d"), ("INPUT", "-s")):
                _run_in(hx.ns, "iptables", "-w", "-I", chain, flag, hy.ip, "-j", "DROP")
        self._partitions.add((min(a, b), max(a, b)))

    def heal(self, a: int, b: int) -> None:
        """Undo :meth:`partition` of a and b."""
        for x, y in ((a, b), (b, a)):
            hx, hy = self.hosts[x], self.hosts[y]
            for chain, flag in (("OUTPUT", "-d"), ("INPUT", "-s")):
                _run_in(hx.ns, "iptables", "-w", "-D", chain, flag, hy.ip, "-j", "DROP", check=False)
        self._partitions.discard((min(a, b), max(a, b)))

    def count_links(self, ports: list[int]) -> None:
        """Byte counters (iptables, chain SWARM_ACCT in each host's namespace) of what each
        host sends to each other host: over the Zenoh routers' links (TCP to or from router
        port ``ports[j]`` of host j, or from its own) and everything else (Ray's own)."""
        for h in self.hosts:
            _run_in(h.ns, "iptables", "-w", "-N", "SWARM_ACCT")
            _run_in(h.ns, "iptables", "-w", "-I", "OUTPUT", "-j", "SWARM_ACCT")
            for o in self.hosts:
                if o.index == h.index:
                    continue
                for flag, port in (("--dport", ports[o.index]), ("--sport", ports[h.index])):
                    _run_in(h.ns, "iptables", "-w", "-A", "SWARM_ACCT", "-d", o.ip, "-p", "tcp", flag, str(port),
                            "-m", "comment", "--comment", f"zenoh {o.index}", "-j", "RETURN")
                _run_in(h.ns, "iptables", "-w", "-A", "SWARM_ACCT", "-d", o.ip, "-m", "comment", "--comment", f"other {o.index}",
                        "-j", "RETURN")

    def link_bytes(self) -> dict[str, int]:
        """``"i->j zenoh"`` / ``"i->j other"`` → bytes host i has sent host j so far (see
        :meth:`count_links`; IP packets, headers included)."""
        out: dict[str, int] = {}
        for h in self.hosts:
            p = _run_in(h.ns, "iptables", "-w", "-L", "SWARM_ACCT", "-v", "-x", "-n", check=False)
            for line in p.stdout.splitlines():
                if "/* " not in line:
                    continue
                f = line.split()
                kind, j = line.split("/* ")[1].split(" */")[0].split()
                key = f"{h.index}->{j} {kind}"
                out[key] = out.get(key, 0) + int(f[1])
        return out

    def pids(self, i: int) -> list[int]:
        """Every process in host i's namespace."""
        return _ns_pids(self.hosts[i].ns)

    def kill(self, i: int) -> list[int]:
        """SIGKILL every process of host i (a host that died); returns their pids."""
        return _kill_ns(self.hosts[i].ns)

    # -- the end ----------------------------------------------------------------------
    def close(self) -> None:
        """Kill whatever runs in the namespaces and delete them (idempotent)."""
        if self._closed:
            return
        self._closed = True
        _teardown(self.names(), f"{PREFIX}{self.tag}r0")
        if self._lifeline_w is not None:
            os.close(self._lifeline_w)  # the reaper reads EOF, finds nothing left, and exits
            self._lifeline_w = None
        if self._reaper is not None:
            try:
                self._reaper.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._reaper.kill()
                self._reaper.wait()

    def __enter__(self) -> Hosts:
        return self.up()

    def __exit__(self, *exc) -> None:
        self.close()


def _ns_pids(ns: str) -> list[int]:
    p = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
    return [int(x) for x in p.stdout.split() if x.isdigit()]


def _kill_ns(ns: str) -> list[int]:
    """SIGKILL every process in namespace ``ns`` until none is left (a process may fork
    while we kill: bounded rounds)."""
    killed: list[int] = []
    for _ in range(50):
        pids = [p for p in _ns_pids(ns) if p != os.getpid()]
        if not pids:
            break
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        # A SIGKILLed process leaves the namespace when the kernel has torn it down: wait
        # for that (bounded), not a fixed time.
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and set(_ns_pids(ns)) & set(pids):
            threading.Event().wait(0.02)
    return killed


def _teardown(namespaces: list[str], root_if: str | None) -> None:
    present = set(_list_namespaces())
    for ns in namespaces:
        if ns in present:
            _kill_ns(ns)
    for ns in namespaces:
        if ns in present:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
    if root_if is not None:  # gone with its peer's namespace; only if that failed
        subprocess.run(["ip", "link", "del", root_if], capture_output=True)


def _list_namespaces() -> list[str]:
    p = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
    return [line.split()[0] for line in p.stdout.splitlines() if line.strip()]


def leftovers(tag: str = "") -> list[str]:
    """Namespaces and root interfaces of this module (of the :class:`Hosts` with ``tag``)
    that still exist (tests: none after a run)."""
    out = [ns for ns in _list_namespaces() if ns.startswith(PREFIX + tag)]
    p = subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True)
    out += [line.split(":")[1].strip().split("@")[0] for line in p.stdout.splitlines()
            if line.split(":")[1].strip().startswith(PREFIX + tag)] if p.returncode == 0 else []
    return out


def _reap(fd: int, namespaces: list[str], interface: str | None) -> None:
    """The reaper: wait for the owner to go (EOF on the lifeline), then clean up."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C in the terminal is the owner's to handle
    try:
        while os.read(fd, 4096):
            pass
    except OSError:
        pass
    _teardown(namespaces, interface)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="clean up namespaced hosts once their owner is gone")
    p.add_argument("--reap", action="store_true", required=True)
    p.add_argument("--fd", type=int, required=True)
    p.add_argument("--tag", required=True)
    p.add_argument("--namespaces", required=True)
    p.add_argument("--interface", default=None)
    a = p.parse_args(argv)
    _reap(a.fd, [x for x in a.namespaces.split(",") if x], a.interface)
    return 0


if __name__ == "__main__":
    sys.exit(main())
