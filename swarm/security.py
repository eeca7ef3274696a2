"""Who may say what on the bus: credentials, the router's access rules, TLS.

Every process of a swarm connects to the router with its own identity: ``world``,
``selector``, ``recorder``, ``cli`` (``swarm fault``), ``supervisor`` (``swarm run``),
``observer`` (read-only tools: tests, participants of other languages), ``claimant`` (an
agent started with ``--id auto`` before it has a satellite), ``mesh`` (a router meshed
with another: it forwards everyone's traffic, so its rules allow the run's whole key
space) and ``agent-<i>``, bound to satellite i. Two Zenoh features carry it, nothing hand-written on the wire:

- **authentication**: Zenoh's user/password authentication (``transport/auth/usrpwd``; the
  router holds a dictionary file of ``user:password`` lines). It is a challenge-response:
  the password itself never crosses the link. A session without a valid credential is
  refused when it connects.
- **access control** on the router (``access_control``, ``default_permission: deny``): a
  subject per identity (by user name), and rules generated from the one table of who may
  use which key, :func:`swarm.bus.messages.grants`. Ingress: what the identity may put,
  subscribe to, query, serve and declare alive. Egress: what the router may send it
  (samples only of keys it may subscribe to, so no agent is ever sent the truth).

Across hosts, **TLS** (``tls/`` endpoints; the router's certificate is signed by a CA
the keys directory holds, and every credential names that CA) encrypts the traffic too.

A keys directory (``swarm run`` makes one per run in its output folder; ``swarm keys``
makes one for compose or several hosts; never in the repository)::

    passwords          the router's dictionary (user:password per line)
    router.json        what the router needs: the dictionary's file name, TLS files if any
    <identity>.json    one credential: {"user": ..., "password": ..., "ca": "ca.pem" (TLS)}
    agents.json        every agent's password, for the world alone: it hands satellite i's
                       to the --id auto agent it gives satellite i (see below)
    ca.pem, router.pem, router.key   with TLS (swarm keys --tls): the CA (ca.key is not
                       kept), the router's certificate and key

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

import json
import os
import re
import secrets
import shutil
import subprocess
from pathlib import Path

from .bus.messages import IDENTITIES, Keys, grants

__all__ = ["make_keys", "acl_config", "apply_router_security", "Credential", "load_credential", "agent_identities"]

_IDENT_RE = re.compile("|".join([*IDENTITIES, r"agent-\d+"]))


def agent_identities(n_sats: int) -> list[str]:
    return [f"agent-{i}" for i in range(n_sats)]


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def make_keys(out: str | Path, n_sats: int, tls_hosts: list[str] | None = None) -> Path:
    """Make a keys directory for a swarm of ``n_sats`` satellites (fresh random passwords;
    ``tls_hosts``: also a CA and a router certificate valid for those names/addresses)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    names = [*IDENTITIES, *agent_identities(n_sats)]
    pw = {name: secrets.token_urlsafe(24) for name in names}
    _write_private(out / "passwords", "".join(f"{n}:{p}\n" for n, p in pw.items()))
    tls = bool(tls_hosts)
    if tls:
        _make_tls(out, tls_hosts)
    for name in names:
        cred = {"user": name, "password": pw[name], **({"ca": "ca.pem"} if tls else {})}
        _write_private(out / f"{name}.json", json.dumps(cred) + "\n")
    _write_private(out / "agents.json", json.dumps({str(i): pw[f"agent-{i}"] for i in range(n_sats)}) + "\n")
    router = {"passwords": "passwords", "n_sats": n_sats, **({"certificate": "router.pem", "private_key": "router.key"} if tls else {})}
    _write_private(out / "router.json", json.dumps(router) + "\n")
    return out


