"""Compose's keys service (swarm/supervise/compose_keys.py) without Docker: keys made on
first use and kept after, each role given its files and nothing else, and the compose files
agreeing with its table of roles. tests/test_compose.py runs it for real."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from swarm.supervise.compose_keys import ROLE_FILES, main, role_files
from swarmrt.security import make_keys

ROOT = Path(__file__).resolve().parents[1]


def _roles(tmp_path: Path, *names: str) -> Path:
    roles = tmp_path / "roles"
    for n in names:
        (roles / n).mkdir(parents=True)
    return roles


def test_first_use_makes_the_keys_then_keeps_them(tmp_path, capsys):
    keys, roles = tmp_path / "keys", _roles(tmp_path, *ROLE_FILES)
    assert main(["--keys", str(keys), "--roles", str(roles), "--n-sats", "5", "--tls", "sat-host.example, 10.1.2.3"]) == 0
    assert "made" in capsys.readouterr().err
    assert (keys / "passwords").is_file() and keys.stat().st_mode & 0o777 == 0o700
    assert json.loads((keys / "router.json").read_text())["n_sats"] == 100  # at least `swarm keys`' default
    assert not [p for p in keys.iterdir() if p.name.startswith(".")]  # no leftover of the making
    names = subprocess.run(["openssl", "x509", "-in", str(keys / "router.pem"), "-noout", "-ext", "subjectAltName"],
                           capture_output=True, text=True, check=True).stdout
    for h in ("DNS:router", "DNS:localhost", "IP Address:127.0.0.1", "DNS:sat-host.example", "IP Address:10.1.2.3"):
        assert h in names, names
    before = {p.name: p.read_bytes() for p in keys.iterdir()}
    # Every later run keeps them (what `docker compose up` does each time).
    assert main(["--keys", str(keys), "--roles", str(roles)]) == 0
    assert "using the keys" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in keys.iterdir()} == before


def test_each_role_gets_its_files_and_nothing_else(tmp_path):
    keys = make_keys(tmp_path / "keys", 4, tls_hosts=["router"])
    roles = _roles(tmp_path, *ROLE_FILES)
    (roles / "agent" / "world.json").write_text("left over from another layout\n")
    assert main(["--keys", str(keys), "--roles", str(roles)]) == 0
    for role, files in ROLE_FILES.items():
        got = sorted(p.name for p in (roles / role).iterdir())
        assert got == sorted(files), (role, got)
        for f in files:
            assert (roles / role / f).read_bytes() == (keys / f).read_bytes()
            mode = (roles / role / f).stat().st_mode & 0o777
            assert mode == (0o644 if f.endswith(".pem") else 0o600), (role, f, oct(mode))
    # Agents hold no one else's credential, above all not the world's list of agent passwords.
    assert not {"agents.json", "world.json", "passwords", "router.key"} & set(ROLE_FILES["agent"])
    # New keys (swarm keys --force) reach the roles on the next run.
    make_keys(keys, 4, tls_hosts=["router"])
    assert main(["--keys", str(keys), "--roles", str(roles)]) == 0
    assert (roles / "world" / "agents.json").read_bytes() == (keys / "agents.json").read_bytes()


def test_keys_without_tls_are_refused_naming_the_command(tmp_path, capsys):
    keys = make_keys(tmp_path / "keys", 4)  # swarm keys --no-tls
    assert main(["--keys", str(keys), "--roles", str(_roles(tmp_path, "router", "agent")), "--shown-as", "./keys"]) == 2
    err = capsys.readouterr().err
    assert "ca.pem" in err and "swarm keys --force" in err, err


def test_a_certificate_for_other_names_is_warned_about(tmp_path, capsys):
    keys = make_keys(tmp_path / "keys", 4, tls_hosts=["compose-host.example"])
    assert main(["--keys", str(keys), "--roles", str(_roles(tmp_path, "agent"))]) == 0
    err = capsys.readouterr().err
    assert "not valid for router" in err and "--tls router" in err, err


def test_an_unknown_role_folder_is_an_error(tmp_path):
    keys = make_keys(tmp_path / "keys", 4, tls_hosts=["router"])
    with pytest.raises(SystemExit, match="no role spy"):
        main(["--keys", str(keys), "--roles", str(_roles(tmp_path, "spy"))])


def _compose(*files: str) -> dict:
    """The services of compose files merged as compose does for what is checked here
    (volumes by container path, depends_on by service)."""
    services: dict[str, dict] = {}
    for f in files:
        # ${VAR:-default} as compose reads it with VAR unset (the test's environment says nothing)
        text = re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", (ROOT / f).read_text())
        for name, svc in (yaml.safe_load(text)["services"] or {}).items():
            cur = services.setdefault(name, {})
            for k, v in (svc or {}).items():
                if k == "volumes":
                    vols = {str(x).split(":")[1]: x for x in cur.get("volumes", [])}
                    vols.update({str(x).split(":")[1]: x for x in v})
                    cur["volumes"] = list(vols.values())
                elif k == "depends_on":
                    dep = cur.get("depends_on", {})
                    cur["depends_on"] = {**dep, **(v if isinstance(v, dict) else {d: {"condition": "service_started"} for d in v})}
                else:
                    cur[k] = v
    return services


@pytest.mark.parametrize("files", [("compose.yaml",), ("compose.yaml", "compose.routers2.yaml"), ("compose.yaml", "compose.remote.yaml"),
                                   ("compose.yaml", "compose.rust.yaml")])
def test_compose_files_agree_with_the_roles_table(files):
    """Every swarm service waits for the keys service and mounts one role's volume at
    /run/secrets; the keys service fills that volume; the credential a service is given
    on its command line is among its role's files."""
    services = _compose(*files)
    filled = {}
    for v in services["keys"]["volumes"]:
        src, dst = str(v).split(":")[:2]
        if dst.startswith("/roles/"):
            filled[src] = dst.removeprefix("/roles/")
    assert all(role_files(r) is not None for r in filled.values()), filled
    for name, svc in services.items():
        if "cluster" in svc.get("profiles", []):
            assert "keys" not in svc.get("depends_on", {}), f"{name}: the Dask cluster needs no keys"
            continue
        if name == "keys":
            continue
        assert svc["depends_on"]["keys"] == {"condition": "service_completed_successfully"}, name
        secrets = [str(v).split(":") for v in svc["volumes"] if str(v).split(":")[1] == "/run/secrets"]
        assert len(secrets) == 1 and secrets[0][2] == "ro", (name, svc["volumes"])
        role = filled.get(secrets[0][0])
        assert role is not None, f"{name} mounts {secrets[0][0]}, which the keys service does not fill"
        cmd = " ".join(svc["command"])
        for used in re.findall(r"/run/secrets/([\w.-]+)", cmd):
            assert used in (role_files(role) or ()), (name, used, role)
        assert "secrets" not in svc, name


