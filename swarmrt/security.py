"""Who may say what on the bus: credentials, the router's access rules, TLS.

Every process of a swarm connects to the router with its own identity: ``world``,
``selector``, ``recorder``, ``cli`` (``swarm fault``), ``supervisor`` (``swarm run``),
``observer`` (read-only tools: tests, participants of other languages), ``viewer`` (the live
3-D view, :mod:`swarm.live`: read-only like the observer, and it sees the truth), ``claimant`` (an
agent started with ``--id auto`` before it has a satellite), ``mesh`` (a router meshed
with another: it forwards everyone's traffic, so its rules allow the run's whole key
space) and ``agent-<i>``, bound to satellite i. Two Zenoh features carry it, nothing hand-written on the wire:

- **authentication**: Zenoh's user/password authentication (``transport/auth/usrpwd``; the
  router holds a dictionary file of ``user:password`` lines). It is a challenge-response:
  the password itself never crosses the link. A session without a valid credential is
  refused when it connects.
- **access control** on the router (``access_control``, ``default_permission: deny``): a
  subject per identity (by user name), and rules generated from the one table of who may
  use which key, :func:`swarmrt.bus.messages.grants`. Ingress: what the identity may put,
  subscribe to, query, serve and declare alive. Egress: what the router may send it
  (samples only of keys it may subscribe to, so no agent is ever sent the truth).

Across hosts, **TLS** (``tls/`` endpoints; the router's certificate is signed by a CA
the keys directory holds, and every credential names that CA) encrypts the traffic too.

A keys directory (``swarm run`` makes one per run in a private temporary directory,
``/tmp/swarm-keys-<run>-*``, owner-only, deleted when the run ends — by its orphaned
children if the supervisor was killed; ``swarm keys`` or compose's ``keys`` service makes
one for compose or several hosts, in ``./keys``, git-ignored; never in the repository)::

    passwords          the router's dictionary (user:password per line)
    router.json        what the router needs: the dictionary's file name, TLS files if any
    <identity>.json    one credential: {"user": ..., "password": ..., "ca": "ca.pem" (TLS)}
    agents.json        every agent's password, for the world alone: it hands satellite i's
                       to the --id auto agent it gives satellite i (see below)
    ca.pem, router.pem, router.key   with TLS (swarm keys --tls): the CA (ca.key is not
                       kept), the router's certificate and key
    driver.pem, driver.key           a cluster run's (mutual TLS between hosts): the
                       client certificate of the driver's identities (DRIVER_IDENTITIES);
                       router.json says "mtls": true, every router certificate serves
                       both ends of a link

``--id auto`` (compose replicas, a remote agent): the replica holds only the ``claimant``
credential, which may do nothing but ask the world for a satellite (``claim/<token>``).
The world answers with the satellite and that satellite's password (a query reply: it
goes to the asker alone, is never recorded, and travels over TLS across hosts); the agent
then reconnects as ``agent-<i>``. The world gives a satellite only when no live agent
flies it and no claim for it is under 30 s old, so a claimant gets a free satellite's
identity and never a live one's.

Files are written owner-only (0600, directory 0700).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import subprocess
from pathlib import Path

from swarmrt.bus.messages import IDENTITIES, MAX_PAYLOAD_BYTES, MAX_PAYLOAD_DEFAULT, MAX_SAT_ID, Keys, MessageError, grants, parse_key

__all__ = ["DEFAULT_TLS_HOSTS", "DRIVER_IDENTITIES", "make_keys", "acl_config", "size_limits", "size_limit_of", "apply_router_security", "load_router_keys", "Credential",
           "load_credential", "load_agent_passwords", "agent_identities"]

#: The names the router's certificate is valid for unless told otherwise: what compose's
#: containers (tls/router:7449) and clients on the compose host use.
DEFAULT_TLS_HOSTS: tuple[str, ...] = ("router", "localhost", "127.0.0.1")

_IDENT_RE = re.compile("|".join([*IDENTITIES, r"agent-\d+"]))

#: The identities a cluster run's driver holds (``swarm run --cluster``, ``swarm fault``, read-only
#: tools): they reach the head's router over the mesh's mutual TLS, so their credentials carry the
#: driver's client certificate (every other process reaches its own node's router on that host's
#: loopback, through the node's ingress gate).
DRIVER_IDENTITIES: tuple[str, ...] = ("supervisor", "cli", "observer")


def agent_identities(n_sats: int) -> list[str]:
    return [f"agent-{i}" for i in range(n_sats)]


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def make_keys(out: str | Path, n_sats: int, tls_hosts: list[str] | None = None,
              router_hosts: list[list[str]] | None = None) -> Path:
    """Make a keys directory for a swarm of ``n_sats`` satellites (fresh random passwords;
    ``tls_hosts``: also a CA and a router certificate valid for those names/addresses;
    ``router_hosts``: a CA and one certificate per router of a cluster run, router i's
    (``router-<i>.pem``, ``router-<i>.key``) valid for the names of ``router_hosts[i]``: each
    node is given its own router's key only, as ``router.pem``/``router.key``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    names = [*IDENTITIES, *agent_identities(n_sats)]
    pw = {name: secrets.token_urlsafe(24) for name in names}
    _write_private(out / "passwords", "".join(f"{n}:{p}\n" for n, p in pw.items()))
    tls = bool(tls_hosts) or bool(router_hosts)
    mtls = bool(router_hosts)
    if tls_hosts or router_hosts:
        certs = ([("router", tls_hosts)] if tls_hosts else []) + [(f"router-{i}", h) for i, h in enumerate(router_hosts or [])]
        _make_tls(out, certs, clients=["driver"] if mtls else [])
    for name in names:
        cred = {"user": name, "password": pw[name], **({"ca": "ca.pem"} if tls else {}),
                **({"certificate": "driver.pem", "private_key": "driver.key"} if mtls and name in DRIVER_IDENTITIES else {})}
        _write_private(out / f"{name}.json", json.dumps(cred) + "\n")
    _write_private(out / "agents.json", json.dumps({str(i): pw[f"agent-{i}"] for i in range(n_sats)}) + "\n")
    router = {"passwords": "passwords", "n_sats": n_sats, **({"certificate": "router.pem", "private_key": "router.key"} if tls else {}),
              **({"mtls": True} if mtls else {})}
    _write_private(out / "router.json", json.dumps(router) + "\n")
    return out


def _make_tls(out: Path, certs: list[tuple[str, list[str]]], clients: list[str] | None = None) -> None:
    """A CA and, for each (name, hosts) of ``certs``, a router certificate ``<name>.pem``
    (key ``<name>.key``) valid for ``hosts``, signed by it (openssl, as any operator would;
    the CA's key is deleted once it has signed them all: new hosts mean new keys). A router's
    certificate serves for both ends of a TLS link (it dials its peers with it when the mesh
    is mutual TLS); each name of ``clients`` gets a client certificate only (``<name>.pem``,
    no host names: what a TLS listener with ``enable_mtls`` asks of who connects)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError("TLS keys need the openssl command (Debian: apt-get install openssl)")

    def run(*args: str) -> None:
        p = subprocess.run([openssl, *args], capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"openssl {args[0]}: {p.stderr.strip()[-500:]}")

    old = os.umask(0o077)
    try:
        run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "825",
            "-subj", "/CN=swarm-coloc CA", "-keyout", str(out / "ca.key"), "-out", str(out / "ca.pem"),
            "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign")
        def sign(name: str, subject: str, extensions: str) -> None:
            """A key ``<name>.key`` and its certificate ``<name>.pem``, signed by the CA."""
            run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-subj", subject,
                "-keyout", str(out / f"{name}.key"), "-out", str(out / f"{name}.csr"))
            ext = out / f"{name}.ext"
            ext.write_text(f"basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\n{extensions}")
            run("x509", "-req", "-in", str(out / f"{name}.csr"), "-CA", str(out / "ca.pem"), "-CAkey", str(out / "ca.key"),
                "-CAcreateserial", "-days", "825", "-extfile", str(ext), "-out", str(out / f"{name}.pem"))

        for name, hosts in certs:
            san = ",".join(f"IP:{h}" if re.fullmatch(r"[0-9.]+|[0-9a-fA-F:]+:[0-9a-fA-F:]*", h) else f"DNS:{h}" for h in hosts)
            sign(name, f"/CN={hosts[0]}", f"subjectAltName={san}\nextendedKeyUsage=serverAuth,clientAuth\n")
        for name in clients or []:
            sign(name, f"/CN=swarm-coloc {name}", "extendedKeyUsage=clientAuth\n")
    finally:
        os.umask(old)
        (out / "ca.key").unlink(missing_ok=True)  # whatever happened: the CA signs nothing more
    every = [*(name for name, _h in certs), *(clients or [])]
    for f in ("ca.srl", *(f"{name}.{x}" for name in every for x in ("csr", "ext"))):
        (out / f).unlink(missing_ok=True)
    for f in ("ca.pem", *(f"{name}.pem" for name in every)):
        os.chmod(out / f, 0o644)  # public
    for name in every:
        os.chmod(out / f"{name}.key", 0o600)


# -- the router -----------------------------------------------------------------------------
_INGRESS = (("put", ("put", "delete")), ("sub", ("declare_subscriber",)), ("query", ("query",)),
            ("serve", ("declare_queryable", "reply")), ("token", ("liveliness_token",)),
            ("watch", ("declare_liveliness_subscriber", "liveliness_query")))


def acl_config(run: str, n_sats: int, links: bool = False, peer_zids: tuple[str, ...] | list[str] = ()) -> dict:
    """Zenoh's ``access_control`` section for one run: deny by default; for each identity,
    what :func:`swarmrt.bus.messages.grants` allows it, and nothing else. ``peer_zids``:
    the Zenoh ids of the other routers of a mesh, given the ``mesh`` identity's rights.

    (A router that dialled another presented its ``mesh`` credential; the dialled router
    presented none — user/password authentication is one-way — so on the dialling side
    the link had no user name, matched no subject, and the default denied everything
    across it: clients of the two routers could not hear each other. Found by ``swarm
    chaos --routers 2``: an agent restarted onto the other router waited 120 s for its
    peers' tokens. The routers of a run have fixed ids, :func:`router_zid`.)"""
    keys = Keys(run)
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []
    root = f"{keys.root}/**"
    for name in [*IDENTITIES, *agent_identities(n_sats)]:
        g = grants(keys, name, links=links)
        ids: list[str] = []

        def rule(flow: str, messages: tuple[str, ...], key_exprs, what: str, _name=name, _ids=ids) -> None:
            if key_exprs:
                rid = f"{_name}:{flow}:{what}"
                rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
                              "key_exprs": sorted(set(key_exprs))})
                _ids.append(rid)

        for field, messages in _INGRESS:
            rule("ingress", messages, getattr(g, field), field)
        # What the router may send it: samples of what it may subscribe to, the queries
        # to what it serves, the replies to what it asks; declarations (who listens,
        # who serves, who is alive) of the run's keys, so that it knows where to send.
        rule("egress", ("put", "delete"), g.sub, "samples")
        rule("egress", ("query",), g.serve, "queries")
        rule("egress", ("reply",), g.query, "replies")
        rule("egress", ("declare_subscriber", "declare_queryable", "liveliness_token", "declare_liveliness_subscriber",
                        "liveliness_query"), [root], "declarations")
        subjects.append({"id": name, "usernames": [name]})
        who = [name]
        if name == "mesh" and peer_zids:
            subjects.append({"id": "mesh-routers", "zids": sorted(peer_zids)})
            who.append("mesh-routers")
        policies.append({"id": name, "rules": ids, "subjects": who})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


