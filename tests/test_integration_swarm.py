"""The distributed emulator, for real: every role its own process on a loopback Zenoh bus.

No mock of the bus anywhere; waits are on events (liveliness, messages) with timeouts.
"""

import json
import os
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh
from swarm_harness import run_swarm, scenario, within_3sigma_fraction, within_3sigma_per_observer

from swarm.simulation import simulate_scenario
from swarmcore.cameras import best_camera
from swarmcore.estimators import estimator_class
from swarmcore.graphs import radio_peers, scenario_graph
from swarmcore.mekf import RelativeMeasurements
from swarmcore.sensors import relative_pose
from swarmcore.sim import simulate
from swarmcore.world import initial_truth, step_truth, world_params
from swarmrt.bus import messages as M
from swarmrt.bus.convert import batch_msg
from swarmrt.bus.messages import Clock, Keys

pytestmark = pytest.mark.integration


def test_distributed_run_equals_in_process_run(tmp_path):
    sc = scenario(duration_s=15)
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    res = simulate_scenario(sc)  # with each batch's size on the bus, as the agents count it
    ref = res.summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean"):
        assert summary[key] == ref[key], key
    assert summary["steps"] == sc.steps and rec.alive.all()
    # One result schema: the recording's RunResult is the simulator's, array for array (but
    # the wall-clock times, and the schedule: without a selector no `select` is recorded).
    assert_same_arrays(rec, res)
    _check_complete_recording(tmp_path / "run" / "run.mcap", sc)
    # Every message's one-way bus latency (publisher's Zenoh timestamp → recorder) is
    # recorded: on loopback, small and positive for every sender.
    lat = summary["bus_latency_ms"]
    print("bus latency (ms):", json.dumps(lat))
    assert set(lat) == {"world", *(f"agent-{i}" for i in range(sc.n_sats))}, lat
    for sender, s in lat.items():
        assert s["n"] >= sc.steps and "unstamped" not in s, (sender, s)
        assert 0 < s["min"] <= s["p50"] <= s["p95"] <= s["max"] and s["p50"] < 100.0, (sender, s)


@pytest.mark.parametrize("estimator", ["ci", "pairwise", "gbp"])
def test_graph_radio_run_equals_in_process_run(tmp_path, estimator):
    """An estimator that hears only its graph neighbours (radio "graph"): each agent is sent
    only their batches (batches/<i>), and the numbers are still the simulator's, bit for bit."""
    sc = scenario(duration_s=8, n_sats=7, estimator={"kind": estimator}, graph={"kind": "nearest", "neighbors": 2},
                  initial={"layout": "lattice"})
    hears = radio_peers(scenario_graph(sc), "graph")
    assert hears is not None and max(len(h) for h in hears) < sc.n_sats - 1  # the test means something: not everyone
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    res = simulate_scenario(sc)
    ref = res.summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean"):
        assert json.dumps(summary[key]) == json.dumps(ref[key]), key  # NaN (pairs never estimated) equal too
    assert_same_arrays(rec, res)
    _check_complete_recording(tmp_path / "run" / "run.mcap", sc)


def test_gbp_late_run_equals_in_process_run(tmp_path):
    """``gbp`` (``fusion: joint``) behind a 2 s link latency: every message late, replayed at
    its step, each cavity sent predicted to the step it is used at and held messages carried
    through the dynamics; across processes the numbers are still the simulator's, bit for bit."""
    sc = scenario(duration_s=10, n_sats=6, estimator={"kind": "gbp"}, graph={"kind": "nearest", "neighbors": 2},
                  initial={"layout": "lattice"}, filter={"late": "replay", "history_s": 30},
                  links={"enabled": True, "latency": {"fixed_s": 2.0, "speed_of_light": False}})
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    res = simulate_scenario(sc)
    ref = res.summary()
    assert ref["late"]["used"] > 0
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean"):
        assert json.dumps(summary[key]) == json.dumps(ref[key]), key
    assert_same_arrays(rec, res)