def _make_tls(out: Path, hosts: list[str]) -> None:
    """A CA and a router certificate signed by it (openssl, as any operator would; the CA's
    key is deleted once it has signed: new hosts mean new keys)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError("TLS keys need the openssl command (Debian: apt-get install openssl)")
    san = ",".join(f"IP:{h}" if re.fullmatch(r"[0-9.]+|[0-9a-fA-F:]+:[0-9a-fA-F:]*", h) else f"DNS:{h}" for h in hosts)

    def run(*args: str) -> None:
        p = subprocess.run([openssl, *args], capture_output=True, text=True)
        if p.returncode != 0:
            raise RuntimeError(f"openssl {args[0]}: {p.stderr.strip()[-500:]}")

    old = os.umask(0o077)
    try:
        run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "825",
            "-subj", "/CN=swarm-coloc CA", "-keyout", str(out / "ca.key"), "-out", str(out / "ca.pem"),
            "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign")
        run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-subj", f"/CN={hosts[0]}",
            "-keyout", str(out / "router.key"), "-out", str(out / "router.csr"))
        ext = out / "router.ext"
        ext.write_text(f"subjectAltName={san}\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth\n")
        run("x509", "-req", "-in", str(out / "router.csr"), "-CA", str(out / "ca.pem"), "-CAkey", str(out / "ca.key"),
            "-CAcreateserial", "-days", "825", "-extfile", str(ext), "-out", str(out / "router.pem"))
    finally:
        os.umask(old)
    for f in ("ca.key", "router.csr", "router.ext", "ca.srl"):
        (out / f).unlink(missing_ok=True)
    for f in ("ca.pem", "router.pem"):
        os.chmod(out / f, 0o644)  # public
    os.chmod(out / "router.key", 0o600)


# -- the router -----------------------------------------------------------------------------
_INGRESS = (("put", ("put", "delete")), ("sub", ("declare_subscriber",)), ("query", ("query",)),
            ("serve", ("declare_queryable", "reply")), ("token", ("liveliness_token",)),
            ("watch", ("declare_liveliness_subscriber", "liveliness_query")))


def acl_config(run: str, n_sats: int, links: bool = False) -> dict:
    """Zenoh's ``access_control`` section for one run: deny by default; for each identity,
    what :func:`swarm.bus.messages.grants` allows it, and nothing else."""
    keys = Keys(run)
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []
    root = f"{keys.root}/**"
    for name in [*IDENTITIES, *agent_identities(n_sats)]:
        g = grants(keys, name, links=links)
        ids = []

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
        policies.append({"id": name, "rules": ids, "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def apply_router_security(cfg, keys_dir: str | Path, run: str, n_sats: int, links: bool = False) -> list[str]:
    """Make a router configuration secure: the password dictionary, the access rules of
    ``run``, and the TLS certificate and key when the keys have them. Returns the TLS
    settings applied (empty without TLS)."""
    keys_dir = Path(keys_dir)
    meta_path = keys_dir / "router.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {"passwords": "passwords"}
    dictionary = keys_dir / meta["passwords"]
    if not dictionary.is_file():
        raise SystemExit(f"router: no password dictionary at {dictionary} (make keys with `swarm keys`)")
    users = {line.split(":", 1)[0] for line in dictionary.read_text().splitlines() if ":" in line}
    missing = [a for a in agent_identities(n_sats) if a not in users]
    if missing:
        raise SystemExit(f"router: the keys in {keys_dir} have no credential for {', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''} (made for fewer satellites: `swarm keys --n-sats {n_sats}`)")
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary.resolve())))
    cfg.insert_json5("access_control", json.dumps(acl_config(run, n_sats, links)))
    if (keys_dir / "mesh.json").is_file():  # what it shows a router it meshes with
        load_credential(keys_dir / "mesh.json").apply(cfg)
    applied = []
    if "certificate" in meta:
        cfg.insert_json5("transport/link/tls/listen_certificate", json.dumps(str((keys_dir / meta["certificate"]).resolve())))
        cfg.insert_json5("transport/link/tls/listen_private_key", json.dumps(str((keys_dir / meta["private_key"]).resolve())))
        applied.append("tls")
    return applied


# -- a process's own credential -------------------------------------------------------------
class Credential:
    """One identity's credential (a ``<identity>.json`` of a keys directory)."""

    def __init__(self, user: str, password: str, ca: str | None = None):
        if not _IDENT_RE.fullmatch(user):
            raise ValueError(f"credential: {user!r} is not a swarm identity")
        self.user = user
        self.password = password
        self.ca = ca

    def with_identity(self, user: str, password: str) -> Credential:
        """The same trust (CA), another identity (an --id auto agent once it has its satellite)."""
        return Credential(user, password, self.ca)

    def apply(self, cfg) -> None:
        cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(self.user))
        cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(self.password))
        if self.ca:
            cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(self.ca))

    def __repr__(self) -> str:  # never the password
        return f"Credential({self.user!r}{', TLS' if self.ca else ''})"


def load_credential(path: str | Path) -> Credential:
    """Read a credential file; a bad one fails naming the file and what is wrong."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise SystemExit(f"credential {path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise SystemExit(f"credential {path}: {exc}") from None
    if not isinstance(d, dict) or not isinstance(d.get("user"), str) or not isinstance(d.get("password"), str):
        raise SystemExit(f"credential {path}: expected a JSON object with \"user\" and \"password\"")
    ca = d.get("ca")
    if ca is not None:
        ca = str((path.parent / ca).resolve())
        if not Path(ca).is_file():
            raise SystemExit(f"credential {path}: its CA certificate {ca} is missing")
    try:
        return Credential(d["user"], d["password"], ca)
    except ValueError as exc:
        raise SystemExit(f"credential {path}: {exc}") from None


def load_agent_passwords(path: str | Path) -> dict[int, str]:
    """``agents.json``: satellite → password (the world's, for --id auto agents)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
        return {int(k): str(v) for k, v in d.items()}
    except (OSError, ValueError, AttributeError) as exc:
        raise SystemExit(f"agent passwords {path}: {exc}") from None