#: Router indices a run's mesh may use (``swarm run --routers 2``: 0 and 1; compose.routers2.yaml).
MESH_ROUTERS = 16


def router_zid(mesh_secret: str, index: int) -> str:
    """The Zenoh id of router ``index`` of a mesh: derived from the ``mesh`` identity's
    password (only routers hold it), so that each router knows its peers' ids before they
    connect and a client cannot guess one to pass for a router."""
    if not 0 <= index < MESH_ROUTERS:
        raise ValueError(f"router index {index}: 0..{MESH_ROUTERS - 1}")
    digest = hashlib.sha256(f"swarm-coloc/router/{index}/{mesh_secret}".encode()).hexdigest()
    return "a" + digest[:31]  # 16 bytes of hex, never all zeros


def _mesh_secret(dictionary_text: str) -> str | None:
    for line in dictionary_text.splitlines():
        user, sep, password = line.partition(":")
        if sep and user == "mesh" and password:
            return password
    return None


#: Kinds whose size the scenario bounds well: an estimate (a view of at most n satellites:
#: ~730 B each with its covariances), a health report and a fault report (small, whatever n).
_EST_BASE_BYTES, _EST_PER_SAT_BYTES, _SMALL_BYTES = 64 * 1024, 2 * 1024, 64 * 1024