def test_bearing_run_equals_in_process_run(tmp_path):
    """Angles-only bearings flown by ``ci`` (``scenarios/starfox.yaml``, 100 s: J2 truth and
    filter, bearings, GPS on one satellite, the delayed lossy crosslink, late replay): each
    observer turns its lines of sight into I with its own-state prediction, in its process
    as in the simulator, and the numbers are the simulator's, bit for bit."""
    from pathlib import Path

    from swarmrt.scenario_files import load_scenario

    sc = load_scenario(Path(__file__).resolve().parents[1] / "scenarios" / "starfox.yaml", ["duration_s=100", "estimator.kind=ci"])
    assert sc.sensors.relative.model == "bearing" and sc.links.enabled
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    res = simulate_scenario(sc)
    ref = res.summary()
    assert ref["gate"]["accepted"] + int(res.late_used.sum()) > 0  # bearings were fused (on time or replayed)
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean"):
        assert json.dumps(summary[key]) == json.dumps(ref[key]), key
    assert_same_arrays(rec, res)


def assert_same_arrays(rec, res) -> None:
    """A recording's RunResult holds the simulator's arrays, dtype and bits (NaN equal to
    NaN), but the wall-clock times and the schedule (no `select` is recorded without a
    selector)."""
    want = dict(_arrays(res))
    for name, a in _arrays(rec):
        b = want[name]
        if name not in ("step_ms", "cpu_ms", "schedule"):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name


def _arrays(r, prefix=""):
    """Every array of a RunResult (and of its truth and estimates), by name."""
    import dataclasses

    for f in dataclasses.fields(r):
        v = getattr(r, f.name)
        if isinstance(v, np.ndarray):
            yield prefix + f.name, v
        elif dataclasses.is_dataclass(v) and f.name in ("truth", "est"):
            yield from _arrays(v, f"{f.name}.")


def _check_complete_recording(path, sc):
    """A fault-free lockstep run's recording holds exactly its protocol: one channel per key
    of the run (nothing malformed, no selector, no faults), every message valid under the
    schema its channel names, published (Zenoh timestamp) before it was received, one per step
    and satellite on each per-step channel — plus the derived Foxglove channels."""
    from collections import defaultdict

    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.messages import decode, parse_key

    n, K = sc.n_sats, sc.steps
    chans = defaultdict(list)
    for topic, schema, data, log_ns, pub_ns in iter_messages(path):
        chans[topic].append((schema, data, log_ns - pub_ns))
    runs = {t.split("/")[1] for t in chans if t.startswith("swarm/")}
    assert len(runs) == 1, runs
    run = runs.pop()
    root = f"swarm/{run}"
    per_sat = [f"{root}/{kind}" for i in range(n) for kind in (f"sat/{i}/sensors", f"sat/{i}/cam", f"meas/{i}", f"est/{i}", f"health/{i}")]
    # The ideal radio: one message a step to everyone, or (radio "graph") one to each agent.
    hears = radio_peers(scenario_graph(sc), estimator_class(sc.estimator.kind).radio)
    radio_keys = [f"{root}/batches"] if hears is None else [f"{root}/batches/{i}" for i in range(n)]
    assert {t for t in chans if t.startswith("swarm/")} == {f"{root}/clock", f"{root}/truth", *radio_keys, f"{root}/alive", *per_sat}
    steps = defaultdict(list)  # topic -> [(k, message)]
    for topic in chans:
        if not topic.startswith("swarm/") or topic.endswith("/alive"):
            continue
        _run, kind, ident = parse_key(topic)
        for schema, data, latency_ns in chans[topic]:
            m = decode(kind, data)
            assert schema == f"swarm.v1.{type(m).__name__}", (topic, schema)
            # Publish time: the publisher's Zenoh timestamp, strictly before the recorder got it.
            assert m.run == run and latency_ns > 0, (topic, m.k, latency_ns)
            if ident is not None and kind != "batches":  # batches/<i>: to agent i, not about it
                assert ident == getattr(m, {"meas": "observer", "est": "own"}.get(kind, "sat")), (topic, m.k)
            steps[topic].append((m.k, m))
    every_step = list(range(K))
    assert sorted(k for k, _m in steps[f"{root}/truth"]) == every_step
    # The ideal radio: one message a step, carrying every agent's batch of that step as sent
    # (or, radio "graph", one message a step to each agent with its graph neighbours' batches).
    for key, peers in ([(f"{root}/batches", list(range(n)))] if hears is None
                       else [(f"{root}/batches/{i}", hears[i].tolist()) for i in range(n)]):
        radio = dict(steps[key])
        assert sorted(radio) == every_step and all(list(m.observers) == peers for m in radio.values()), key
        for k, m in radio.items():
            sent = sorted((b for i in peers for kb, b in steps[f"{root}/meas/{i}"] if kb == k), key=lambda b: b.observer)
            assert list(m.counts) == [len(b.target) for b in sent] and list(m.target) == [t for b in sent for t in b.target]
    for i in range(n):
        for kind in (f"sat/{i}/sensors", f"sat/{i}/cam", f"meas/{i}", f"health/{i}"):
            assert sorted(k for k, _m in steps[f"{root}/{kind}"]) == every_step, kind
        est = steps[f"{root}/est/{i}"]
        assert sorted(k for k, m in est if m.phase == "posterior") == every_step
        assert [k for k, m in est if m.phase == "prior"] == [0]
    clocks = [(k, m.done, tuple(m.live_agents)) for k, m in steps[f"{root}/clock"]]
    assert sorted(clocks) == [(k, False, tuple(range(n))) for k in every_step] + [(K - 1, True, tuple(range(n)))]
    # Every role came up (liveliness), and the recorder derived the Foxglove 3-D channels.
    from swarmrt.bus.messages import Liveliness

    up = {(r.role, r.id) for r in (Liveliness.FromString(d) for _s, d, _p in chans[f"{root}/alive"]) if r.alive}
    assert {("world", "0"), ("recorder", "0"), *(("agent", str(i)) for i in range(n))} <= up, up
    fox = {t: len(v) for t, v in chans.items() if not t.startswith("swarm/")}
    assert fox.pop("/foxglove/tf") == fox.pop("/foxglove/truth") == K
    for i in range(n):
        assert fox.pop(f"/foxglove/est/{i}") == K
    assert fox.pop("/foxglove/measurements") == K * n  # one scene per measurement batch
    assert fox.pop("/foxglove/cameras") == K  # the face cameras' frusta, every step
    for i in range(n):
        assert fox.pop(f"/errors/{i}") == K  # each filter's errors against the truth (the Plot panel's)
    assert not fox, f"unexpected channels {sorted(fox)}"