def test_a_fixed_satellite_role_gets_its_own_credential_only(tmp_path):
    """compose.rust.yaml's agent-<i> role: satellite i's credential and the CA, nothing else."""
    keys, roles = tmp_path / "keys", _roles(tmp_path, "agent-4", "agent")
    assert main(["--keys", str(keys), "--roles", str(roles), "--n-sats", "5"]) == 0
    assert sorted(p.name for p in (roles / "agent-4").iterdir()) == ["agent-4.json", "ca.pem"]
    assert json.loads((roles / "agent-4" / "agent-4.json").read_text())["user"] == "agent-4"
    assert role_files("agent-x") is None and role_files("agents") is None


def test_keys_stay_out_of_the_repository_and_the_image():
    r = subprocess.run(["git", "check-ignore", "-q", "keys/passwords"], cwd=ROOT)
    assert r.returncode == 0, "./keys is not git-ignored"
    ignored = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()]
    assert "keys" in ignored, ".dockerignore does not keep ./keys out of the build context"


def test_the_module_runs_as_the_keys_service_runs_it(tmp_path):
    roles = _roles(tmp_path, "agent")
    p = subprocess.run([sys.executable, "-m", "swarm.supervise.compose_keys", "--keys", str(tmp_path / "k"), "--roles", str(roles),
                        "--owner-of", str(tmp_path), "--n-sats", "5", "--tls", "", "--shown-as", "./keys"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "made ./keys" in p.stderr and "gave agent their credentials" in p.stderr, p.stderr
    st = tmp_path.stat()
    assert all((f.stat().st_uid, f.stat().st_gid) == (st.st_uid, st.st_gid) for f in (tmp_path / "k").iterdir())