def size_limit_of(kind: str, n_sats: int) -> int:
    """The largest message of ``kind`` the router lets through for an ``n_sats`` swarm:
    sized from the scenario where its size is bounded (``est``: 64 KiB + 2 KiB per
    satellite, ~3× the largest view; ``health`` and ``fault``: 64 KiB), else the limit
    every receiver holds it to (:data:`swarmrt.bus.messages.MAX_PAYLOAD_BYTES`)."""
    if kind == "est":
        return _EST_BASE_BYTES + _EST_PER_SAT_BYTES * n_sats
    if kind in ("health", "fault", "recorded"):
        return _SMALL_BYTES
    return MAX_PAYLOAD_BYTES.get(kind, MAX_PAYLOAD_DEFAULT)


def put_kinds(keys: Keys, identity: str, links: bool) -> list[tuple[str, str]]:
    """Each key ``identity`` may put (its grants) with the message kind it carries; keys of
    no message kind (liveliness) left out. What the router's size limits and the ingress
    gate's step budgets are sized from."""
    out = []
    for key in grants(keys, identity, links=links).put:
        try:
            out.append((key, parse_key(key.replace("*", "0"))[1]))
        except MessageError:
            continue
    return out


def size_limits(run: str, n_sats: int, links: bool = False) -> list[dict]:
    """Zenoh's ``low_pass_filter`` section for one run: for every key some identity may put
    (the same :func:`swarmrt.bus.messages.grants` the access rules come from), a put larger
    than :func:`size_limit_of` its kind is dropped by the router on the way in, before
    anyone has to receive it. Zenoh's filter selects by key, not by identity; the key space
    gives each identity its own keys (agent i alone puts on ``est/<i>``), so a limit per key
    is a limit per identity. (A rate limit, Zenoh's ``downsampling``, would drop messages,
    not delay them: in lockstep that is a broken step, so there is none.)"""
    keys = Keys(run)
    by_limit: dict[int, set[str]] = {}
    for name in [*IDENTITIES, *agent_identities(n_sats)]:
        if name == "mesh":
            continue  # a router meshed with this one forwards what its own clients put (and its filter checked)
        for key, kind in put_kinds(keys, name, links):
            by_limit.setdefault(size_limit_of(kind, n_sats), set()).add(key)
    return [{"id": f"size-{limit}", "flows": ["ingress"], "messages": ["put"], "key_exprs": sorted(ks), "size_limit": limit}
            for limit, ks in sorted(by_limit.items())]