@pytest.mark.parametrize("strategy", ["greedy", "random"])
def test_distributed_selection_equals_in_process_selection(tmp_path, strategy):
    """With a selector (planned from satellite 0's filter), every step's schedule and every
    estimate equal the in-process run's: the selector plans step 0 only once every agent is
    up, from agent 0's prior, whichever agent came up first; a state-free strategy (random)
    also plans from the estimate, which keeps only the pairs it says are visible, as
    in-process."""
    sc = scenario(n_sats=6, duration_s=10, selection={"strategy": strategy, "budget": 4})
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0 and summary["selector_fallback_steps"] == []
    res = simulate(sc)
    np.testing.assert_array_equal(rec.schedule, res.schedule)
    ref = res.summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis", "measurements_per_step_mean"):
        assert summary[key] == ref[key], key


@pytest.mark.slow
def test_killed_agent_survivors_keep_estimating_it_within_3_sigma(tmp_path):
    sc = scenario(duration_s=40, faults=[{"at_step": 10, "action": "kill-agent", "target": 2}])
    rec, summary, codes, _sw = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    assert codes["agent-2"] == -signal.SIGKILL
    survivors = [0, 1, 3]
    assert rec.alive[:, survivors].all(), "a survivor missed a step"
    assert not rec.alive[11:, 2].any() and rec.alive[:10, 2].all()
    frac, count = within_3sigma_fraction(rec, survivors, 2, k_from=10)
    assert count == 31 * 3 * 6 and frac >= 0.97, f"only {frac:.1%} of errors on the dead satellite within 3σ"
    each = within_3sigma_per_observer(rec, survivors, 2, k_from=10)
    assert min(each.values()) >= 0.95, each  # every survivor on its own, not an aggregate
    # The dead satellite is still seen: survivors keep measuring it.
    assert rec.taken[11:, survivors, 2].all()
    assert not rec.taken[11:, 2, :].any()
    kills = [f for f in summary["faults"] if f["action"] == "kill-agent" and f["phase"] == "done"]
    assert kills and kills[0]["target"] == 2 and kills[0]["sender"] == "supervisor"


