"""The `swarm` command line, run as real processes."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from swarmcore.sim import simulate
from swarmrt.scenario_files import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SWARM = [sys.executable, "-m", "swarm.cli"]


def run(*args, check=True):
    p = subprocess.run([*SWARM, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"swarm {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def _cli_tree():
    """``{path: command}`` for every visible command and group of the ``swarm`` CLI, the
    root at ``()``. typer builds a click tree; groups are the nodes with ``commands``."""
    import typer

    from swarm.cli import app

    tree = {}

    def walk(cmd, path):
        tree[path] = cmd
        for name, sub in getattr(cmd, "commands", {}).items():
            if not sub.hidden:
                walk(sub, (*path, name))

    walk(typer.main.get_command(app), ())
    return tree


def _listed_commands(help_text: str) -> set[str]:
    """The command names in the Commands section of a help page (rich panel or plain click)."""
    if "─ Commands ─" in help_text:
        body = help_text.split("─ Commands ─", 1)[1].split("╰", 1)[0]
        return set(re.findall(r"^│ (\S+)", body, flags=re.M))
    body = help_text.split("Commands:", 1)[1]
    return set(re.findall(r"^  (\S+)", body, flags=re.M))


def test_help_names_every_command():
    """The root and every group's ``--help`` (real processes) list exactly their
    subcommands, and every command answers its own ``--help``. (That every command the
    README and docs/ quote parses, and that the README names every command, is
    tests/test_docs.py's.)"""
    tree = _cli_tree()
    groups = [p for p, c in tree.items() if hasattr(c, "commands")]
    assert len(groups) >= 4 and len(tree) >= 20, "the CLI tree looks empty: the walk is broken"
    for path in groups:
        out = run(*path, "--help").stdout
        assert _listed_commands(out) == {p[-1] for p in tree if p[:-1] == path and len(p) == len(path) + 1}, path
    # Every command, group or leaf, has its own help page under its own name.
    from typer.testing import CliRunner

    from swarm.cli import app

    runner = CliRunner()
    for path, cmd in tree.items():
        if not path or path in groups:
            continue  # run as processes above
        r = runner.invoke(app, [*path, "--help"], prog_name="swarm")
        assert r.exit_code == 0, (path, r.output)
        assert re.search(rf"Usage: swarm {re.escape(' '.join(path))}\b", r.output), (path, r.output)
        for p in cmd.params:
            if p.param_type_name == "option" and not p.hidden:
                assert p.opts[0] in r.output, f"`swarm {' '.join(path)} --help` does not show {p.opts[0]}"
    # And a name that is not a command is refused.
    bad = run("no-such-command", check=False)
    assert bad.returncode == 2 and "no-such-command" in bad.stderr
    assert "--set" in run("sim", "--help").stdout


def test_sim_writes_the_contract_and_matches_in_process_run(tmp_path):
    out = tmp_path / "run"
    run("sim", "scenarios/demo.yaml", "--out", str(out), "--set", "duration_s=12", "--seed", "5")
    s = json.loads((out / "summary.json").read_text())
    for key in ("n_sats", "steps", "dt", "seed"):
        assert key in s
    assert s["n_sats"] == 4 and s["steps"] == 13 and s["seed"] == 5
    for block in ("rms", "rms_second_half"):
        for who in ("self", "others"):
            assert set(s[block][who]) == {"att_rad", "pos_m"}
    assert len(s["per_pair"]) == 16 and set(s["per_pair"][0]) == {"observer", "target", "att_rad", "pos_m"}
    assert s["nees"]["dof"] == 6 and s["gate"]["accepted"] > 0 and s["timing"]["filter_step_ms_median"] > 0
    truth = np.load(out / "truth.npz")
    assert truth["q_BI"].shape == (13, 4, 4) and truth["r_H"].shape == (13, 4, 3)
    for k in ("t", "omega_BI_B", "v_H"):
        assert k in truth
    est = np.load(out / "estimates.npz")
    assert est["q_BI"].shape == (13, 4, 4, 4) and est["P_diag"].shape == (13, 4, 48)
    # Same scenario and seed in this process: the same numbers, bit for bit.
    sc = load_scenario(ROOT / "scenarios/demo.yaml", ["duration_s=12"], seed=5)
    res = simulate(sc)
    np.testing.assert_array_equal(res.est.r_H_m, est["r_H"])
    np.testing.assert_array_equal(res.truth.q_BI, truth["q_BI"])
    assert res.summary()["rms"] == s["rms"]


def test_bad_scenario_fails_with_a_message_naming_the_field(tmp_path):
    p = run("sim", "scenarios/demo.yaml", "--out", str(tmp_path / "x"), "--set", "sensors.gps.sigma_m=0", check=False)
    assert p.returncode == 2
    assert "sensors.gps.sigma_m" in p.stderr and "greater than 0" in p.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_mc_runs_seeds_in_parallel_and_aggregates(tmp_path):
    out = tmp_path / "mc"
    run("mc", "scenarios/demo.yaml", "--runs", "3", "--workers", "2", "--seed", "40", "--out", str(out), "--set", "duration_s=8")
    mc = json.loads((out / "mc.json").read_text())
    assert mc["seeds"] == [40, 41, 42] and mc["runs"] == 3
    vals = [json.loads((out / f"run_{i:04d}" / "summary.json").read_text())["rms"]["others"]["pos_m"] for i in range(3)]
    st = mc["stats"]["rms.others.pos_m"]
    assert st["mean"] == pytest.approx(np.mean(vals)) and st["std"] == pytest.approx(np.std(vals, ddof=1))
    for key in ("rms.self.att_rad", "rms_second_half.others.att_rad", "nees.mean"):
        assert key in mc["stats"]
    # Run i is the scenario with seed S + i.
    single = simulate(load_scenario(ROOT / "scenarios/demo.yaml", ["duration_s=8"], seed=41)).summary()
    assert single["rms"]["others"]["pos_m"] == vals[1]


def test_bench_filter_writes_rows(tmp_path):
    f = tmp_path / "b.json"
    run("bench", "filter", "--sats", "3,4", "--steps", "3", "--out", str(f))
    rows = json.loads(f.read_text())
    assert [r["n"] for r in rows] == [3, 4]
    for r in rows:
        assert set(r) >= {"n", "graph", "ms_per_step_median", "stacked_ms_per_step_median", "ratio"}
        assert r["ms_per_step_median"] > 0 and r["ratio"] > 0


@pytest.mark.render
@pytest.mark.slow
def test_sim_runs_the_rendered_monocular_scenario(tmp_path):
    out = tmp_path / "mono"
    run("sim", "scenarios/mono-5sat.yaml", "--out", str(out), "--set", "duration_s=4")
    s = json.loads((out / "summary.json").read_text())
    assert s["n_sats"] == 5 and s["gate"]["accepted"] > 50
    # Measurements from images: of the dissertation's order at these ranges.
    assert s["rms_second_half"]["others"]["pos_m"] < 0.05 and s["rms_second_half"]["others"]["att_rad"] < 0.01


@pytest.mark.slow
def test_starfox_study_runs_both_configurations_and_refuses_an_unknown_one(tmp_path):
    """`swarm starfox` (the StarFOX-like study, once a script): one seed of each configuration
    in-process, its JSON (per run and aggregate) and figure written; the same seed gives the
    same numbers as a direct call of the study's run function; an unknown configuration is a
    usage error that names it."""
    from typer.testing import CliRunner

    from swarm.cli import app
    from swarm.studies.starfox import KEYS, one_run

    root = Path(__file__).resolve().parents[1]
    scenario, sets = str(root / "scenarios" / "starfox.yaml"), ["duration_s=300"]
    r = CliRunner().invoke(app, ["starfox", scenario, "--runs", "1", "--workers", "1", "--out", str(tmp_path),
                                 *[a for s in sets for a in ("--set", s)]], prog_name="swarm")
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "starfox.json").read_text())
    assert (tmp_path / "percent-of-range.png").stat().st_size > 10_000
    assert [p["config"] for p in doc["per_run"]] == ["single", "several"] and doc["failed"] == []
    for c in ("single", "several"):
        agg = doc["aggregate"][c]
        assert agg["runs"] == 1 and all(np.isfinite(agg[k]["mean"]) for k in KEYS), agg
    seed = doc["per_run"][0]["seed"]
    again = one_run((scenario, "single", seed, sets))
    assert {k: again[k] for k in KEYS} == {k: doc["per_run"][0][k] for k in KEYS}
    # satellite 0 alone sees less than the whole swarm: its relative error is the larger
    assert doc["aggregate"]["single"]["err_pct"]["mean"] > doc["aggregate"]["several"]["err_pct"]["mean"]
    bad = CliRunner().invoke(app, ["starfox", scenario, "--configs", "single,lonely", "--out", str(tmp_path / "x")], prog_name="swarm")
    assert bad.exit_code == 2 and "lonely" in bad.output, bad.output


