"""Links end to end: in-process and distributed give the same numbers with latency,
jitter, bursty loss, a rate cap and a dead link; every filter still holds every satellite
within 3σ."""

from __future__ import annotations

import numpy as np
import pytest
from swarm_harness import run_swarm, scenario, within_3sigma_fraction

from swarm.simulation import simulate_scenario
from swarmcore import quat
from swarmcore.mekf import BLOCK

LINKS = {
    "enabled": True,
    "latency": {"fixed_s": 1.2, "jitter": {"distribution": "exponential", "scale_s": 0.4}},
    "loss": {"model": "gilbert_elliott", "rate": 0.2, "mean_burst": 2.0},
    "rate_Bps": 2500.0,
    "queue_bytes": 6000,
    "overrides": [{"from": 1, "to": 2, "dead": True}, {"from": 3, "to": 0, "loss": {"model": "bernoulli", "rate": 0.5}}],
}


def _sim_3sigma(res) -> np.ndarray:
    """(F, n): for each (filter, satellite) pair, the fraction of its (step, component)
    errors within 3σ after step 5, in-process. A pair is held on its own, not in an
    aggregate that one bad pair could hide in."""
    a = quat.local(res.truth.q_BI[:, None], res.est.q_BI)  # (K, F, n, 3)
    dr = res.truth.r_H_m[:, None] - res.est.r_H_m
    K, F, n = a.shape[:3]
    P = res.est.P_diag.reshape(K, F, n, BLOCK)
    sd = np.sqrt(np.concatenate([P[..., 0:3], P[..., 6:9]], axis=-1))
    e = np.concatenate([a, dr], axis=-1)
    return np.mean(np.abs(e[5:]) <= 3 * sd[5:], axis=(0, 3))


def test_a_dead_link_leaves_every_filter_estimating_every_satellite_within_3_sigma():
    sc = scenario(n_sats=4, duration_s=60, links=LINKS)
    res = simulate_scenario(sc)
    s = res.summary()
    assert s["links"]["per_link"]["unreachable"][1][2] == sc.steps and s["links"]["per_link"]["sent"][1][2] == 0
    frac = _sim_3sigma(res)
    # 6 components × 55 steps per pair: a consistent filter leaves ~0.3 % outside 3σ; 95 %
    # per pair still fails a pair that spends a twentieth of the run overconfident.
    assert frac.min() >= 0.95, np.round(frac, 3)
    assert s["late"]["used"] > 0


@pytest.mark.integration
def test_links_distributed_equal_in_process(tmp_path):
    sc = scenario(n_sats=4, duration_s=20, links=LINKS)
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")  # a random run id: sizes on the radio do not depend on it
    assert codes["world"] == 0
    ref = simulate_scenario(sc).summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "late", "links"):
        assert summary[key] == ref[key], key
    t = ref["links"]["totals"]
    assert t["lost"] > 0 and t["dropped_queue"] > 0 and t["delivered_late"] > 0 and t["unreachable"] > 0
    # Every survivor (all four) holds every satellite, the cut link's ends included.
    for target in range(4):
        frac, count = within_3sigma_fraction(rec, [0, 1, 2, 3], target, k_from=5)
        assert count > 0 and frac >= 0.95, (target, frac)


@pytest.mark.integration
def test_link_faults_at_run_time_act_on_the_radio(tmp_path):
    """Scheduled link faults (the world carries them out at their step, before its radio):
    satellite 1 cut off for 5 steps (every link both ways unreachable), 0 → 2 2 s slower for
    4 steps (every batch late), 3 → 0 losing half for 4 steps; each given back the
    scenario's parameters. Counted per directed link, reported done by the world."""
    faults = [{"at_step": 5, "action": "link", "target": 1, "state": "off"},
              {"at_step": 10, "action": "link", "target": 1, "state": "on"},
              {"at_step": 12, "action": "link", "target": 0, "peer": 2, "delay_s": 2.0},
              {"at_step": 16, "action": "link", "target": 0, "peer": 2, "state": "on"},
              {"at_step": 18, "action": "link", "target": 3, "peer": 0, "rate": 0.5},
              {"at_step": 22, "action": "link", "target": 3, "peer": 0, "state": "on"}]
    sc = scenario(n_sats=4, duration_s=26, links={"enabled": True, "latency": {"speed_of_light": False}}, faults=faults)
    rec, summary, codes, _sw = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    per = summary["links"]["per_link"]
    unreachable = np.array(per["unreachable"])
    expect = np.zeros((4, 4), dtype=int)
    expect[1, [0, 2, 3]] = expect[[0, 2, 3], 1] = 5
    np.testing.assert_array_equal(unreachable, expect)
    late = np.array(per["delivered_late"])
    assert late[0, 2] == 4 and late.sum() == 4, late
    lost = np.array(per["lost"])
    assert lost[3, 0] >= 1 and lost.sum() == lost[3, 0], lost  # seeded draws at 50 % over 4 steps
    done = [f for f in summary.get("faults", []) if f["action"] == "link" and f["phase"] == "done"] or \
        [f for f in rec.bus.faults if f.get("action") == "link" and f.get("phase") == "done"]
    assert len(done) == 6 and {f["sender"] for f in done} == {"world"}, done
    # Listed with what they did (a chaos campaign matches each fired command by these).
    assert [(f["target"], f["peer"], f["state"], f["delay_s"], f["rate"]) for f in done] == \
        [(x["target"], x.get("peer"), x.get("state"), x.get("delay_s"), x.get("rate")) for x in faults]


