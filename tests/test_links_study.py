"""``swarm links-study``: a tiny sweep through the real command writes its table and plots,
and every number in it is what a direct run of the same cell gives."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from swarm.simulation import simulate_scenario
from swarmrt.scenario_files import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "scenarios" / "links-study.yaml"
BASE = ["duration_s=6"]


def _cell_sets(p: dict) -> list[str]:
    """The overrides a cell stands for, as its documentation states them (``--set`` form)."""
    sets = ["links.enabled=true", f"links.latency.fixed_s={p['latency_s']}", "links.latency.speed_of_light=false",
            f"filter.late={p['late']}"]
    if p["loss"] > 0:
        sets += ["links.loss.model=gilbert_elliott", f"links.loss.rate={p['loss']}", f"links.loss.mean_burst={p['mean_burst']}"]
    if p["rate_Bps"] is not None:
        sets += [f"links.rate_Bps={p['rate_Bps']!r}", f"links.queue_bytes={p['queue_bytes']}"]
    if p["arm"] == "greedy":
        sets += ["selection.strategy=greedy", f"selection.budget={p['budget']}"]
    elif p["group"] == "cap":
        sets += ["selection.strategy=none"]
    return sets


@pytest.mark.slow
def test_tiny_sweep_through_the_command_equals_direct_runs(tmp_path):
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "swarm.cli", "links-study", str(SCEN), "--out", str(out), "--runs", "1", "--workers", "2",
           "--latencies", "0,2", "--losses", "0.3", "--caps", "0.5", *[a for s in BASE for a in ("--set", s)]]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stdout + p.stderr
    for f in ("links_study.md", "links_study.json", "latency.png", "loss.png", "cap.png"):
        assert (out / f).stat().st_size > 0, f
    doc = json.loads((out / "links_study.json").read_text())
    cells = {c["key"]: c for c in doc["cells"]}
    params = [c["params"] for c in doc["cells"]]
    # 2 latencies × replay/drop, the loss rate at 2 s × replay/drop, and at the cap: the
    # complete graph, greedy, and greedy without the cap.
    assert sorted((q["group"], q["latency_s"], q["loss"], q["late"]) for q in params if q["group"] != "cap") == [
        ("latency", 0.0, 0.0, "drop"), ("latency", 0.0, 0.0, "replay"), ("latency", 2.0, 0.0, "drop"), ("latency", 2.0, 0.0, "replay"),
        ("loss", 2.0, 0.3, "drop"), ("loss", 2.0, 0.3, "replay")]
    caps = [q for q in params if q["group"] == "cap"]
    assert [(q["arm"], q["rate_Bps"] is not None) for q in caps] == [("complete", True), ("greedy", True), ("greedy", False)]
    md = (out / "links_study.md").read_text()
    assert md.count("\n| latency |") == 4 and md.count("\n| loss |") == 2 and md.count("\n| cap | 0 | 0% |") == 3
    assert "## replay / drop" in md and "## greedy / complete under the cap" in md
    seed = doc["seeds"][0]
    # swarm report takes the study's folder too.
    p = subprocess.run([sys.executable, "-m", "swarm.cli", "report", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    page = (out / "report" / "report.html").read_text()
    assert "replay / drop" in page and page.count("data:image/png;base64,") == 3

    # Every cell's numbers are those of a direct run of the same scenario (same seed).
    for key, c in cells.items():
        q = c["params"]
        res = simulate_scenario(load_scenario(SCEN, BASE + _cell_sets(q), seed=seed))
        s = res.summary()
        (run,) = c["runs"]
        assert run["att_others"] == s["rms"]["others"]["att_rad"], key
        assert run["pos_others"] == s["rms"]["others"]["pos_m"], key
        assert run["nees"] == s["nees"]["mean"], key
        assert run["links"] == s["links"]["totals"], key
        assert run["late"] == s["late"], key
        assert c["stats"]["att_others"]["mean"] == run["att_others"]
        if (q["latency_s"], q["loss"], q["late"], q["rate_Bps"]) == (0.0, 0.0, "replay", None) and q["arm"] == "complete":
            # Latency 0 without range / c is the ideal network: bit-equal to no links at all.
            ideal = simulate_scenario(load_scenario(SCEN, [*BASE, "links.enabled=false"], seed=seed))
            np.testing.assert_array_equal(res.est.q_BI, ideal.est.q_BI)
            np.testing.assert_array_equal(res.est.P_diag, ideal.est.P_diag)
            # What the complete graph needs (the probe): n − 1 copies of each batch per step.
            K = res.K
            sent_per_tx = np.asarray(s["links"]["per_link"]["bytes_delivered"]).sum(axis=1) / K / res.scenario.dt_s
            np.testing.assert_allclose(doc["probe"]["need_Bps"], sent_per_tx.max(), rtol=0.02)
        if q["arm"] == "greedy" and q["rate_Bps"] is None:
            # The budget's swarm-average load per transmitter fits the cap it was chosen for.
            cap = next(x["rate_Bps"] for x in caps if x["rate_Bps"] is not None)
            tot = s["links"]["totals"]["bytes_delivered"] / res.scenario.n_sats / res.K / res.scenario.dt_s
            assert tot <= cap, (tot, cap)
    # Replay beats drop at 2 s (every peer batch is late; drop throws all of them away).
    r = next(c for c in cells.values() if c["params"]["group"] == "latency" and c["params"]["latency_s"] == 2 and c["params"]["late"] == "replay")
    d = next(c for c in cells.values() if c["params"]["group"] == "latency" and c["params"]["latency_s"] == 2 and c["params"]["late"] == "drop")
    assert r["runs"][0]["late"]["used"] > 0 and d["runs"][0]["late"]["dropped"] > 0
    assert r["stats"]["att_others"]["mean"] < d["stats"]["att_others"]["mean"]


def test_bad_sweep_options_fail_naming_the_option(tmp_path):
    from typer.testing import CliRunner

    from swarm.cli import app

    res = CliRunner().invoke(app, ["links-study", str(SCEN), "--out", str(tmp_path), "--losses", "0.3,1.5"])
    assert res.exit_code == 2 and "--losses" in res.output
    res = CliRunner().invoke(app, ["links-study", str(SCEN), "--out", str(tmp_path), "--late", "replay,sometimes"])
    assert res.exit_code == 2 and "--late" in res.output
