"""The netem impairment's argument grammar: what a ``netem`` Fault carries (the runtime's
part of netem: every receiver of a Fault checks it). The other two: :mod:`swarm.supervise.netem`
(the ``tc`` commands that apply it to a compose container) and :mod:`swarm.supervise.netemd`
(the fallback daemon for kernels without netem).

Values in, values out: :class:`Netem` parses and validates the CLI's strings and writes
the canonical netem argument string (``delay 200ms 50ms loss 10% rate 1mbit``) that the
``Fault`` message carries, that every receiver checks (:func:`validate_field`) and that
``tc`` reads (:mod:`swarm.supervise.netem` applies it). Written by hand: ``tc`` has no
Python binding here, and only this grammar, not tc's whole, is accepted.
"""


from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["Netem", "NetemError", "CLEAR", "MAX_DELAY_S", "parse_time_s", "parse_percent", "parse_rate_bit_s", "validate_field"]

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