def rate_limits(run: str, n_sats: int, links: bool, hz: float) -> list[dict]:
    """Zenoh's ``downsampling`` section that would cap every agent identity's puts at ``hz``
    per key, on the way in (one rule per key: Zenoh keeps one state per rule and transport).
    Not applied to a run unless ``SWARM_ROUTER_RATE_LIMIT_HZ`` is set, and then only to
    measure why not (``scripts/flood_bench.py --rate-limit-hz``; docs/security.md, "Size limits on
    the router"): Zenoh's downsampler passes a message only if 1/hz has gone by since the last it
    passed on that rule, with no allowance for a burst, and a role whose bus came back sends
    its last two steps' messages back to back (:class:`swarmrt.protocol.Outbox`), so the
    second, the step's own, is dropped however high ``hz`` is short of the burst's spacing."""
    keys = Keys(run)
    rules = [{"key_expr": key, "freq": float(hz)}
             for i in range(n_sats) for key in sorted(grants(keys, f"agent-{i}", links=links).put)]
    return [{"id": "rate", "flows": ["ingress"], "messages": ["put"], "rules": rules}]


def load_router_keys(keys_dir: str | Path) -> tuple[dict, Path, set[str]]:
    """What the router reads of a keys directory: ``router.json`` (or its default), the
    password dictionary's path and the user names in it. A missing or malformed file fails
    with SystemExit naming it and what is wrong."""
    meta, dictionary, text = _read_router_keys(keys_dir)
    return meta, dictionary, _dictionary_users(text)


def _dictionary_users(text: str) -> set[str]:
    return {line.split(":", 1)[0] for line in text.splitlines() if ":" in line}


