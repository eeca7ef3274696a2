"""Compose's ``keys`` service: the swarm's credentials on first use, each role given its own.

python -m swarm.supervise.compose_keys --keys /keys --roles /roles --owner-of /scenarios

Runs before every other service of compose.yaml (they wait for it to complete):

1. ``--keys`` (the host's ``${SWARM_KEYS:-./keys}``, bind-mounted) holds no keys
   (no ``passwords``): make them there, as ``swarm keys`` does (TLS for
   :data:`~swarmrt.security.DEFAULT_TLS_HOSTS` and ``--tls``), owned by the owner of
   ``--owner-of`` (a folder of the checkout), so that the user who ran ``docker compose
   up`` can read ``cli.json`` for ``swarm fault --compose`` and replace them with ``swarm
   keys --force``. Keys already there are kept, whoever made them.
2. Every folder ``--roles/<role>`` (a named volume the role mounts read-only at
   /run/secrets) is given that role's files of :data:`ROLE_FILES` and nothing else, as
   compose's file secrets did: an agent container holds the claimant's credential and the
   CA, never the world's list of agent passwords. A folder ``agent-<i>`` is given satellite
   i's own credential and the CA: an agent of another language with a fixed satellite
   (compose.rust.yaml), which claims nothing.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["ROLE_FILES", "ensure_keys", "give_roles", "main", "role_files"]

#: What each role's container finds at /run/secrets (compose.yaml mounts volume
#: ``keys-<role>`` there; the keys service mounts it at ``/roles/<role>``).
ROLE_FILES: dict[str, tuple[str, ...]] = {
    "router": ("passwords", "router.json", "router.pem", "router.key"),
    # compose.routers2.yaml's second router: the first's files, and what it shows the
    # first when it connects (the "mesh" identity, checked against the CA).
    "router2": ("passwords", "router.json", "router.pem", "router.key", "mesh.json", "ca.pem"),
    "recorder": ("recorder.json", "ca.pem"),
    "world": ("world.json", "agents.json", "ca.pem"),
    "selector": ("selector.json", "ca.pem"),
    # Every --id auto agent: compose's replicas and compose.remote.yaml's remote_agent.
    "agent": ("claimant.json", "ca.pem"),
    # The live 3-D view (profile "live"): the read-only viewer.
    "live": ("viewer.json", "ca.pem"),
}


def role_files(role: str) -> tuple[str, ...] | None:
    """The files of ``role``: :data:`ROLE_FILES`, or for ``agent-<i>`` (a satellite flown
    by a program with a fixed id) its own credential and the CA; None for no such role."""
    if role in ROLE_FILES:
        return ROLE_FILES[role]
    if m := re.fullmatch(r"agent-(\d{1,6})", role):
        return (f"agent-{int(m[1])}.json", "ca.pem")
    return None


#: Roles a keys directory made before them may lack the files of: skipped with a warning
#: (the swarm runs; that service cannot connect until the keys are replaced).
OPTIONAL_ROLES = frozenset({"live"})

_PUBLIC = {"ca.pem", "router.pem"}


def _say(msg: str) -> None:
    print(f"keys: {msg}", file=sys.stderr, flush=True)


def ensure_keys(keys: Path, n_sats: int, tls_hosts: list[str], owner_of: Path | None = None, shown: str | None = None) -> bool:
    """Make the keys in ``keys`` unless it already holds some (a ``passwords`` file).
    Returns True when it made them. Made in a folder beside them first, so that an
    interrupted run never leaves half a keys directory that a later one would keep."""
    from swarmrt.security import make_keys

    shown = shown or str(keys)
    if (keys / "passwords").is_file():
        return False
    keys.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".new-", dir=keys))
    try:
        make_keys(tmp, n_sats, tls_hosts=tls_hosts)
        # The password dictionary last: its presence is what says "keys here".
        for f in sorted(tmp.iterdir(), key=lambda p: p.name == "passwords"):
            os.replace(f, keys / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    os.chmod(keys, 0o700)
    if owner_of is not None:
        st = owner_of.stat()
        for p in [keys, *keys.iterdir()]:
            os.chown(p, st.st_uid, st.st_gid)
    _say(f"made {shown}: credentials of {n_sats} agents and the other roles, a CA and a router certificate for "
         f"{', '.join(tls_hosts)} (never commit them: ./keys is git-ignored; `swarm keys --force` replaces them)")
    return True


def _missing(keys: Path, roles: list[str]) -> list[str]:
    need = sorted({f for r in roles for f in role_files(r) or ()})
    return [f for f in need if not (keys / f).is_file()]


def give_roles(keys: Path, roles_dir: Path, skip: frozenset[str] | set[str] = frozenset()) -> list[str]:
    """Copy each role's files into ``roles_dir/<role>`` (replacing what was there), but the
    roles in ``skip``. Returns the roles served."""
    roles = sorted(p.name for p in roles_dir.iterdir() if p.is_dir() and p.name not in skip) if roles_dir.is_dir() else []
    unknown = [r for r in roles if role_files(r) is None]
    if unknown:
        raise SystemExit(f"keys: no role {', '.join(unknown)} (known: {', '.join(ROLE_FILES)}, agent-<i>)")
    for role in roles:
        dest = roles_dir / role
        want = role_files(role) or ()
        for old in dest.iterdir():
            if old.name in want:
                continue
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink()
        for name in want:
            tmp = dest / f".{name}.new"
            shutil.copyfile(keys / name, tmp)
            os.chmod(tmp, 0o644 if name in _PUBLIC else 0o600)
            os.replace(tmp, dest / name)
    return roles


def _cert_names(pem: Path) -> set[str] | None:
    """The names and addresses a certificate is valid for (None: openssl could not tell)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        return None
    p = subprocess.run([openssl, "x509", "-in", str(pem), "-noout", "-ext", "subjectAltName"], capture_output=True, text=True)
    if p.returncode != 0:
        return None
    return set(re.findall(r"(?:DNS|IP Address):([^,\s]+)", p.stdout))


