"""The agent contract's document, the kit's clause table and its injected messages agree
(no bus; the kit itself runs in tests/test_conformance.py)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import zenoh

from swarm.conformance.clauses import CLAIMS, CLAUSES, CONTRACT_VERSION, SCHEMA
from swarm.conformance.inputs import injections, self_check
from swarm.conformance.kit import CASE_NAMES, DEFAULT_SCENARIO, kit_scenario
from swarmcore.scenario import Scenario
from swarmcore.streams import stream
from swarmrt.bus.messages import Keys, grants

DOC = Path(__file__).resolve().parents[1] / "docs" / "agent-contract.md"


def test_the_document_and_the_kit_number_the_same_clauses():
    text = DOC.read_text()
    assert f"**Contract version {CONTRACT_VERSION}, for the wire schema `{SCHEMA}`**" in text
    heads = re.findall(r"^### (C\d+)\. (.*)$", text, flags=re.M)
    assert [h[0] for h in heads] == [c.id for c in CLAUSES]
    optional = text.split("## Optional clauses", 1)[1]
    for c in CLAUSES:
        title = dict(heads)[c.id]
        if c.mandatory:
            assert f"### {c.id}." not in optional, c.id
        else:
            assert f"### {c.id}." in optional and f"(claim `{c.claim}`)" in title, (c.id, title)
    for name in CASE_NAMES:
        assert f"| {name} |" in text, name  # the kit's table of cases
    assert set(CLAIMS) == {"warm-rejoin", "late-replay"}


def test_the_drop_draws_in_the_document_are_the_streams():
    """C12's table is what another language must reproduce: it must stay the truth."""
    text = DOC.read_text()
    rows = re.findall(r"^\| (\d+) \| (\d+) \| (\d+) \| (\d) \| ([0-9.]+) \|$", text, flags=re.M)
    assert len(rows) == 4
    for seed, i, k, what, value in rows:
        assert repr(stream(int(seed), "drop", int(i), int(k), int(what)).random()) == value


def test_injections_are_what_they_claim_and_reach_only_the_agents_inputs():
    items = injections("cf-x", 1, 4, 5)
    self_check(items, 4)
    assert sum(not i.forged for i in items) == 6 and sum(i.forged for i in items) == 4
    keys = Keys("cf-x")
    mine = set(grants(keys, "agent-1").sub)
    world_may = set(grants(keys, "world").put)
    def allowed(key, exprs):
        return any(zenoh.KeyExpr(e).includes(zenoh.KeyExpr(key)) for e in exprs)

    for it in items:
        assert allowed(it.key, mine) and allowed(it.key, world_may), it.key


def test_the_kit_scenario_refuses_what_it_cannot_run():
    base = kit_scenario(None, 1, "prog")
    assert base.n_sats == DEFAULT_SCENARIO["n_sats"] and base.emulator.agent_commands == {1: "prog"}
    assert base.emulator.time_mode == "lockstep" and not base.links.enabled and base.faults == []
    with pytest.raises(ValueError, match="at least 15 steps"):
        kit_scenario(Scenario(n_sats=4, duration_s=5), 1, "prog")
    with pytest.raises(ValueError, match="not a satellite"):
        kit_scenario(None, 7, "prog")


def test_from_env_names_a_missing_variable(capsys):
    from sat_agent.from_env import environment

    with pytest.raises(SystemExit) as e:
        environment({"SWARM_SAT_ID": "1"})
    assert e.value.code == 2
    assert "SWARM_RUN is not set" in capsys.readouterr().err
    env = {"SWARM_SAT_ID": "1", "SWARM_RUN": "r", "SWARM_CONNECT": "tcp/127.0.0.1:1", "SWARM_SCENARIO_JSON": "s.json",
           "SWARM_RESTART": "0"}
    assert environment(env)["SWARM_CREDENTIAL"] == ""


def test_c13_takes_the_token_back_whichever_the_recorder_heard_first():
    """The times of CI's failed run (ns after the agent's first token): killed at 4.897 s,
    its token gone at 4.902 s, the new process's token at 5.598423 s, the supervisor's
    report that it started it 0.3 ms later. The token is back; one that never went is not
    taken for a return; a token up before the kill is not the new process's."""
    from swarm.conformance.judge import token_gone_and_back

    s = 1_000_000_000
    events = [(True, 0), (False, 4_901_609_541), (True, 5_598_423_075)]
    gone, ups = token_gone_and_back(events, t_kill_cmd=4_897_397_269, t_started=5_598_711_249)
    assert gone and ups == [5_598_423_075]
    gone, ups = token_gone_and_back([(True, 0)], t_kill_cmd=4 * s, t_started=5 * s)
    assert not gone and ups == []
    gone, ups = token_gone_and_back([(True, 0), (False, 4 * s + 1)], t_kill_cmd=4 * s, t_started=5 * s)
    assert gone and ups == []
