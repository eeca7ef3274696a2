"""A packet delayer for kernels without netem: NFQUEUE, held verdicts, iptables, tc tbf.
This module owns the fallback daemon (``python -m swarm.supervise.netemd`` in a helper
container, started by :mod:`swarm.supervise.faults`); the argument grammar is
:mod:`swarmrt.netem`'s, the ``tc`` netem commands and this daemon's arguments
(``netemd_args``) :mod:`swarm.supervise.netem`'s.

``swarm fault --compose netem`` uses the kernel's netem qdisc (:mod:`swarm.supervise.netem`). Some
kernels are built without it (``CONFIG_NET_SCH_NETEM`` unset: ``tc`` answers "Specified
qdisc kind is unknown"; the micro-VM kernels of some CI machines, this project's own
build machine among them). This process builds the same impairment from what such
kernels usually do have, in the network namespace it runs in (a helper container started
with ``--network container:<agent> --cap-add NET_ADMIN``):

- loss: ``iptables -A SWARM_NETEM ! -o lo -m statistic --mode random --probability p -j DROP``
  (the kernel's own random drop of each outgoing packet, as netem's ``loss p``);
- delay and jitter: ``iptables -A SWARM_NETEM ! -o lo -j NFQUEUE --queue-num Q --queue-bypass``
  hands every outgoing packet's metadata to this process over netlink; it gives the
  kernel its verdict (accept) only at ``t_arrival + delay + u``, ``u`` uniform in
  ``[−jitter, +jitter]`` (netem's default jitter), and never before the packet ahead of
  it (one FIFO, like a radio link's queue: netem instead reorders when jitter exceeds the
  packet spacing). The packet itself stays in the kernel; ``--queue-bypass`` lets packets
  through untouched should this process die;
- rate: ``tc qdisc replace dev D root tbf rate R burst B latency 2s`` on every interface
  but lo (a token bucket: netem's ``rate`` without its per-packet overhead options).

The order is netem's: loss, then delay, then the rate-limited queue. SIGTERM removes the
rules and the tbf, lets the packets already held leave when they are due, and exits.
``python -m swarm.supervise.netemd --delay-s 0.2 --jitter-s 0.05 --loss-pct 10 --rate-bit-s 1000000``
prints ``READY`` once the rules are in place.

The NFQUEUE netlink protocol (``linux/netfilter/nfnetlink_queue.h``) is spoken here
with the standard library's ``socket.AF_NETLINK``: a Python binding (NetfilterQueue)
needs libnetfilter-queue and a C build in the image, for four message layouts.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import time

from swarmcore.streams import stream

log = logging.getLogger("netemd")

__all__ = ["NfQueue", "Delayer", "main", "CHAIN"]

#: The iptables chain of the impairment (jumped to from OUTPUT); ``clear`` deletes it.
CHAIN = "SWARM_NETEM"

# linux/netlink.h, linux/netfilter/nfnetlink.h, nfnetlink_queue.h
_NETLINK_NETFILTER = 12
_NLM_F_REQUEST, _NLM_F_ACK = 0x1, 0x4
_NLMSG_ERROR = 2
_NFNL_SUBSYS_QUEUE = 3
_NFQNL_MSG_PACKET, _NFQNL_MSG_VERDICT, _NFQNL_MSG_CONFIG = 0, 1, 2
_NFQA_PACKET_HDR, _NFQA_VERDICT_HDR, _NFQA_PAYLOAD = 1, 2, 10
_NFQA_CFG_CMD, _NFQA_CFG_PARAMS, _NFQA_CFG_QUEUE_MAXLEN = 1, 2, 3
_NFQNL_CFG_CMD_BIND, _NFQNL_CFG_CMD_UNBIND = 1, 2
_NFQNL_COPY_PACKET = 2
_NF_DROP = 0
_SO_MARK, _SO_RCVBUFFORCE = 36, 33
_HDR = struct.Struct("=IHHII")  # nlmsghdr (host byte order)
_NFGEN = struct.Struct("!BBH")  # nfgenmsg: family, version, res_id (big-endian queue number)
_ATTR = struct.Struct("=HH")  # nlattr: length, type
#: Packets this process sends carry this mark; the chain lets them through.
MARK = 0x5EED


def _attr(kind: int, payload: bytes) -> bytes:
    n = _ATTR.size + len(payload)
    return _ATTR.pack(n, kind) + payload + b"\0" * (-n % 4)


class NfQueue:
    """One bound NFQUEUE in copy-packet mode: ``packets()`` takes the queued IPv4 packets
    (the kernel then frees them at once, see :meth:`packets`) and :meth:`send` puts one
    back on the wire, marked so the chain does not queue it again."""

    def __init__(self, queue: int, maxlen: int = 8192):
        self.queue = queue
        self.sock = socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, _NETLINK_NETFILTER)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, 16 << 20)
        except OSError:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        self.sock.bind((0, 0))
        self.seq = 0
        self._config(_attr(_NFQA_CFG_CMD, struct.pack("!BBH", _NFQNL_CFG_CMD_BIND, 0, socket.AF_INET)))
        self._config(_attr(_NFQA_CFG_PARAMS, struct.pack("!IB", 0xFFFF, _NFQNL_COPY_PACKET))
                     + _attr(_NFQA_CFG_QUEUE_MAXLEN, struct.pack("!I", maxlen)))
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)  # IP_HDRINCL
        self.raw.setsockopt(socket.SOL_SOCKET, _SO_MARK, MARK)

    def fileno(self) -> int:
        return self.sock.fileno()

    def _send(self, msg_type: int, flags: int, body: bytes) -> int:
        self.seq += 1
        payload = _NFGEN.pack(socket.AF_UNSPEC, 0, self.queue) + body
        self.sock.send(_HDR.pack(_HDR.size + len(payload), (_NFNL_SUBSYS_QUEUE << 8) | msg_type, flags, self.seq, 0) + payload)
        return self.seq

    def _config(self, body: bytes) -> None:
        """Send a configuration message and wait for the kernel's acknowledgement."""
        seq = self._send(_NFQNL_MSG_CONFIG, _NLM_F_REQUEST | _NLM_F_ACK, body)
        while True:
            data = self.sock.recv(65536)
            for mtype, mseq, payload in self._messages(data):
                if mtype == _NLMSG_ERROR and mseq == seq:
                    err = struct.unpack_from("=i", payload)[0]
                    if err:
                        raise OSError(-err, f"NFQUEUE {self.queue} configuration: {os.strerror(-err)}")
                    return

    @staticmethod
    def _messages(data: bytes):
        off = 0
        while off + _HDR.size <= len(data):
            length, mtype, _flags, seq, _pid = _HDR.unpack_from(data, off)
            if length < _HDR.size:
                break
            yield mtype, seq, data[off + _HDR.size : off + length]
            off += (length + 3) & ~3

    def packets(self) -> list[bytes]:
        """The packets of one read of the socket ([] if none), each answered at once with
        the verdict drop: the kernel frees its copy, so the sending socket's memory is
        released as netem releases it (``skb_orphan_partial``). Holding the verdict
        instead keeps every held packet charged to its TCP socket, and TCP Small Queues
        then lets ~2 packets per round trip out (measured: 200 KB over a 200 ms delay took
        13 s, not 2 s)."""
        try:
            data = self.sock.recv(16 << 20, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return []
        except OSError as exc:  # ENOBUFS: the kernel overran the socket and dropped those packets
            log.warning("NFQUEUE read: %s", exc)
            return []
        out = []
        for mtype, _seq, payload in self._messages(data):
            if mtype != (_NFNL_SUBSYS_QUEUE << 8) | _NFQNL_MSG_PACKET:
                continue
            off, pid, pkt = _NFGEN.size, None, None
            while off + _ATTR.size <= len(payload):
                n, kind = _ATTR.unpack_from(payload, off)
                if n < _ATTR.size:
                    break
                kind &= 0x3FFF
                if kind == _NFQA_PACKET_HDR:
                    pid = struct.unpack_from("!I", payload, off + _ATTR.size)[0]
                elif kind == _NFQA_PAYLOAD:
                    pkt = payload[off + _ATTR.size : off + n]
                off += (n + 3) & ~3
            if pid is None:
                continue
            self._send(_NFQNL_MSG_VERDICT, _NLM_F_REQUEST, _attr(_NFQA_VERDICT_HDR, struct.pack("!II", _NF_DROP, pid)))
            if pkt is not None and len(pkt) >= 20 and pkt[0] >> 4 == 4:
                out.append(pkt)
        return out

    def send(self, pkt: bytes) -> None:
        """Put an IPv4 packet (header included) back on its way."""
        try:
            self.raw.sendto(pkt, (socket.inet_ntoa(pkt[16:20]), 0))
        except OSError as exc:  # e.g. no route any more: the packet is lost, as on a link
            log.debug("re-send: %s", exc)

    def close(self) -> None:
        try:
            self._send(_NFQNL_MSG_CONFIG, _NLM_F_REQUEST, _attr(_NFQA_CFG_CMD, struct.pack("!BBH", _NFQNL_CFG_CMD_UNBIND, 0, socket.AF_INET)))
        finally:
            self.sock.close()
            self.raw.close()


class Delayer:
    """Release times of a FIFO link with a fixed delay and uniform jitter: packet m
    arriving at ``a_m`` leaves at ``d_m = max(d_{m−1}, a_m + delay + u_m)``, ``u_m ~
    U[−jitter, jitter]`` (clipped so that ``delay + u_m ≥ 0``). The draws come from one
    seeded stream in packet order: packet timing is not part of the run's reproducible
    numbers (lockstep runs are bit-equal whatever the network does)."""

    def __init__(self, delay_s: float, jitter_s: float = 0.0, seed: int = 0):
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self.rng = stream(seed, "netem-jitter")
        self.last = -float("inf")

    def release_at(self, arrival_s: float) -> float:
        u = self.rng.uniform(-self.jitter_s, self.jitter_s) if self.jitter_s > 0 else 0.0
        self.last = max(self.last, arrival_s + max(0.0, self.delay_s + u))
        return self.last


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    if check and p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {p.stderr.strip() or p.stdout.strip()}")
    return p


def _interfaces() -> list[str]:
    out = _run("ip", "-o", "link", "show").stdout
    return [line.split(": ")[1].split("@")[0] for line in out.splitlines() if ": " in line and line.split(": ")[1].split("@")[0] != "lo"]


def remove_rules() -> None:
    """Undo :func:`install`: the iptables chain and the tbf qdiscs (idempotent)."""
    _run("iptables", "-w", "-D", "OUTPUT", "-j", CHAIN, check=False)
    _run("iptables", "-w", "-F", CHAIN, check=False)
    _run("iptables", "-w", "-X", CHAIN, check=False)
    for d in _interfaces():
        if " tbf " in _run("tc", "qdisc", "show", "dev", d, check=False).stdout:
            _run("tc", "qdisc", "del", "dev", d, "root", check=False)


def install(queue: int | None, loss_pct: float | None, rate_bit_s: int | None) -> None:
    remove_rules()
    if loss_pct or queue is not None:
        _run("iptables", "-w", "-N", CHAIN)
        # Our own re-sends first: they were queued (and passed the loss) once already.
        _run("iptables", "-w", "-A", CHAIN, "-m", "mark", "--mark", hex(MARK), "-j", "RETURN")
        if loss_pct:
            _run("iptables", "-w", "-A", CHAIN, "!", "-o", "lo", "-m", "statistic", "--mode", "random",
                 "--probability", f"{loss_pct / 100:.6f}", "-j", "DROP")
        if queue is not None:
            _run("iptables", "-w", "-A", CHAIN, "!", "-o", "lo", "-j", "NFQUEUE", "--queue-num", str(queue), "--queue-bypass")
        _run("iptables", "-w", "-I", "OUTPUT", "1", "-j", CHAIN)
    if rate_bit_s:
        # Burst: 10 ms at the rate, and at least a few full-size packets (tbf needs ≥ one MTU).
        burst = max(rate_bit_s // 8 // 100, 16 * 1514)
        for d in _interfaces():
            _run("tc", "qdisc", "replace", "dev", d, "root", "tbf", "rate", f"{rate_bit_s}bit", "burst", str(burst), "latency", "2s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="netem without the netem qdisc (NFQUEUE delay, iptables loss, tc tbf rate)")
    p.add_argument("--delay-s", type=float, default=None)
    p.add_argument("--jitter-s", type=float, default=0.0)
    p.add_argument("--loss-pct", type=float, default=None)
    p.add_argument("--rate-bit-s", type=int, default=None)
    p.add_argument("--queue", type=int, default=4711, help="NFQUEUE number")
    p.add_argument("--seed", type=int, default=0, help="seed of the jitter draws")
    p.add_argument("--clear", action="store_true", help="only remove the rules and exit")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s netemd %(levelname)s %(message)s", stream=sys.stderr)
    if a.clear:
        remove_rules()
        return 0
    stop = []
    r_fd, w_fd = os.pipe()  # signals wake the select at once (set_wakeup_fd writes here)
    os.set_blocking(w_fd, False)
    signal.set_wakeup_fd(w_fd)
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, lambda *_: stop.append(1))
    delay = a.delay_s is not None and (a.delay_s > 0 or a.jitter_s > 0)
    q = NfQueue(a.queue) if delay else None
    try:
        install(a.queue if delay else None, a.loss_pct, a.rate_bit_s)
        log.info("delay %s s jitter %s s loss %s %% rate %s bit/s on %s", a.delay_s, a.jitter_s, a.loss_pct, a.rate_bit_s, _interfaces())
        print("READY", flush=True)
        held: collections.deque[tuple[float, bytes]] = collections.deque()
        dl = Delayer(a.delay_s or 0.0, a.jitter_s, a.seed) if delay else None
        passed = 0
        while not stop:
            wait = None if not held else max(0.0, held[0][0] - time.monotonic())
            try:
                ready, _, _ = select.select([r_fd] + ([q] if q is not None else []), [], [], wait)
            except InterruptedError:
                continue
            if q is None or dl is None:  # no delay: nothing is queued here
                continue
            if q in ready:
                now = time.monotonic()
                for pkt in q.packets():
                    held.append((dl.release_at(now), pkt))
            now = time.monotonic()
            while held and held[0][0] <= now:
                q.send(held.popleft()[1])
                passed += 1
        # Stop queueing (new packets go straight out), then let what is already on the
        # "link" arrive when it is due: a clear does not shorten the delay of packets sent
        # before it.
        remove_rules()
        while q is not None and dl is not None:
            for pkt in q.packets():
                held.append((dl.release_at(time.monotonic()), pkt))
            if not held:
                break
            time.sleep(max(0.0, held[0][0] - time.monotonic()))
            now = time.monotonic()
            while held and held[0][0] <= now:
                q.send(held.popleft()[1])
                passed += 1
        log.info("stopped after %d delayed packets", passed)
    finally:
        remove_rules()
        if q is not None:
            q.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