def main(argv=None) -> int:
    from swarmrt.security import DEFAULT_TLS_HOSTS

    p = argparse.ArgumentParser(description="compose's keys service: make the keys on first use, give each role its own")
    p.add_argument("--keys", type=Path, required=True, help="the keys directory (made when it holds no keys; kept otherwise)")
    p.add_argument("--roles", type=Path, required=True, help="a folder of role folders (role names of ROLE_FILES) to fill")
    p.add_argument("--owner-of", type=Path, default=None, help="keys made here belong to this path's owner and group")
    p.add_argument("--n-sats", type=int, default=100, help="make credentials for at least this many agents (default 100)")
    p.add_argument("--tls", default="", help="more names or addresses the router's certificate must be valid for "
                   f"(comma- or space-separated; always {', '.join(DEFAULT_TLS_HOSTS)})")
    p.add_argument("--shown-as", default=None, help="the keys directory's name on the host, for messages")
    a = p.parse_args(argv)
    shown = a.shown_as or str(a.keys)
    extra = [h for h in re.split(r"[,\s]+", a.tls) if h]
    hosts = list(dict.fromkeys([*DEFAULT_TLS_HOSTS, *extra]))
    if not ensure_keys(a.keys, max(a.n_sats, 100), hosts, a.owner_of, shown):
        _say(f"using the keys in {shown}")
    roles = sorted(p.name for p in a.roles.iterdir() if p.is_dir()) if a.roles.is_dir() else []
    late = {r for r in roles if r in OPTIONAL_ROLES and _missing(a.keys, [r])}
    if late:
        _say(f"{shown} lacks {', '.join(_missing(a.keys, sorted(late)))} (keys made before the {', '.join(sorted(late))} service): "
             f"it cannot connect; `swarm keys --force --out {shown}` replaces the keys")
    missing = _missing(a.keys, [r for r in roles if role_files(r) is not None and r not in late])
    if missing:
        _say(f"{shown} lacks {', '.join(missing)}: the compose swarm needs keys with TLS (its router also listens on "
             f"tls/0.0.0.0:7449). Replace them: swarm keys --force --out {shown}")
        return 2
    # compose.remote.yaml's agent checks the certificate against "router"; --tls names more.
    if (a.keys / "router.pem").is_file() and (names := _cert_names(a.keys / "router.pem")) is not None:
        lacking = [h for h in ["router", *extra] if h not in names]
        if lacking:
            _say(f"warning: the router's certificate in {shown} is not valid for {', '.join(lacking)} (it is for "
                 f"{', '.join(sorted(names))}): TLS clients that name it so are refused. Replace the keys: swarm keys --force "
                 f"--out {shown} {' '.join(f'--tls {h}' for h in hosts)}")
    served = give_roles(a.keys, a.roles, skip=late)
    _say(f"gave {', '.join(served) or 'no role'} their credentials")
    return 0


if __name__ == "__main__":
    sys.exit(main())