@pytest.mark.integration
def test_free_running_links_delay_in_wall_time_and_late_batches_are_replayed(tmp_path):
    """Free-running mode: the radio delays batches in (scaled) wall time; each agent takes
    what has arrived when it updates and replays the rest when it comes."""
    sc = scenario(n_sats=3, duration_s=30, emulator={"time_mode": "free", "realtime_factor": 5.0},
                  links={"enabled": True, "latency": {"fixed_s": 1.5, "speed_of_light": False}})
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    assert rec.alive.mean() > 0.8
    lat = np.array([x[3] for x in rec.links.latencies])
    assert lat.size > 0 and np.all(lat >= 1.5) and np.median(lat) < 1.5 + 0.5 * sc.dt_s * 5
    assert summary["late"]["used"] > 0
    assert summary["rms_second_half"]["others"]["pos_m"] < 0.1


@pytest.mark.integration
def test_a_restarted_agent_gets_its_state_through_the_radio(tmp_path):
    """With links, the full estimate a restarted agent fetches from a peer crosses the
    radio: it takes the peer's transmitter (a 20 kB/s cap takes ~1.3 s for it) and the latency,
    and the agent rejoins at the first step at or after its arrival."""
    sc = scenario(n_sats=4, duration_s=40, faults=[{"at_step": 10, "action": "kill-agent", "target": 2},
                                                   {"at_step": 15, "action": "restart-agent", "target": 2}],
                  links={"enabled": True, "latency": {"fixed_s": 0.5}, "rate_Bps": 20000.0, "queue_bytes": 10**6})
    rec, _summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    fates = [f for f in rec.bus.rejoins if f["sat"] == 2]
    assert fates and fates[0]["fate"] == "delivered"
    size, t_arr = fates[0]["bytes"], fates[0]["arrival_t_s"]
    assert size > 12 * 4 * 12 * 4 * 8  # the full 48×48 covariance at least
    assert t_arr >= 15 * sc.dt_s + size / 20000.0 + 0.5 - 1e-9
    first = int(np.ceil(t_arr / sc.dt_s - 1e-9))
    alive2 = np.flatnonzero(rec.alive[:, 2])
    back = alive2[alive2 > 10]
    assert back.size and back[0] >= first, (back[:3], first)
    frac, count = within_3sigma_fraction(rec, [2], 2, k_from=int(back[0]) + 3)
    assert count > 0 and frac >= 0.9, frac


@pytest.mark.integration
def test_swarm_run_prints_its_link_table(tmp_path):
    """`swarm run` ends with the link table, as `swarm sim` does, whether or not the bus had a
    gap (it used to print it only after a gap)."""
    import json
    import os
    import subprocess
    import sys

    import yaml

    scn = tmp_path / "links.yaml"
    scn.write_text(yaml.safe_dump({"name": "lt", "seed": 2, "n_sats": 3, "duration_s": 8,
                                   "links": {"enabled": True, "latency": {"fixed_s": 0.5}}}))
    env = dict(os.environ, COLUMNS="240")
    run = subprocess.run([sys.executable, "-m", "swarm.cli", "run", str(scn), "--out", str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=600, env=env)
    sim = subprocess.run([sys.executable, "-m", "swarm.cli", "sim", str(scn), "--out", str(tmp_path / "sim")],
                         capture_output=True, text=True, timeout=600, env=env)
    assert run.returncode == 0 and sim.returncode == 0, run.stderr[-2000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert not summary.get("bus_gaps")
    for out in (run.stdout + run.stderr, sim.stdout + sim.stderr):
        assert "links (all directed links)" in out, out[-3000:]
        assert str(summary["links"]["totals"]["sent"]) in out