def _busiest_camera(sc, sat, step):
    wp = world_params(sc)
    tr = initial_truth(sc)
    for _ in range(step):
        tr, _g = step_truth(wp, tr)
    others = np.array([j for j in range(sc.n_sats) if j != sat])
    _q, r = relative_pose(wp.mean_motion, tr.t, tr.q_BI, tr.r_H, np.full(others.size, sat), others)
    cams = best_camera(r)
    return int(np.bincount(cams, minlength=6).argmax())


def test_camera_off_produces_nothing_after_the_fault(tmp_path):
    sat, k_fault = 1, 8
    sc0 = scenario(duration_s=25)
    cam = _busiest_camera(sc0, sat, k_fault)
    sc = scenario(duration_s=25, faults=[{"at_step": k_fault, "action": "camera", "target": sat, "camera": cam, "state": "off"}])
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.messages import decode

    used = {"before": 0, "after": 0}
    for topic, _s, data, _lt, _pt in iter_messages(tmp_path / "run" / "run.mcap"):
        if topic.endswith(f"/meas/{sat}"):
            m = decode("meas", data)
            n_cam = sum(1 for c in m.camera if c == cam)
            used["before" if m.k < k_fault else "after"] += n_cam
    assert used["before"] > 0, "the camera saw nothing before the fault: the test would prove nothing"
    assert used["after"] == 0
    assert any(f["action"] == "camera" and f["phase"] == "done" for f in summary["faults"])
    assert rec.alive.all()


@pytest.mark.slow
def test_selector_killed_fallback_within_two_steps(tmp_path):
    k_kill = 8
    sc = scenario(
        duration_s=25,
        selection={"strategy": "random", "budget": 4},
        faults=[{"at_step": k_kill, "action": "kill-selector"}],
    )
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0 and codes["selector"] == -signal.SIGKILL
    fb = summary["selector_fallback_steps"]
    assert fb and min(fb) <= k_kill + 2, f"fallback started at {min(fb) if fb else None}"
    assert all(k >= k_kill for k in fb), "fallback before the selector died"
    assert set(range(k_kill + 2, sc.steps)) <= set(fb)
    # Every step had measurements scheduled, before and after.
    assert rec.schedule.sum(axis=(1, 2)).min() > 0
    assert rec.alive.all()


@pytest.mark.slow
def test_restarted_agent_reconverges(tmp_path):
    sc = scenario(
        duration_s=60,
        faults=[{"at_step": 10, "action": "kill-agent", "target": 2}, {"at_step": 20, "action": "restart-agent", "target": 2}],
    )
    rec, _summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    back = np.flatnonzero(rec.alive[:, 2])
    assert back[back > 10].min() <= 21, "the restarted agent did not rejoin at once"
    assert rec.alive[21:, 2].all()
    # Reconverged: over the last 15 steps its errors on every satellite sit inside its
    # 3σ bounds and are of the survivors' size.
    frac = [within_3sigma_fraction(rec, [2], j, k_from=sc.steps - 15)[0] for j in range(4)]
    assert min(frac) >= 0.95, frac
    att, pos = rec.att_err_rad, rec.pos_err_m
    late = slice(sc.steps - 15, None)
    assert np.nanmean(pos[late, 2]) < 3 * np.nanmean(pos[late][:, [0, 1, 3]])
    assert np.nanmean(att[late, 2, 2]) < 1e-3  # its own attitude: star tracker level again


