"""The link model (swarmcore/links.py): latency, data rate and queue, loss, range, line of
sight, overrides; its determinism; and the scenario's validation of it."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from swarm.simulation import simulate_scenario
from swarmcore.links import SPEED_OF_LIGHT_M_S, LinkModel, ge_probabilities
from swarmcore.scenario import Links, Scenario
from swarmrt.bus.convert import batch_wire_size


def model(n=3, seed=0, radius=0.35, **links) -> LinkModel:
    return LinkModel(Links.model_validate({"enabled": True, **links}), n, seed, radius)


def line(n, spacing=10.0):
    return np.array([[spacing * i, 0.0, 0.0] for i in range(n)])


def test_latency_is_fixed_plus_range_over_c_plus_per_metre():
    lm = model(latency={"fixed_s": 0.25, "per_m_s": 1e-3})
    lm.at_step(0, line(3))
    lm.send(0, [1, 2], "m", 100, 0.0)
    got = {d.receiver: d.arrival_t for d in lm.due(10.0)}
    for j, r in ((1, 10.0), (2, 20.0)):
        assert got[j] == pytest.approx(0.25 + 1e-3 * r + r / SPEED_OF_LIGHT_M_S, abs=1e-15)


def test_nothing_arrives_before_its_time_and_late_deliveries_are_counted():
    lm = model(n=2, latency={"fixed_s": 1.5, "speed_of_light": False})
    lm.at_step(0, line(2))
    lm.send(0, [1], "a", 10, 0.0)
    assert lm.due(1.0) == []
    lm.at_step(1, line(2))
    assert lm.due(1.0) == []
    lm.at_step(2, line(2))
    (d,) = lm.due(2.0)
    assert d.arrival_t == 1.5 and d.sent_step == 0
    assert lm.counters.delivered_late[0, 1] == 1 and lm.latencies == [(0, 1, 0, 1.5)]


@pytest.mark.parametrize("dist", ["uniform", "normal", "exponential"])
def test_jitter_distributions_have_their_scale(dist):
    lm = model(n=2, latency={"speed_of_light": False, "jitter": {"distribution": dist, "scale_s": 0.2}})
    lat = []
    for k in range(4000):
        lm.at_step(k, line(2))
        lm.send(0, [1], k, 10, float(k))
        lat += [d.arrival_t - d.sent_t for d in lm.due(k + 100.0)]
    lat = np.array(lat)
    assert lat.min() >= 0
    mean = {"uniform": 0.1, "normal": 0.2 * np.sqrt(2 / np.pi), "exponential": 0.2}[dist]
    assert lat.mean() == pytest.approx(mean, rel=0.05)


def test_bernoulli_loss_rate():
    lm = model(n=2, loss={"model": "bernoulli", "rate": 0.3})
    for k in range(5000):
        lm.at_step(k, line(2))
        lm.send(0, [1], k, 10, float(k))
        lm.due(float(k))
    lm.due(1e9)
    c = lm.counters
    assert c.lost[0, 1] + c.delivered[0, 1] == 5000
    assert c.lost[0, 1] / 5000 == pytest.approx(0.3, abs=0.02)


def test_gilbert_elliott_loss_rate_and_mean_burst():
    L, B = 0.3, 4.0
    p, r = ge_probabilities(L, B)
    assert r == 1 / B and p / (p + r) == pytest.approx(L)
    lm = model(n=2, loss={"model": "gilbert_elliott", "rate": L, "mean_burst": B})
    lost = []
    for k in range(20000):
        lm.at_step(k, line(2))
        lm.send(0, [1], k, 10, float(k))
        before = lm.counters.lost[0, 1]
        lm.due(float(k))
        lost.append(lm.counters.lost[0, 1] > before)
    lost = np.array(lost)
    assert lost.mean() == pytest.approx(L, abs=0.02)
    starts = np.flatnonzero(lost[1:] & ~lost[:-1]) + 1
    ends = np.flatnonzero(~lost[1:] & lost[:-1]) + 1
    runs = [e - s for s, e in zip(starts, ends[ends > starts[0]][: len(starts)], strict=False)]
    assert np.mean(runs) == pytest.approx(B, rel=0.1)


def test_rate_cap_is_honoured_while_the_queue_is_not_empty():
    """Bytes delivered per second within 5 % of the cap while the transmitter has a backlog."""
    rate = 2000.0
    lm = model(n=4, rate_Bps=rate, queue_bytes=10**7, latency={"speed_of_light": False})
    for k in range(30):  # 3 copies × 1500 B each second: 4500 B/s offered, 2000 B/s carried
        lm.at_step(k, line(4))
        lm.send(0, [1, 2, 3], k, 1500, float(k))
    t_end = 30.0
    arrived = lm.due(t_end)
    assert (lm.queue_bytes(t_end) > 0)[0], "the backlog is still there at the end"
    delivered = sum(d.size for d in arrived)
    assert delivered / t_end == pytest.approx(rate, rel=0.05)
    # Every second carries the cap's worth (the copy in transmission excepted).
    per_s = np.histogram([d.arrival_t for d in arrived], bins=np.arange(0, 31), weights=[d.size for d in arrived])[0]
    assert np.all(np.abs(per_s[1:] - rate) <= 1500)


@pytest.mark.parametrize("policy", ["drop_tail", "drop_head"])
def test_queue_overflow_is_dropped_by_the_stated_policy_and_counted(policy):
    lm = model(n=2, rate_Bps=100.0, queue_bytes=250, queue_policy=policy, latency={"speed_of_light": False})
    lm.at_step(0, line(2))
    for tag in "abcd":  # 100 B each at t=0: the transmitter holds 2.5 of them
        lm.send(0, [1], tag, 100, 0.0)
    got = [d.payload for d in lm.due(100.0)]
    assert lm.counters.dropped_queue[0, 1] == 2 and lm.counters.sent[0, 1] == 2
    assert got == (["a", "b"] if policy == "drop_tail" else ["a", "d"])


def test_range_and_dead_links_are_unreachable_and_overrides_apply_per_direction():
    lm = model(n=3, max_range_m=15.0, overrides=[{"from": 1, "to": 0, "dead": True},
                                                  {"from": 0, "to": 2, "max_range_m": 50.0,
                                                   "latency": {"fixed_s": 3.0}}])
    lm.at_step(0, line(3))
    assert lm.send(0, [1, 2], "x", 10, 0.0) == {1: "queued", 2: "queued"}
    assert lm.send(1, [0, 2], "y", 10, 0.0) == {0: "unreachable", 2: "queued"}
    assert lm.send(2, [0, 1], "z", 10, 0.0) == {0: "unreachable", 1: "queued"}
    arr = {(d.sender, d.receiver): d.arrival_t for d in lm.due(10.0)}
    assert arr[(0, 2)] >= 3.0 and arr[(0, 1)] < 1e-6


def test_link_faults_impair_and_restore_the_scenarios_links_at_run_time():
    """A link fault (the world's ``link`` action) acts like a scenario override from the
    step it is applied: dead (at once), latency added to the scenario's (not to an earlier
    fault's), Bernoulli loss; ``restore`` gives back exactly the scenario's parameters."""
    lm = model(n=3, latency={"fixed_s": 0.5, "speed_of_light": False}, overrides=[{"from": 2, "to": 0, "dead": True}])
    lm.at_step(0, line(3))
    assert lm.impair(0, 1, dead=True) == 1
    assert lm.send(0, [1, 2], "a", 10, 0.0) == {1: "unreachable", 2: "queued"}
    assert lm.impair(1, delay_s=2.0) == 4  # every link of 1, both ways
    lm.impair(1, delay_s=1.0)  # added to the scenario's 0.5 s, not to the 2.5 s of the first
    assert lm.p.fixed_s[1, 2] == lm.p.fixed_s[2, 1] == lm.p.fixed_s[0, 1] == 1.5 and lm.p.fixed_s[0, 2] == 0.5
    lm.impair(2, 1, loss_rate=1.0)
    assert lm.send(2, [1], "b", 10, 0.0) == {1: "queued"}
    lm.at_step(1, line(3))
    assert lm.send(0, [1], "c", 10, 1.0) == {1: "unreachable"}  # still dead
    assert lm.restore(1) == 4 and lm.restore(0, 1) == 1
    lm.at_step(2, line(3))
    assert lm.send(0, [1], "d", 10, 2.0) == {1: "queued"}
    for name in ("dead", "fixed_s", "loss_kind", "loss_rate"):
        np.testing.assert_array_equal(getattr(lm.p, name), getattr(model(n=3, latency={"fixed_s": 0.5, "speed_of_light": False},
                                                                         overrides=[{"from": 2, "to": 0, "dead": True}]).p, name))
    assert lm.send(2, [0], "e", 10, 2.0) == {0: "unreachable"}  # the scenario's own dead link stays dead
    lm.due(10.0)  # a copy lost on the channel counts when it would have arrived
    assert lm.counters.lost[2, 1] == 1 and lm.counters.unreachable[0, 1] == 2
    with pytest.raises(ValueError, match="not a link"):
        lm.impair(1, 1, dead=True)


def test_another_satellite_blocks_the_line_of_sight():
    lm = model(n=3, line_of_sight=True, radius=0.35)
    r = np.array([[0.0, 0, 0], [5.0, 0.1, 0], [10.0, 0, 0]])  # 1 sits between 0 and 2
    lm.at_step(0, r)
    assert not lm.reachable(0, 2) and not lm.reachable(2, 0)
    assert lm.reachable(0, 1) and lm.reachable(1, 2)
    lm.at_step(1, r + np.array([[0, 0, 0], [0, 2.0, 0], [0, 0, 0]]))  # 1 moves aside
    assert lm.reachable(0, 2)


def test_fates_depend_on_the_link_and_step_not_on_the_order_of_sending():
    kw = dict(n=4, seed=7, loss={"model": "gilbert_elliott", "rate": 0.4, "mean_burst": 2},
              latency={"jitter": {"distribution": "exponential", "scale_s": 0.5}})
    a, b = model(**kw), model(**kw)
    for k in range(20):
        a.at_step(k, line(4))
        b.at_step(k, line(4))
        for i in range(4):
            a.send(i, range(4), (i, k), 10, float(k))
        for i in reversed(range(4)):
            b.send(i, range(4), (i, k), 10, float(k))
    key = lambda d: (d.sender, d.receiver, d.sent_step, d.arrival_t)  # noqa: E731
    assert sorted(map(key, a.due(1e9))) == sorted(map(key, b.due(1e9)))
    np.testing.assert_array_equal(a.counters.lost, b.counters.lost)


@pytest.mark.parametrize(
    "bad, field",
    [
        ({"loss": {"model": "bernoulli", "rate": 1.5}}, "links.loss.rate"),
        ({"loss": {"model": "gilbert_elliott", "rate": 0.2, "mean_burst": 0.5}}, "links.loss.mean_burst"),
        ({"latency": {"fixed_s": -1}}, "links.latency.fixed_s"),
        ({"latency": {"jitter": {"distribution": "cauchy"}}}, "links.latency.jitter.distribution"),
        ({"rate_Bps": 0}, "links.rate_Bps"),
        ({"queue_policy": "random"}, "links.queue_policy"),
        ({"overrides": [{"from": 0, "to": 9}]}, "links.overrides.0.to"),
        ({"overrides": [{"from": 1, "to": 1}]}, "links.overrides.0"),
        ({"overrides": [{"from": 0, "to": 1}, {"from": 0, "to": 1, "dead": True}]}, "links.overrides"),
        ({"bandwidth": 5}, "links.bandwidth"),
    ],
)
def test_bad_link_parameters_fail_naming_the_field(bad, field):
    with pytest.raises(ValidationError) as e:
        Scenario.model_validate({"n_sats": 3, "links": {"enabled": True, **bad}})
    text = str(e.value)
    last = field.split(".")[-1]
    assert last in text, text


def test_ideal_links_through_the_radio_equal_no_links_bit_for_bit():
    """Links on, but zero latency (no propagation delay either), no loss, no cap: every
    batch arrives in its own step, so every filter equals the one of the ideal network."""
    base = {"name": "ideal", "seed": 5, "n_sats": 4, "duration_s": 20}
    off = simulate_scenario(Scenario.model_validate(base)).summary()
    on = simulate_scenario(Scenario.model_validate({**base, "links": {"enabled": True, "latency": {"speed_of_light": False}}})).summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis"):
        assert on[key] == off[key], key
    assert on["links"]["totals"]["delivered"] == on["links"]["totals"]["sent"] == 21 * 4 * 3
    assert on["links"]["totals"]["delivered_late"] == 0 and on["late"]["used"] == 0


def test_radio_size_is_the_encoded_batch_less_the_run_id():
    from swarmcore.mekf import RelativeMeasurements
    from swarmrt.bus.convert import batch_msg
    from swarmrt.bus.messages import encode

    rel = RelativeMeasurements(np.array([1]), np.array([2]), np.array([[0, 0, 0, 1.0]]), np.array([[1.0, 2, 3]]),
                               np.eye(6)[None])
    on_bus = len(encode(batch_msg(rel, np.array([3]), run="r1", sender="agent-1", k=4, t_s=4.0, observer=1)))
    size = batch_wire_size("r1")(1, 4, 4.0, rel, np.array([3]))
    assert size == on_bus - len(b"r1") - 2  # field tag and length of the run id
    assert batch_wire_size("a-much-longer-run-id-0042")(1, 4, 4.0, rel, np.array([3])) == size
