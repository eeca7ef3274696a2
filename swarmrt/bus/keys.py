"""Keys and identities: the key expressions of a run (:class:`Keys`), reading a key
(:func:`parse_key`), a message against the key it came on (:func:`check_key`), and who may
use which key (:func:`grants`, :data:`IDENTITIES`; :mod:`swarmrt.security` makes the
router's rules of it)."""

from __future__ import annotations

import functools
import re
from typing import NamedTuple

from swarmrt.bus.wire import RUN_ID_RE, KeyMismatch, MessageError

# -- the message against its key ----------------------------------------------------------
_WORLD_KEYS = ("clock", "sensors", "cam", "img", "truth", "claim", "rx", "batches", "links", "rejoin")
_OWNER_FIELD = {"sensors": "sat", "cam": "sat", "img": "sat", "health": "sat", "meas": "observer", "est": "own", "full_est": "own", "rx": "sat", "rejoin": "sat"}


_REPORTER_RE = re.compile(r"world|selector|supervisor|cli|agent-\d+")


def check_key(key: str, kind: str, sat: int | None, msg) -> None:
    """The message agrees with the key it came on: the satellite the key names is the one
    the message is about, and the sender is the role that publishes on that key
    (:class:`KeyMismatch` otherwise)."""
    field = _OWNER_FIELD.get(kind)
    if sat is not None and field is not None and getattr(msg, field) != sat:
        raise KeyMismatch(f"key says satellite {sat}, message {field} says {getattr(msg, field)}")
    want: tuple[str, ...]
    if kind in _WORLD_KEYS or (kind == "full_est" and "/init/" in key):
        want = ("world",)
    elif kind in ("meas", "est", "health", "full_est"):
        want = (f"agent-{sat}",)
    elif kind == "select":
        want = ("selector", "world")
    elif kind == "recorded":
        want = ("recorder",)
    else:  # fault: commands on fault (the CLI's, the world's schedule); outcomes on fault/<reporter>
        tail = key.rsplit("/", 1)[1]
        if tail == "fault":
            if msg.phase != "command":
                raise KeyMismatch(f"a fault {msg.phase!r} report on {key} (reports go on fault/<reporter>)")
            want = ("cli", "world")
        else:
            if msg.phase == "command":
                raise KeyMismatch(f"a fault command on {key} (commands go on fault)")
            if not _REPORTER_RE.fullmatch(tail):
                raise KeyMismatch(f"{tail[:64]!r} is not a role that carries out faults")
            want = (tail,)
    if msg.sender not in want:
        raise KeyMismatch(f"sender {msg.sender[:64]!r} may not publish on {key} (expected {' or '.join(want)})")


# -- keys ----------------------------------------------------------------------------------