def _garbage(keys: Keys, n: int):
    """Malformed and hostile payloads: not protobuf, truncated, an unknown schema version,
    another run, a message of the wrong type, NaN, a non-unit quaternion, an indefinite
    covariance, a huge announced array, an oversized payload, wrong senders."""
    hdr = dict(run=keys.run, sender="evil", k=1, t_s=1.0)
    rel = RelativeMeasurements(np.array([0]), np.array([1]), np.array([[0, 0, 0, 1.0]]), np.array([[1.0, 2, 3]]), np.eye(6)[None] * 1e-4)
    good_meas = batch_msg(rel, np.array([0]), run=keys.run, sender="agent-0", k=1, t_s=1.0, observer=0)

    def meas(**ch):
        return M.encode(M.replace(good_meas, **ch))

    nan_R = M.replace(good_meas)
    nan_R.R_Bi.data[0] = float("nan")
    bad_R = M.replace(good_meas)
    bad_R.R_Bi.data[0] = -1.0
    payloads = [
        b"\x00\x01\x02 not protobuf",
        b"",
        b"{}",
        M.encode(good_meas)[:-7],  # truncated
        M.encode(M.Clock(schema_version=99, **hdr, mode="lockstep")),
        M.encode(M.Clock(**{**hdr, "run": "another-run"}, mode="lockstep")),
        M.encode(M.Health(**hdr, sat=0, camera_ok=[True] * 6)),  # a message of another type, on every key
        M.encode(nan_R),
        meas(q_BjBi=[0.0, 0.0, 0.0, 2.0]),
        M.encode(bad_R),
        meas(R_Bi=M.Matrix(shape=[1 << 31, 6, 6], data=[1.0])),  # a huge array announced
        meas(sender="agent-2"),  # observer 0's batch from someone else
        os.urandom(3000),
    ]
    targets = [keys.clock(), keys.select(), keys.fault(), keys.truth()]
    for i in range(n):
        targets += [keys.sensors(i), keys.cam(i), keys.meas(i), keys.est(i), keys.health(i)]
    targets += [keys.meas(99), keys.est(77), keys.sensors(12345)]  # unknown satellites
    huge = meas(r_ij_Bi_m=np.zeros(1_100_000).tolist())  # ~9 MB: over the size limit
    return targets, payloads, hdr, huge


def test_malformed_flood_on_every_key_kills_nobody(tmp_path):
    # Security and the router's ingress gate off: the access rules would stop this garbage
    # before any receiver (tests/test_security.py) and the gate would hold the flood back
    # (tests/test_router_gate.py); what is tested here is the receivers' own checks.
    sc = scenario(n_sats=3, duration_s=20, emulator={"security": False, "gate": False})
    sent = {"n": 0}
    stop = threading.Event()

    def flood(sw):
        keys = Keys(sw.run)
        targets, payloads, hdr, huge = _garbage(keys, sc.n_sats)
        sent["keys"] = len(set(targets) | {keys.meas(0), keys.est(1), keys.clock()})
        # Well-formed messages that name satellites this swarm does not have.
        payloads.append(M.encode(M.MeasBatch(**{**hdr, "sender": "agent-7"}, observer=7, R_Bi=M.Matrix(shape=[0, 6, 6]))))
        payloads.append(M.encode(M.Clock(**{**hdr, "sender": "world"}, live_agents=[0, 1, 2, 50], mode="lockstep")))
        with zenoh.open(sw.bus_as("observer").zenoh_config()) as s:
            rounds = 0
            while not stop.is_set() and sw.procs["world"].poll() is None:
                for key in targets:
                    for p in payloads:
                        s.put(key, p)
                        sent["n"] += 1
                if rounds % 10 == 0:
                    for key in (keys.meas(0), keys.est(1), keys.clock()):
                        s.put(key, huge)
                        sent["huge"] = sent.get("huge", 0) + 1
                rounds += 1
                stop.wait(0.05)

    try:
        rec, summary, codes, _sw = run_swarm(sc, tmp_path / "run", during=flood)
    finally:
        stop.set()
    assert sent["n"] > 1000
    for name, code in codes.items():
        assert code in (0, None), f"{name} exited with {code}"
    assert codes["world"] == 0 and rec.alive.all()
    assert summary["messages"].get("_malformed", 0) > 100 and sent.get("huge", 0) > 0
    # The recorder's flood cap: at most 200 malformed messages written per key, the rest counted.
    from swarm.record.recorder import FLOOD_CAP_MALFORMED_PER_KEY

    cut = summary["messages"].get("not_recorded_over_the_flood_cap", {})
    written = summary["messages"]["_malformed"]
    assert cut and written <= FLOOD_CAP_MALFORMED_PER_KEY * sent["keys"], (written, cut, sent)
    assert written + sum(cut.values()) >= sent["n"] * 0.5, (written, cut, sent)  # what the router passed, written or counted
    # Every agent counted what it dropped (its health reports say so).
    from swarm.record.mcaplog import iter_messages

    malformed = {}
    for topic, _s, data, _lt, _pt in iter_messages(tmp_path / "run" / "run.mcap"):
        if "/health/" in topic:
            h = M.decode("health", data)
            malformed[h.sat] = max(malformed.get(h.sat, 0), h.malformed)
    assert sorted(malformed) == [0, 1, 2] and min(malformed.values()) > 100, malformed
    ref = simulate(sc).summary()
    assert summary["rms"] == ref["rms"], "garbage changed the numbers"


