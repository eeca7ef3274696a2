"""The Rust agent shares only the .proto schemas with the emulator, not code: the lists its
checks hold as data of its own must stay the emulator's. Read from its source (a fast test,
no cargo): the fault actions it accepts, and the ones that need a target satellite."""

import re
from pathlib import Path

from swarmcore.scenario import FAULT_ACTIONS, TARGETED_FAULTS

CHECKS = Path(__file__).resolve().parents[1] / "participants" / "rust-agent" / "src" / "checks.rs"


def _rust_str_array(name: str) -> list[str]:
    """The strings of ``const NAME: [&str; N] = [...]`` in checks.rs, with N checked."""
    src = CHECKS.read_text()
    m = re.search(rf"const {name}: \[&str; (\d+)\]\s*=\s*\[(.*?)\];", src, re.S)
    assert m, f"{CHECKS}: no const {name}: [&str; N]"
    items = re.findall(r'"([^"]*)"', m.group(2))
    assert len(items) == int(m.group(1))
    return items


def test_the_rust_agent_accepts_exactly_the_emulators_fault_actions():
    assert _rust_str_array("FAULT_ACTIONS") == list(FAULT_ACTIONS)


def test_the_rust_agent_asks_a_target_of_exactly_the_emulators_targeted_faults():
    assert sorted(_rust_str_array("TARGETED")) == sorted(TARGETED_FAULTS)
