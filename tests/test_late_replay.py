"""Late (out-of-sequence) measurements: replay inserts them at their own step and gives
the posterior of having had them on time; older than the history, or ``late: drop``,
they are dropped and counted."""

from __future__ import annotations

import numpy as np
import pytest

from swarmcore.agent import AgentFilter, filter_params
from swarmcore.graphs import scenario_graph
from swarmcore.mekf import RelativeMeasurements
from swarmcore.scenario import Scenario
from swarmcore.synthetic import synthetic_batch
from swarmcore.world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params


def _inputs(sc: Scenario, steps: int):
    """Per step: gyro of filter 0, its absolute reading, and every observer's batch."""
    wp = world_params(sc)
    G = scenario_graph(sc)
    truth = initial_truth(sc)
    obs, tgt = np.nonzero(G & ~np.eye(sc.n_sats, dtype=bool))
    out, gyro = [], None
    for k in range(steps):
        if k > 0:
            truth, gyro = step_truth(wp, truth)
        rel = synthetic_batch(wp, truth, obs, tgt)
        per_obs = {i: rel.subset(rel.observer == i) for i in range(sc.n_sats)}
        out.append((None if gyro is None else gyro[0], absolute_measurements(wp, truth)[0], per_obs))
    return initial_truth(sc), out


def _filter(sc, truth0, late="replay", history=50):
    return AgentFilter(filter_params(sc, 0), initial_estimate(sc, truth0, 0), sc.filter.mode, late=late, history_steps=history)


def _same(a, b):
    for name in ("q_BI", "omega_BI_B", "r_H", "v_H", "bias_B", "P"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("seed", [0, 1])
def test_every_batch_late_in_shuffled_order_gives_the_on_time_posterior(seed):
    sc = Scenario.model_validate({"name": "late", "seed": seed, "n_sats": 4, "duration_s": 20})
    truth0, steps = _inputs(sc, 12)
    on_time = _filter(sc, truth0)
    for k, (g, a, per_obs) in enumerate(steps):
        on_time.step(k, g, a, RelativeMeasurements.concat(list(per_obs.values())))

    late = _filter(sc, truth0)
    rng = np.random.default_rng(seed)
    # Peer batches arrive 1–4 steps after they were taken, in a random order within a step.
    pending: dict[int, list[tuple[int, RelativeMeasurements]]] = {}
    for k, (_g, _a, per_obs) in enumerate(steps):
        for j in (1, 2, 3):
            pending.setdefault(k + int(rng.integers(1, 5)), []).append((k, per_obs[j]))
    used = 0
    for k, (g, a, per_obs) in enumerate(steps):
        arrivals = pending.pop(k, [])
        rng.shuffle(arrivals)
        by_step: dict[int, list] = {}
        for s, m in arrivals:
            by_step.setdefault(s, []).append(m)
        _rep, lrep = late.step(k, g, a, per_obs[0], late={s: RelativeMeasurements.concat(v) for s, v in by_step.items()})
        assert lrep.dropped == 0
        used += lrep.used
    # What is still in flight arrives at the next step: insert it, then compare at the
    # last step (the on-time filter's posterior).
    rest: dict[int, list] = {}
    for arrivals in pending.values():
        for s, m in arrivals:
            rest.setdefault(s, []).append(m)
    lrep = late._insert_late({s: RelativeMeasurements.concat(v) for s, v in rest.items()})
    used += lrep.used
    assert used == sum(len(per_obs[j]) for _g, _a, per_obs in steps for j in (1, 2, 3))
    _same(late.est, on_time.est)


def test_measurements_older_than_the_history_are_dropped_and_counted():
    sc = Scenario.model_validate({"name": "late", "seed": 2, "n_sats": 3, "duration_s": 20})
    truth0, steps = _inputs(sc, 8)
    f = _filter(sc, truth0, history=3)
    for k, (g, a, per_obs) in enumerate(steps[:7]):
        f.step(k, g, a, per_obs[0])
    # At step 7 the history holds steps 3..6 (+ 7 once updated): step 2 is too old.
    g, a, per_obs = steps[7]
    _rep, lrep = f.step(7, g, a, per_obs[0], late={2: steps[2][2][1], 4: steps[4][2][1]})
    assert lrep.dropped == len(steps[2][2][1]) and lrep.used == len(steps[4][2][1])
    assert lrep.oldest_step == 4 and lrep.replayed_steps == 3  # steps 4, 5, 6 again, then 7


def test_drop_mode_discards_every_late_measurement():
    sc = Scenario.model_validate({"name": "late", "seed": 3, "n_sats": 3, "duration_s": 20})
    truth0, steps = _inputs(sc, 4)
    f = _filter(sc, truth0, late="drop")
    ref = _filter(sc, truth0, late="drop")
    for k, (g, a, per_obs) in enumerate(steps):
        late = {k - 1: steps[k - 1][2][1]} if k else None
        _rep, lrep = f.step(k, g, a, per_obs[0], late=late)
        ref.step(k, g, a, per_obs[0])
        assert lrep.used == 0 and lrep.dropped == (len(steps[k - 1][2][1]) if k else 0)
    _same(f.est, ref.est)


def test_a_measurement_of_a_step_not_yet_updated_is_refused():
    sc = Scenario.model_validate({"name": "late", "seed": 3, "n_sats": 3, "duration_s": 20})
    truth0, steps = _inputs(sc, 2)
    f = _filter(sc, truth0)
    g, a, per_obs = steps[0]
    with pytest.raises(ValueError, match="not late"):
        f.step(0, g, a, per_obs[0], late={0: per_obs[1]})


def test_replay_when_the_current_step_was_predicted_first():
    """Image pipelines predict before measuring; a late batch then replays up to the last
    updated step and predicts again (same gyro) to the current one."""
    sc = Scenario.model_validate({"name": "late", "seed": 4, "n_sats": 3, "duration_s": 20})
    truth0, steps = _inputs(sc, 6)
    a_f, b_f = _filter(sc, truth0), _filter(sc, truth0)
    for k, (g, a, per_obs) in enumerate(steps):
        a_f.step(k, g, a, RelativeMeasurements.concat([per_obs[0], per_obs[1]]))
        if k > 0:
            b_f.predict_to(k, g)
        late = {k - 1: steps[k - 1][2][1]} if k else None
        b_f.step(k, g, a, per_obs[0], late=late)
    b_f._insert_late({5: steps[5][2][1]})
    _same(b_f.est, a_f.est)


def test_bench_late_replays_lag_steps_each_step():
    from swarm.bench.filter import bench_late

    rows = bench_late(n=3, history_s=5.0, lags=(0, 2), steps=12, log=lambda s: None)
    assert [r["lag_steps"] for r in rows] == [0, 2]
    assert [r["replayed_steps_per_step"] for r in rows] == [0.0, 2.0]
    assert all(r["ms_per_step_median"] > 0 for r in rows)