def test_recorder_sigkill_leaves_a_readable_file(tmp_path):
    sc = scenario(n_sats=3, duration_s=30)
    killed = {}

    def kill_recorder(sw):
        with zenoh.open(sw.bus_as("observer").zenoh_config()) as s:
            seen = threading.Event()
            sub = s.declare_subscriber(Keys(sw.run).clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= 12 and seen.set())
            assert seen.wait(120)
            sw.procs["recorder"].send_signal(signal.SIGKILL)
            killed["at"] = True
            sub.undeclare()

    out = tmp_path / "run"
    rec, _summary, codes, _sw = run_swarm(sc, out, during=kill_recorder)
    assert killed and codes["recorder"] == -signal.SIGKILL and codes["world"] == 0
    from mcap.reader import make_reader

    with open(out / "run.mcap", "rb") as f:
        msgs = list(make_reader(f).iter_messages())
    assert len(msgs) > 50
    # Everything up to the last flush (at least once per simulated second of what the
    # recorder has taken in) is there: a prefix of whole steps. The recorder may lag the
    # world by a few steps on a loaded machine, so the kill at step 12 leaves at least
    # the first few seconds, each complete.
    kf = int(np.argmin(np.isfinite(rec.t_s))) if not np.isfinite(rec.t_s).all() else len(rec.t_s)
    assert kf >= 5, f"only {kf} steps recorded before the kill at step 12"
    assert np.isfinite(rec.t_s[:kf]).all() and rec.alive[: kf - 1].all()


@pytest.mark.slow
def test_cli_faults_against_a_running_swarm_and_dropped_messages(tmp_path):
    # Paced (lockstep, at most 8× real time) so the CLI has time to act mid-run.
    sc = scenario(n_sats=4, duration_s=100, emulator={"lockstep_max_realtime_factor": 8.0})
    sat = 1
    cam = _busiest_camera(sc, sat, 12)
    results = {}

    def inject(sw):
        with zenoh.open(sw.bus_as("observer").zenoh_config()) as s:
            seen = threading.Event()
            sub = s.declare_subscriber(Keys(sw.run).clock(), lambda smp: Clock.FromString(smp.payload.to_bytes()).k >= 10 and seen.set())
            assert seen.wait(120)
            sub.undeclare()
        for args in (["camera", str(sat), str(cam), "off"], ["drop", "3", "--rate", "0.5"]):
            p = subprocess.run([sys.executable, "-m", "swarm.cli", "fault", "--run-dir", str(sw.out), *args], capture_output=True, text=True, timeout=120)
            results[args[0]] = (p.returncode, p.stdout + p.stderr)

    rec, summary, codes, _sw = run_swarm(sc, tmp_path / "run", during=inject)
    assert codes["world"] == 0
    assert results["camera"][0] == 0 and "done" in results["camera"][1], results
    assert results["drop"][0] == 0 and "done" in results["drop"][1], results
    done = {f["action"]: f["k"] for f in summary["faults"] if f["phase"] == "done"}
    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.messages import decode

    after = 0
    for topic, _s, data, _lt, _pt in iter_messages(tmp_path / "run" / "run.mcap"):
        if topic.endswith(f"/meas/{sat}"):
            m = decode("meas", data)
            if m.k > done["camera"]:
                after += sum(1 for c in m.camera if c == cam)
    assert after == 0
    # Agent 3 lost about half its batches after the drop fault; everyone coped and finished.
    k_drop = done["drop"]
    lost = (~rec.taken[k_drop + 1 :, 3, :].any(axis=1)).mean()
    assert 0.2 < lost < 0.8, lost
    assert rec.alive[:, [0, 1, 2]].all()


