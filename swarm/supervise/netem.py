"""Real network impairment of a compose satellite: Linux traffic control (``tc`` netem).
This module owns the ``tc`` commands (run in a helper container); the argument grammar is
:mod:`swarmrt.netem`'s, the fallback for kernels without netem :mod:`swarm.supervise.netemd`'s.

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
kind is unknown") get the same impairment from :mod:`swarm.supervise.netemd` instead, in a
long-lived helper container (iptables loss, an NFQUEUE delayer, tc tbf for the rate); see
there. ``clear`` removes either.

This module is the helper container's scripts; the argument grammar they apply is the
runtime's (:mod:`swarmrt.netem`, since every receiver of a Fault checks it). Written by
hand because ``tc`` has no Python binding here (pyroute2 is not a dependency, and it would
still need the namespace and the capability the helper container provides).
"""

from __future__ import annotations

import shlex

from swarmrt.netem import CLEAR, Netem, NetemError

__all__ = ["Netem", "NetemError", "CLEAR", "tc_script", "show_script", "netemd_args", "NO_QDISC", "UNKNOWN_QDISC"]


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
    :mod:`swarm.supervise.netemd` fallback) and the fallback's iptables chain wherever they are.
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
    """``python -m swarm.supervise.netemd`` arguments for the same impairment (the fallback)."""
    n = Netem.parse(netem)
    out = []
    if n.delay_s is not None:
        out += ["--delay-s", repr(n.delay_s), "--jitter-s", repr(n.jitter_s or 0.0)]
    if n.loss_pct is not None:
        out += ["--loss-pct", repr(n.loss_pct)]
    if n.rate_bit_s is not None:
        out += ["--rate-bit-s", str(n.rate_bit_s)]
    return out
