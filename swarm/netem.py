"""Real network impairment of a compose satellite: Linux traffic control (``tc`` netem).

``swarm fault --compose netem 3 --delay 200ms --jitter 50ms --loss 10% --rate 1mbit`` puts
a netem queueing discipline on the egress of satellite 3's container::

    tc qdisc replace dev eth0 root netem delay 200ms 50ms loss 10% rate 1mbit

and ``swarm fault --compose netem 3 clear`` removes it (``tc qdisc del dev eth0 root``).
Egress only, as netem works: what satellite 3 sends (its batches, estimates, health, and
the TCP acknowledgements of what it receives) waits ``delay ± jitter``, is lost with the
given probability, and leaves no faster than ``rate``. Every message from satellite 3 then
reaches the router (and everyone else) at least ``delay − jitter`` after it was published,
which the recording shows (``bus_latency_ms`` of ``agent-3``).

The agents' containers hold no NET_ADMIN capability, so the command runs in a short-lived
helper container of the same image that joins the target's network namespace
(``docker run --rm --network container:<id> --cap-add NET_ADMIN IMAGE sh -c 'tc ...'``);
the image carries iproute2 for it. The helper applies it to every interface of the
namespace but ``lo`` (one, ``eth0``, for an agent of compose.yaml; after ``partition`` and
``heal`` the interface is a new one, which is why the name is not assumed).

Kernels built without netem (``CONFIG_NET_SCH_NETEM`` unset; ``tc`` says "Specified qdisc
kind is unknown") get the same impairment from :mod:`swarm.netemd` instead, in a
long-lived helper container (iptables loss, an NFQUEUE delayer, tc tbf for the rate); see
there. ``clear`` removes either.

This module is the argument grammar (values in, values out: :class:`Netem` parses and
validates the CLI's strings, and writes the canonical netem argument string that the
``Fault`` message carries and ``tc`` reads) and the helper container's scripts. Written by
hand because ``tc`` has no Python binding here (pyroute2 is not a dependency, and it would
still need the namespace and the capability the helper container provides).
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass

__all__ = ["Netem", "NetemError", "CLEAR", "parse_time_s", "parse_percent", "parse_rate_bit_s", "tc_script", "show_script", "netemd_args"]

#: The ``netem`` field of a Fault that removes the impairment.
CLEAR = "clear"

#: Longest delay or jitter accepted (s): a longer one stalls even lockstep runs past their
#: step timeout and the Zenoh lease (10 s), which is a partition, not a delay.
MAX_DELAY_S = 60.0
#: Slowest and fastest transmitter rates accepted (bit/s).
MIN_RATE_BIT_S = 1_000
MAX_RATE_BIT_S = 100_000_000_000

# tc's time units (tc-netem(8), `tc/tc_util.c: get_time`), in seconds. A bare number means
# microseconds to tc, which nobody expects: a unit is required here.
_TIME_UNITS = {"s": 1.0, "sec": 1.0, "secs": 1.0, "ms": 1e-3, "msec": 1e-3, "msecs": 1e-3,
               "us": 1e-6, "usec": 1e-6, "usecs": 1e-6}
# tc's rate units (tc(8) RATES): bit-based are SI (kbit = 1000 bit/s), "bps" means BYTES per second.
_RATE_UNITS = {"bit": 1, "kbit": 10**3, "mbit": 10**6, "gbit": 10**9,
               "bps": 8, "kbps": 8 * 10**3, "mbps": 8 * 10**6, "gbps": 8 * 10**9}
_NUM = r"(?P<num>[0-9]+(?:\.[0-9]*)?|\.[0-9]+)"


class NetemError(ValueError):
    """A netem argument that is malformed or out of range; the message names it."""


def parse_time_s(name: str, text: str) -> float:
    """``"200ms"`` → 0.2 (s). Units: s, ms, us (and tc's sec/msec/usec); 0 ≤ t ≤ 60 s."""
    m = re.fullmatch(_NUM + r"\s*(?P<unit>[a-z]+)", str(text).strip().lower())
    if not m or m["unit"] not in _TIME_UNITS:
        raise NetemError(f"{name} {text!r}: give a time with a unit, e.g. 200ms, 0.2s or 500us")
    t = float(m["num"]) * _TIME_UNITS[m["unit"]]
    if not 0.0 <= t <= MAX_DELAY_S:
        raise NetemError(f"{name} {text!r}: must be between 0 and {MAX_DELAY_S:g} s")
    return t


def parse_percent(name: str, text: str) -> float:
    """``"10%"`` → 10.0 (percent, 0–100). The % sign is required: tc reads a bare 0.1 as
    0.1 %, not 10 %, and the two are easy to confuse."""
    m = re.fullmatch(_NUM + r"\s*%", str(text).strip())
    if not m:
        raise NetemError(f"{name} {text!r}: give a percentage with %, e.g. 10%")
    p = float(m["num"])
    if not 0.0 <= p <= 100.0:
        raise NetemError(f"{name} {text!r}: must be between 0% and 100%")
    return p


def parse_rate_bit_s(name: str, text: str) -> int:
    """``"1mbit"`` → 1 000 000 (bit/s). Units as tc's: bit, kbit, mbit, gbit (SI), and
    bps, kbps, mbps, gbps (BYTES per second); 1 kbit/s ≤ rate ≤ 100 gbit/s."""
    m = re.fullmatch(_NUM + r"\s*(?P<unit>[a-z]+)", str(text).strip().lower())
    if not m or m["unit"] not in _RATE_UNITS:
        raise NetemError(f"{name} {text!r}: give a rate with a unit, e.g. 1mbit, 500kbit or 100kbps (bytes/s)")
    r = round(float(m["num"]) * _RATE_UNITS[m["unit"]])
    if not MIN_RATE_BIT_S <= r <= MAX_RATE_BIT_S:
        raise NetemError(f"{name} {text!r}: must be between 1kbit and 100gbit per second")
    return r


def _fmt_time(t_s: float) -> str:
    us = round(t_s * 1e6)
    return f"{us // 1000}ms" if us % 1000 == 0 else f"{us}us"


def _fmt_rate(bit_s: int) -> str:
    for unit, f in (("gbit", 10**9), ("mbit", 10**6), ("kbit", 10**3)):
        if bit_s % f == 0:
            return f"{bit_s // f}{unit}"
    return f"{bit_s}bit"


@dataclass(frozen=True)
class Netem:
    """One netem impairment: ``delay_s`` (mean one-way delay added), ``jitter_s`` (netem's
    uniform ± spread around it), ``loss_pct`` (independent loss probability of each packet,
    percent) and ``rate_bit_s`` (egress rate cap); None: that part is off."""

    delay_s: float | None = None
    jitter_s: float | None = None
    loss_pct: float | None = None
    rate_bit_s: int | None = None

    def __post_init__(self):
        if self.delay_s is None and self.loss_pct is None and self.rate_bit_s is None:
            raise NetemError("netem needs at least one of --delay, --loss, --rate (or 'clear')")
        if self.jitter_s is not None and self.delay_s is None:
            raise NetemError("--jitter needs --delay (netem's jitter is a spread around the delay)")

    @classmethod
    def from_cli(cls, delay: str | None = None, jitter: str | None = None, loss: str | None = None, rate: str | None = None) -> Netem:
        """From the CLI's option strings (each validated, errors name the option)."""
        return cls(
            delay_s=None if delay is None else parse_time_s("--delay", delay),
            jitter_s=None if jitter is None else parse_time_s("--jitter", jitter),
            loss_pct=None if loss is None else parse_percent("--loss", loss),
            rate_bit_s=None if rate is None else parse_rate_bit_s("--rate", rate),
        )

    def args(self) -> str:
        """The canonical netem argument string, e.g. ``delay 200ms 50ms loss 10% rate 1mbit``."""
        out = []
        if self.delay_s is not None:
            out += ["delay", _fmt_time(self.delay_s)] + ([_fmt_time(self.jitter_s)] if self.jitter_s else [])
        if self.loss_pct is not None:
            out += ["loss", f"{self.loss_pct:g}%"]
        if self.rate_bit_s is not None:
            out += ["rate", _fmt_rate(self.rate_bit_s)]
        return " ".join(out)

    @classmethod
    def parse(cls, args: str) -> Netem:
        """Inverse of :meth:`args` (what a received Fault message carries): the same grammar
        and ranges; anything else raises :class:`NetemError` naming the word."""
        words = str(args).split()
        kw: dict = {}
        i = 0
        while i < len(words):
            w = words[i]
            rest = words[i + 1 :]
            if w == "delay" and rest and "delay_s" not in kw:
                kw["delay_s"] = parse_time_s("delay", rest[0])
                i += 2
                if i < len(words) and words[i] not in ("loss", "rate"):
                    kw["jitter_s"] = parse_time_s("jitter", words[i])
                    i += 1
            elif w == "loss" and rest and "loss_pct" not in kw:
                kw["loss_pct"] = parse_percent("loss", rest[0])
                i += 2
            elif w == "rate" and rest and "rate_bit_s" not in kw:
                kw["rate_bit_s"] = parse_rate_bit_s("rate", rest[0])
                i += 2
            else:
                raise NetemError(f"netem arguments {args!r}: unexpected {w!r} (expected delay T [J], loss P%, rate R)")
        return cls(**kw)


def validate_field(value: str) -> str:
    """The ``netem`` field of a Fault message: ``clear`` or canonical netem arguments."""
    if value == CLEAR:
        return value
    return Netem.parse(value).args()


# The helper container's scripts (``sh -c``) act on every interface of the namespace but
# lo (an agent of compose.yaml has one, eth0). `ip -o link` lists them as "2: eth0@if7: <...>".
_DEVS = "devs=$(ip -o link show | awk -F': ' '{print $2}' | cut -d@ -f1 | grep -vx lo); " \
        "[ -n \"$devs\" ] || { echo 'no network interface but lo' >&2; exit 3; }; "
#: Exit status of :func:`tc_script` when ``tc`` refused the netem qdisc.
NO_QDISC = 10
#: The stderr of ``tc`` on a kernel built without netem (``CONFIG_NET_SCH_NETEM`` unset).
UNKNOWN_QDISC = "Specified qdisc kind is unknown"


def tc_script(netem: str) -> str:
    """Apply: ``tc qdisc replace dev D root netem ARGS`` on every interface D but lo (exit
    :data:`NO_QDISC` if tc refuses). ``clear``: delete the root netem (or the tbf of the
    :mod:`swarm.netemd` fallback) and the fallback's iptables chain wherever they are.
    Both then print the state (:func:`show_script`) for the fault's detail."""
    if netem == CLEAR:
        act = ("for d in $devs; do if tc qdisc show dev $d | grep -qE '^qdisc (netem|tbf) '; then tc qdisc del dev $d root; fi; done; "
               "if command -v iptables >/dev/null; then iptables -w -D OUTPUT -j SWARM_NETEM 2>/dev/null || true; "
               "iptables -w -F SWARM_NETEM 2>/dev/null || true; iptables -w -X SWARM_NETEM 2>/dev/null || true; fi; ")
    else:
        args = " ".join(shlex.quote(w) for w in Netem.parse(netem).args().split())
        act = f"for d in $devs; do tc qdisc replace dev $d root netem {args} || exit {NO_QDISC}; done; "
    return "set -e; " + _DEVS + act + _SHOW


_SHOW = ("for d in $devs; do echo \"$d: $(tc qdisc show dev $d | head -n1)\"; done; "
         "if command -v iptables >/dev/null && iptables -w -S SWARM_NETEM >/dev/null 2>&1; then "
         "iptables -w -S SWARM_NETEM | grep -v '^-N' | sed 's/^/iptables: /'; fi")


def show_script() -> str:
    """Print ``D: <root qdisc>`` of every interface D but lo, and the rules of the
    fallback's iptables chain if it exists (``iptables: -A SWARM_NETEM ...``)."""
    return _DEVS + _SHOW


def netemd_args(netem: str) -> list[str]:
    """``python -m swarm.netemd`` arguments for the same impairment (the fallback)."""
    n = Netem.parse(netem)
    out = []
    if n.delay_s is not None:
        out += ["--delay-s", repr(n.delay_s), "--jitter-s", repr(n.jitter_s or 0.0)]
    if n.loss_pct is not None:
        out += ["--loss-pct", repr(n.loss_pct)]
    if n.rate_bit_s is not None:
        out += ["--rate-bit-s", str(n.rate_bit_s)]
    return out