def test_free_running_mode_keeps_pace_and_estimates(tmp_path):
    sc = scenario(n_sats=3, duration_s=40, emulator={"time_mode": "free", "realtime_factor": 10.0})
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    clocks = np.isfinite(rec.t_s)
    assert clocks.all()
    # The pace: the world's steps went out at realtime_factor × wall time. The publish times
    # of its truth (one a step, with the clock), step to step, are dt / realtime_factor
    # apart (a paced clock, not lockstep's as-fast-as-the-agents), within a scheduling
    # tolerance, and the whole run took its simulated duration / realtime_factor of wall time.
    assert rec.bus is not None and rec.bus.times is not None
    bt = rec.bus.times
    pub = np.sort(bt.published_ns[(bt.kind == "truth") & (bt.sender == "world")]) / 1e9
    assert pub.size >= sc.steps - 1, pub.size
    gaps = np.diff(pub)
    expected = sc.dt_s / sc.emulator.realtime_factor
    assert abs(np.median(gaps) - expected) < 0.02, (np.median(gaps), expected)
    assert abs((pub[-1] - pub[0]) - sc.duration_s / sc.emulator.realtime_factor) < 1.0, pub[-1] - pub[0]
    # Paced by wall time, agents keep up on loopback: nearly every step is estimated.
    assert rec.alive.mean() > 0.8, rec.alive.mean()
    assert summary["rms_second_half"]["others"]["pos_m"] < 0.1


def test_free_running_graph_radio_sends_each_batch_to_the_observers_neighbours(tmp_path):
    """Free-running, radio "graph" (ci on a duplex chain): each batch goes on as it comes,
    on batches/<j> of its observer's neighbours j only; the agents keep estimating."""
    from swarm.record.mcaplog import iter_messages
    from swarmrt.bus.messages import decode, parse_key

    sc = scenario(n_sats=5, duration_s=20, estimator={"kind": "ci"}, graph={"kind": "duplex_chain"},
                  emulator={"time_mode": "free", "realtime_factor": 5.0})
    hears = radio_peers(scenario_graph(sc), "graph")
    assert hears is not None
    rec, _summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0
    assert rec.alive.mean() > 0.8, rec.alive.mean()
    carried: dict[int, set[int]] = {i: set() for i in range(sc.n_sats)}
    for topic, _schema, data, _log, _pub in iter_messages(tmp_path / "run" / "run.mcap"):
        if "/batches" not in topic or not topic.startswith("swarm/"):
            continue
        _run, kind, to = parse_key(topic)
        assert kind == "batches" and to is not None, f"a whole-swarm radio message on {topic}"
        m = decode("batches", data)
        assert set(m.observers) <= set(hears[to].tolist()), (to, list(m.observers))
        carried[to] |= set(m.observers)
    assert carried == {i: set(hears[i].tolist()) for i in range(sc.n_sats)}  # every neighbour heard, no one else


def test_bench_bus_prints_and_writes_json(tmp_path):
    out = tmp_path / "bus.json"
    p = subprocess.run([sys.executable, "-m", "swarm.cli", "bench", "bus", "--samples", "30", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    rows = json.loads(out.read_text())["rows"]
    # Security on (authenticated clients, the router's access rules), then off, side by side.
    assert [r["security"] for r in rows] == ["on"] * 3 + ["off"] * 3
    assert [r["bytes"] > 1_000_000 for r in rows] == [False, False, True] * 2
    assert [r.get("n") for r in rows] == [10, 40, None] * 2
    for r in rows:
        assert 0 < r["one_way"]["p50_ms"] <= r["one_way"]["p99_ms"]
    for r in rows[:2]:
        assert r["codec"]["encode_us"] > 0 and r["codec"]["decode_us"] > 0 and r["codec"]["bytes"] == r["bytes"]


def test_bench_run_measures_a_real_swarm(tmp_path):
    """`swarm bench run`'s measurement: a real lockstep swarm, its real-time factor and the
    agents' filter times read back from the recording."""
    from swarm.bench.bus import bench_realtime

    (row,) = bench_realtime([3], duration_s=4.0, workdir=tmp_path, log=lambda s: None)
    assert row["world_exit_code"] == 0 and row["n"] == 3
    assert row["realtime_factor"] > 0 and row["stepping_wall_s"] > 0
    assert row["agent_filter_ms_median"] is not None and row["agent_filter_ms_median"] > 0