class Keys:
    """Key expressions of one run."""

    def __init__(self, run: str):
        if not RUN_ID_RE.fullmatch(run):
            raise ValueError(f"run id {run!r}: use 1-64 letters, digits, '_', '-' or '.'")
        self.run = run
        self.root = f"swarm/{run}"

    def clock(self) -> str:
        return f"{self.root}/clock"

    def recorded(self) -> str:
        """How far the recorder has got (recorder → world: the bounded recorder lag)."""
        return f"{self.root}/recorded"

    def sensors(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/sensors"

    def cam(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/cam"

    def img(self, i: int | str) -> str:
        return f"{self.root}/sat/{i}/img"

    def meas(self, i: int | str = "*") -> str:
        return f"{self.root}/meas/{i}"

    def est(self, i: int | str = "*") -> str:
        return f"{self.root}/est/{i}"

    def cov(self, i: int | str = "*") -> str:
        return f"{self.root}/cov/{i}"

    def init(self, i: int | str = "*") -> str:
        return f"{self.root}/init/{i}"

    def select(self) -> str:
        return f"{self.root}/select"

    def fault(self) -> str:
        """Fault commands (the CLI's, and the world's from the scenario's schedule)."""
        return f"{self.root}/fault"

    def fault_report(self, reporter: str = "*") -> str:
        """What ``reporter`` (``world``, ``supervisor``, ``agent-3``...) carried out."""
        return f"{self.root}/fault/{reporter}"

    def faults(self) -> str:
        """Commands and every report."""
        return f"{self.root}/fault/**"

    def health(self, i: int | str = "*") -> str:
        return f"{self.root}/health/{i}"

    def truth(self) -> str:
        return f"{self.root}/truth"

    def rx(self, i: int | str = "*") -> str:
        return f"{self.root}/rx/{i}"

    def batches(self, i: int | str | None = None) -> str:
        """The ideal radio (links.enabled false): every batch of a step, to every agent
        (``batches``); or what agent i's radio delivers, its graph neighbours' batches
        (``batches/<i>``, an estimator whose ``radio`` is ``"graph"``)."""
        return f"{self.root}/batches" if i is None else f"{self.root}/batches/{i}"

    def links(self) -> str:
        return f"{self.root}/links"

    def rejoin(self, i: int | str = "*", peer: int | str | None = None, size: int | str | None = None) -> str:
        """``rejoin/<i>``: the fates the world gives agent i's rejoin transfers (recorded);
        ``rejoin/<i>/<peer>/<bytes>``: agent i's question about one (a query)."""
        tail = "" if peer is None else f"/{peer}/{size}"
        return f"{self.root}/rejoin/{i}{tail}"

    def claim(self, token: str = "*") -> str:
        return f"{self.root}/claim/{token}"

    def alive(self, role: str = "*", ident: int | str = "*") -> str:
        return f"{self.root}/alive/{role}/{ident}"

    def everything(self) -> str:
        return f"{self.root}/**"


_KEY_RE = re.compile(
    r"^swarm/(?P<run>[^/]+)/(?:"
    r"(?P<clock>clock)|(?P<select>select)|(?P<fault>fault)(?:/[A-Za-z0-9_.-]+)?|(?P<truth>truth)|(?P<links>links)|(?P<batches>batches)|(?P<recorded>recorded)"
    r"|sat/(?P<sat>\d+)/(?P<satkind>sensors|cam|img)"
    r"|(?P<idkind>meas|est|health|cov|init|rx|rejoin|batches)/(?P<id>\d+)(?:/\d+/\d+)?"
    r"|claim/(?P<token>[^/]+)"
    r"|alive/(?P<role>[^/]+)/(?P<ident>[^/]+))$"
)


def parse_key(key: str) -> tuple[str, str, int | None]:
    """``(run, kind, satellite id or None)`` of a key; :class:`MessageError` if unknown."""
    return _parse_key(str(key))


@functools.lru_cache(maxsize=4096)  # a run's ~5n keys recur every step
def _parse_key(key: str) -> tuple[str, str, int | None]:
    m = _KEY_RE.match(key)
    if not m:
        raise MessageError(f"unexpected key {str(key)[:200]!r}")
    run = m["run"]
    for k in ("clock", "select", "fault", "truth", "links", "batches", "recorded"):
        if m[k]:
            return run, k, None
    if m["satkind"]:
        return run, m["satkind"], int(m["sat"])
    if m["idkind"]:
        kind = {"cov": "full_est", "init": "full_est"}.get(m["idkind"], m["idkind"])
        return run, kind, int(m["id"])
    if m["token"]:
        return run, "claim", None
    ident = m["ident"]
    return run, "alive", int(ident) if ident.isdigit() else None


# -- who may use which key ------------------------------------------------------------------
#: The identities of a swarm other than the agents (``agent-<i>``, bound to satellite i).
IDENTITIES = ("world", "selector", "recorder", "cli", "supervisor", "observer", "claimant", "mesh", "viewer")


class Grants(NamedTuple):
    """What one identity may do on the bus, as key expressions (the router allows nothing
    else: :mod:`swarmrt.security` turns this into Zenoh access-control rules)."""

    put: tuple[str, ...] = ()  # put (and delete)
    sub: tuple[str, ...] = ()  # declare a subscriber (and be sent what matches)
    query: tuple[str, ...] = ()  # get (and be sent the replies)
    serve: tuple[str, ...] = ()  # declare a queryable and reply (and be sent the queries)
    token: tuple[str, ...] = ()  # declare a liveliness token
    watch: tuple[str, ...] = ()  # liveliness subscribers and queries


def grants(keys: Keys, identity: str, links: bool = False) -> Grants:
    """The single table of who may say what. Agents hear their peers' batches only through
    the world, the radio: ``batches`` or their own ``batches/<i>`` (the ideal radio) or,
    when the scenario's ``links`` are on, their own ``rx/<i>``; never another agent's
    ``meas/<j>`` or ``batches/<j>``."""
    k = keys
    alive = f"{k.root}/alive/**"
    if identity == "world":
        return Grants(
            put=(k.clock(), k.sensors("*"), k.cam("*"), k.img("*"), k.truth(), k.links(), k.rx("*"), k.batches(),
                 k.batches("*"), k.rejoin("*"), k.select(), k.fault(), k.fault_report("world")),
            sub=(k.est(), k.health(), k.select(), k.faults(), k.meas(), k.recorded()),
            serve=(k.init(), k.claim(), k.rejoin("*") + "/*/*", k.clock(), k.health()),
            token=(k.alive("world"),), watch=(alive,))
    if m := re.fullmatch(r"agent-(\d+)", identity):
        i = int(m[1])
        return Grants(
            put=(k.meas(i), k.est(i), k.health(i), k.fault_report(identity)),
            sub=(k.clock(), k.sensors(i), k.cam(i), k.img(i), *((k.rx(i),) if links else (k.batches(), k.batches(i))), k.fault()),
            query=(k.init(i), k.cov(), k.rejoin(i, "*", "*")),
            serve=(k.cov(i),), token=(k.alive("agent", i),), watch=(alive,))
    if identity == "selector":
        return Grants(put=(k.select(), k.fault_report("selector")), sub=(k.est(), k.fault(), k.health(), k.clock()),
                      query=(k.cov(), k.clock(), k.health()), token=(k.alive("selector"),), watch=(alive,))
    if identity == "recorder":
        return Grants(put=(k.recorded(),), sub=(k.everything(),), token=(k.alive("recorder"),), watch=(alive,))
    if identity == "cli":  # swarm fault: commands; under compose it carries out process faults and reports them
        return Grants(put=(k.fault(), k.fault_report("cli")), sub=(k.faults(), k.clock(), k.health()),
                      token=(k.alive("cli"),), watch=(alive,))
    if identity == "supervisor":  # swarm run: carries out process faults and reports them
        return Grants(put=(k.fault_report("supervisor"),), sub=(k.faults(), k.clock()), token=(k.alive("supervisor"),),
                      watch=(alive,))
    if identity == "observer":  # read-only telemetry for tools and participants (never the truth)
        return Grants(sub=(k.clock(), k.est(), k.health(), k.select(), k.faults(), k.links()),
                      token=(k.alive("observer"),), watch=(alive,))
    if identity == "viewer":  # the live 3-D view (swarm.live): read-only, and a ground tool: it shows the truth
        return Grants(sub=(k.clock(), k.truth(), k.est(), k.meas(), k.links(), k.faults(), k.health(), k.select()),
                      token=(k.alive("viewer"),), watch=(alive,))
    if identity == "claimant":  # an agent started with --id auto, before it has a satellite
        return Grants(query=(k.claim(),), token=(k.alive("claimant"),))
    if identity == "mesh":  # a router meshed with this one (swarm run --routers 2): it forwards everyone's traffic
        every = (k.everything(),)
        return Grants(put=every, sub=every, query=every, serve=every, token=every, watch=every)
    raise ValueError(f"unknown identity {identity!r} (expected agent-<i> or one of {', '.join(IDENTITIES)})")