def _read_router_keys(keys_dir: str | Path) -> tuple[dict, Path, str]:
    """:func:`load_router_keys` but with the dictionary's text (read once, bounded)."""
    keys_dir = Path(keys_dir)
    meta_path = keys_dir / "router.json"
    meta = _read_json(meta_path, "router keys") if meta_path.exists() else {"passwords": "passwords"}
    if not isinstance(meta, dict) or not isinstance(meta.get("passwords"), str) or not meta["passwords"]:
        raise SystemExit(f"router keys {meta_path}: expected a JSON object with \"passwords\" (the dictionary's file name)")
    tls = [f for f in ("certificate", "private_key") if f in meta]
    if tls and (len(tls) != 2 or not all(isinstance(meta[f], str) and meta[f] for f in tls)):
        raise SystemExit(f"router keys {meta_path}: \"certificate\" and \"private_key\" go together, each a file name")
    if "mtls" in meta and (meta["mtls"] not in (True, False) or (meta["mtls"] and not tls)):
        raise SystemExit(f"router keys {meta_path}: \"mtls\" is true or false, and true only with a \"certificate\"")
    dictionary = keys_dir / meta["passwords"]
    try:
        if not dictionary.is_file():
            raise SystemExit(f"router: no password dictionary at {dictionary} (make keys with `swarm keys`)")
        text = _read_bounded(dictionary).decode()
    except (OSError, ValueError) as exc:
        raise SystemExit(f"router: password dictionary {dictionary}: {exc}") from None
    return meta, dictionary, text


def apply_router_security(cfg, keys_dir: str | Path, run: str, n_sats: int, links: bool = False, index: int = 0) -> list[str]:
    """Make a router configuration secure: the password dictionary, the access rules of
    ``run``, and the TLS certificate and key when the keys have them; router ``index`` of
    a mesh gets its fixed id and its peers' (:func:`router_zid`). Returns the TLS settings
    applied (empty without TLS)."""
    keys_dir = Path(keys_dir)
    meta, dictionary, text = _read_router_keys(keys_dir)
    users = _dictionary_users(text)
    peer_zids: list[str] = []
    if (secret := _mesh_secret(text)) is not None:
        cfg.insert_json5("id", json.dumps(router_zid(secret, index)))
        peer_zids = [router_zid(secret, j) for j in range(MESH_ROUTERS) if j != index]
    missing = [a for a in agent_identities(n_sats) if a not in users]
    if missing:
        raise SystemExit(f"router: the keys in {keys_dir} have no credential for {', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''} (made for fewer satellites: `swarm keys --n-sats {n_sats}`)")
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary.resolve())))
    cfg.insert_json5("access_control", json.dumps(acl_config(run, n_sats, links, peer_zids)))
    if os.environ.get("SWARM_ROUTER_SIZE_LIMITS", "on") != "off":  # off: only to measure what they do (scripts/flood_bench.py)
        cfg.insert_json5("low_pass_filter", json.dumps(size_limits(run, n_sats, links)))
    if (hz := os.environ.get("SWARM_ROUTER_RATE_LIMIT_HZ")):  # only to measure what a rate limit breaks (rate_limits)
        cfg.insert_json5("downsampling", json.dumps(rate_limits(run, n_sats, links, float(hz))))
    if (keys_dir / "mesh.json").is_file():  # what it shows a router it meshes with
        load_credential(keys_dir / "mesh.json").apply(cfg)
    applied = []
    if "certificate" in meta:
        cert, key = (json.dumps(str((keys_dir / meta[f]).resolve())) for f in ("certificate", "private_key"))
        cfg.insert_json5("transport/link/tls/listen_certificate", cert)
        cfg.insert_json5("transport/link/tls/listen_private_key", key)
        applied.append("tls")
        if meta.get("mtls") is True:
            # Mutual TLS (a cluster's mesh): a TLS peer must show a certificate of the run's
            # CA (another node's router, or the driver's), so a stolen agent's password alone
            # cannot reach the router from another host, around the node's ingress gate; the
            # router dials its peers with its own certificate.
            _mutual_tls(cfg, cert, key)
            applied.append("mtls")
    return applied


def _mutual_tls(cfg, certificate_json: str, private_key_json: str) -> None:
    """Mutual TLS on: ask a TLS peer for its certificate, and show this one (JSON strings of
    the files' paths) when connecting."""
    cfg.insert_json5("transport/link/tls/enable_mtls", "true")
    cfg.insert_json5("transport/link/tls/connect_certificate", certificate_json)
    cfg.insert_json5("transport/link/tls/connect_private_key", private_key_json)