def test_starfox_per_estimator_table(tmp_path):
    """`swarm starfox --estimators`: one seed per estimator on the same seed, the table per
    estimator written (the JSON lines resumable: a second call runs nothing more); an
    unknown estimator is a usage error that names it."""
    from typer.testing import CliRunner

    from swarm.cli import app

    root = Path(__file__).resolve().parents[1]
    scenario = str(root / "scenarios" / "starfox.yaml")
    args = ["starfox", scenario, "--estimators", "ci,gbp", "--configs", "several", "--runs", "1", "--out", str(tmp_path),
            "--set", "duration_s=200", "--set", "links.enabled=false"]
    r = CliRunner().invoke(app, args, prog_name="swarm")
    assert r.exit_code == 0, r.output
    rows = [json.loads(line) for line in (tmp_path / "per-estimator.jsonl").read_text().splitlines()]
    assert sorted(x["estimator"] for x in rows) == ["ci", "gbp"] and len({x["seed"] for x in rows}) == 1
    table = (tmp_path / "per-estimator.md").read_text()
    assert "| several | ci | 1 |" in table and "| several | gbp | 1 |" in table, table
    again = CliRunner().invoke(app, args, prog_name="swarm")
    assert again.exit_code == 0 and len((tmp_path / "per-estimator.jsonl").read_text().splitlines()) == 2
    bad = CliRunner().invoke(app, [*args[:3], "ci,nosuch", *args[4:]], prog_name="swarm")
    assert bad.exit_code == 2 and "nosuch" in bad.output, bad.output
