"""`make demo`'s scenario: valid, the default swarm, distributed with a selector, and the
faults the README's quick start lists. (Faulted distributed runs themselves — a camera off,
an agent killed, an agent killed and restarted — are run in tests/test_integration_swarm.py.)"""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from swarmrt.scenario_files import load_scenario

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenarios" / "demo-faults.yaml"


def _readme_demo_faults() -> list[dict]:
    """The YAML block of the quick start that is headed ``# scenarios/demo-faults.yaml``."""
    text = (ROOT / "README.md").read_text()
    quick = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    blocks = [b for b in re.findall(r"```yaml\n(.*?)```", quick, flags=re.S) if "scenarios/demo-faults.yaml" in b]
    assert len(blocks) == 1, "the quick start must show demo-faults.yaml's faults in one yaml block"
    return yaml.safe_load(blocks[0])["faults"]


def test_demo_scenario_validates_and_is_the_default_swarm_with_a_selector():
    sc = load_scenario(DEMO)
    base = load_scenario(ROOT / "scenarios" / "demo.yaml")
    # The default swarm: every field of demo.yaml but the name, the selection and the faults.
    skip = {"name", "selection", "faults"}
    assert sc.model_dump(exclude=skip) == base.model_dump(exclude=skip)
    assert base.faults == [] and base.selection.strategy == "none"  # demo.yaml stays fault-free
    assert sc.selection.strategy != "none", "the demo must start the selector process"
    assert sc.selection.budget < sc.n_sats * (sc.n_sats - 1), "a budget that takes every pair selects nothing"
    assert sc.vision.distributed_refusal() is None  # `swarm run` accepts it


def test_demo_faults_are_the_ones_the_readme_lists():
    sc = load_scenario(DEMO)
    listed = _readme_demo_faults()
    got = [f.model_dump(exclude_none=True) for f in sc.faults]
    assert got == listed
    actions = [f.action for f in sc.faults]
    # What issue 10 asks the demo to show: a camera off, an agent killed and later restarted.
    assert "camera" in actions
    kill = next(f for f in sc.faults if f.action == "kill-agent")
    restart = next(f for f in sc.faults if f.action == "restart-agent")
    assert restart.target == kill.target and kill.at_step < restart.at_step < sc.steps - 1


def test_make_demo_runs_the_demo_scenario_distributed_and_writes_the_report():
    make = (ROOT / "Makefile").read_text()
    recipe = make.split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    assert "run scenarios/demo-faults.yaml" in recipe and " report " in recipe
    assert " sim " not in recipe  # the in-process simulator is `make sim`
    assert "\nsim:" in make