# -- a process's own credential -------------------------------------------------------------
class Credential:
    """One identity's credential (a ``<identity>.json`` of a keys directory)."""

    def __init__(self, user: str, password: str, ca: str | None = None, certificate: str | None = None,
                 private_key: str | None = None):
        if not _IDENT_RE.fullmatch(user):
            raise ValueError(f"credential: {user!r} is not a swarm identity")
        if (certificate is None) != (private_key is None):
            raise ValueError("credential: a client certificate and its private key go together")
        self.user = user
        self.password = password
        self.ca = ca
        self.certificate = certificate  # a client certificate (mutual TLS: a cluster's driver)
        self.private_key = private_key

    def with_identity(self, user: str, password: str) -> Credential:
        """The same trust (CA, client certificate), another identity (an --id auto agent once it has its satellite)."""
        return Credential(user, password, self.ca, self.certificate, self.private_key)

    def apply(self, cfg) -> None:
        cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(self.user))
        cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(self.password))
        if self.ca:
            cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(self.ca))
        if self.certificate and self.private_key:
            _mutual_tls(cfg, json.dumps(self.certificate), json.dumps(self.private_key))

    def __repr__(self) -> str:  # never the password
        return f"Credential({self.user!r}{', TLS' if self.ca else ''}{', client certificate' if self.certificate else ''})"


#: The largest keys file read (a credential is ~100 bytes; agents.json of 10,000 satellites ~450 KB).
MAX_KEYS_FILE_BYTES = 4 << 20


def _read_bounded(path: Path) -> bytes:
    """A keys file's bytes; ValueError if it is larger than any keys file can be."""
    with open(path, "rb") as f:
        raw = f.read(MAX_KEYS_FILE_BYTES + 1)
    if len(raw) > MAX_KEYS_FILE_BYTES:
        raise ValueError(f"larger than {MAX_KEYS_FILE_BYTES} bytes: not a keys file")
    return raw


def _read_json(path: Path, what: str):
    """A keys file's JSON value; SystemExit naming ``what``, the file and the problem."""
    try:
        return json.loads(_read_bounded(path))
    except FileNotFoundError:
        raise SystemExit(f"{what} {path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{what} {path}: {exc}") from None
    except RecursionError:
        raise SystemExit(f"{what} {path}: not valid JSON (nested too deeply)") from None


def load_credential(path: str | Path) -> Credential:
    """Read a credential file; a bad one fails naming the file and what is wrong."""
    path = Path(path)
    d = _read_json(path, "credential")
    if not isinstance(d, dict) or not isinstance(d.get("user"), str) or not isinstance(d.get("password"), str):
        raise SystemExit(f"credential {path}: expected a JSON object with \"user\" and \"password\"")
    files: dict[str, str | None] = {}
    for field, what in (("ca", "CA certificate"), ("certificate", "client certificate"), ("private_key", "client private key")):
        name = d.get(field)
        if name is not None:
            if not isinstance(name, str) or not name or "\0" in name:
                raise SystemExit(f"credential {path}: \"{field}\" must be the {what}'s file name, not {str(name)[:80]!r}")
            try:
                name = str((path.parent / name).resolve())
                found = Path(name).is_file()
            except (OSError, ValueError):
                found = False
            if not found:
                raise SystemExit(f"credential {path}: its {what} {str(name)[:300]} is missing")
        files[field] = name
    try:
        return Credential(d["user"], d["password"], files["ca"], files["certificate"], files["private_key"])
    except ValueError as exc:
        raise SystemExit(f"credential {path}: {exc}") from None


_SAT_RE = re.compile(r"[0-9]{1,5}")


def load_agent_passwords(path: str | Path) -> dict[int, str]:
    """``agents.json``: satellite → password (the world's, for --id auto agents)."""
    path = Path(path)
    d = _read_json(path, "agent passwords")
    if not isinstance(d, dict):
        raise SystemExit(f"agent passwords {path}: expected a JSON object of satellite id → password")
    for k, v in d.items():
        if not _SAT_RE.fullmatch(k) or int(k) > MAX_SAT_ID:
            raise SystemExit(f"agent passwords {path}: {k[:80]!r} is not a satellite id (0-{MAX_SAT_ID})")
        if not isinstance(v, str):
            raise SystemExit(f"agent passwords {path}: satellite {k}'s password is a {type(v).__name__}, not a string")
    return {int(k): v for k, v in d.items()}
