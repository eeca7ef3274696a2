"""The import contracts hold the architecture (pyproject.toml, docs/architecture.md), and
they can fail: a copy of the tree with one deliberately wrong import breaks exactly the
contract that forbids it. (A contract that cannot break would hold nothing.)"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("swarmcore", "swarmvision", "swarmrt", "swarm", "world_sim", "sat_agent", "selector")
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(tree: Path) -> subprocess.CompletedProcess[str]:
    # The copy comes first on the path, ahead of the editable install of the checkout.
    env = dict(os.environ, PYTHONPATH=str(tree), COLUMNS="400")  # one contract per line
    return subprocess.run([str(LINT), "--no-cache"], cwd=tree, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    dst = tmp_path_factory.mktemp("tree")
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, dst / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    clean = _lint(dst)
    assert clean.returncode == 0, clean.stdout + clean.stderr
    assert "5 kept, 0 broken" in clean.stdout, clean.stdout
    return dst


def _broken(out: str) -> set[str]:
    # "NAME BROKEN" or "NAME BROKEN (k ignored imports)"
    return {line.split(" BROKEN", 1)[0].strip() for line in out.splitlines() if " BROKEN" in line and not line.startswith(" ")}


@pytest.mark.parametrize(
    ("module", "wrong_import", "contract"),
    [
        # flight software reaching for the truth
        ("sat_agent/protocol.py", "import swarmcore.world", "Flight software reads no truth"),
        # the core reaching up into the application
        ("swarmcore/quat.py", "import swarm.outputs", "Layers: application > roles > runtime > vision > core"),
        # a role importing a sibling role
        ("selector/protocol.py", "import world_sim.protocol", "Layers: application > roles > runtime > vision > core"),
        # a protocol machine importing the bus
        ("world_sim/protocol.py", "import zenoh", "Protocol machines are bus-free"),
        # the core reading YAML files
        ("swarmcore/quat.py", "import yaml", "The core is pure"),
        # vision reaching for the bus
        ("swarmvision/tags.py", "import zenoh", "Vision imports no bus"),
    ],
)
def test_a_wrong_import_breaks_its_contract(tree: Path, module: str, wrong_import: str, contract: str) -> None:
    path = tree / module
    original = path.read_text()
    try:
        path.write_text(original + f"\n{wrong_import}  # deliberately wrong (test_contracts)\n")
        res = _lint(tree)
    finally:
        path.write_text(original)
    assert res.returncode != 0, res.stdout
    broken = _broken(res.stdout)
    assert any(name.startswith(contract) for name in broken), (contract, broken, res.stdout[-2000:])
