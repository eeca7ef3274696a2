"""What the Cramér–Rao bound of a recorded run counts (swarm.record.recording.BoundInputs):
the relative measurements and absolute readings as the recording holds them, handed over
in the order the in-process simulator hands its own; and the bound load_recording then
computes along the recorded truth."""

from __future__ import annotations

import numpy as np
import pytest

from swarm.record.recording import BoundInputs, load_recording
from swarmcore.crlb import posterior_crlb
from swarmcore.mekf import AbsoluteMeasurement, RelativeMeasurements
from swarmcore.scenario import Scenario
from swarmcore.world import initial_truth, step_truth, world_params
from swarmrt.bus.codec import decode, encode
from swarmrt.bus.convert import batch_msg, relative_from_batches, sensors_msg, step_batches_msg, truth_msg
from swarmrt.bus.messages import Delivered, Delivery, Keys

RUN = "u"
KEYS = Keys(RUN)
N, K = 3, 4
ANCHORS = (0, 1)  # the satellites whose sensors carry a GPS reading


def _sc(**kw) -> Scenario:
    return Scenario(name="u", seed=5, n_sats=N, duration_s=K - 1, **kw)


def _r(k: int, i: int, j: int) -> float:
    """The R scale of observer i's measurement of j at step k: tells every row apart."""
    return 1e-4 * (1 + k + 10 * i + 100 * j)


def _meas(k: int, i: int):
    targets = [(i + 1) % N] + ([2] if i == 0 else [])  # observer 0 measures two
    m = len(targets)
    rel = RelativeMeasurements(observer=np.full(m, i), target=np.array(targets), q_BjBi=np.tile([0.0, 0.0, 0.0, 1.0], (m, 1)),
                               r_ij_Bi=np.tile([10.0, -3.0, 2.0], (m, 1)), R_Bi=np.stack([np.eye(6) * _r(k, i, j) for j in targets]))
    return batch_msg(rel, np.zeros(m, dtype=int), run=RUN, sender=f"agent-{i}", k=k, t_s=float(k), observer=i)


def _sensors(k: int, i: int):
    absm = AbsoluteMeasurement(q_BI=None, r_H=np.array([1.0, 2.0, 3.0]), sigma_att_rad=1e-3, sigma_pos_m=0.5) if i in ANCHORS else None
    return sensors_msg(run=RUN, k=k, t_s=float(k), sat=i, gyro=None, absm=absm, sigma_star=1e-3, sigma_gps=0.5)


def _stamped(msg):
    encode(msg)  # stamps its schema version, as the agent's encoding did before the world relayed it
    return msg


def _rx(k: int, sat: int, batches):
    return Delivery(run=RUN, sender="world", k=k, t_s=float(k), sat=sat,
                    items=[Delivered(arrival_t_s=k + 0.5, batch=_stamped(_meas(s, o))) for s, o in batches])


def _rows(rel: RelativeMeasurements) -> list[tuple[int, int, float]]:
    return [(int(o), int(t), round(float(R[0, 0]), 12)) for o, t, R in zip(rel.observer, rel.target, rel.R_Bi)]


class Calls:
    """A RunBuilder's two bound calls, written down in order."""

    def __init__(self):
        self.calls = []

    def measured_at(self, k, batch):
        self.calls.append(("rel", k, _rows(batch)))

    def absolute_at(self, k, sats):
        self.calls.append(("abs", k, list(sats)))


def _meas_rel(k: int, i: int) -> RelativeMeasurements:
    """Observer i's batch of step k as a reader converts it."""
    return relative_from_batches([decode("meas", encode(_meas(k, i)), n_sats=N)])


def _own(k: int, i: int) -> tuple:
    return ("rel", k, _rows(_meas_rel(k, i)))


# Sat 1 dead at step 2 (no sensors, no batch), sat 2 dead at step 3.
LIVE = {0: [0, 1, 2], 1: [0, 1, 2], 2: [0, 2], 3: [0, 1]}
# What the radio (links) delivered to satellite 1 at each step: (step taken, observer), in
# the link model's order (not sorted); a delivery at step 2 that the world would not send a
# dead agent (not counted: the simulator counts nothing of a dead filter's step).
RX_1 = {0: [], 1: [(1, 2), (0, 0)], 2: [(1, 0)], 3: [(3, 2), (2, 0), (3, 0)]}


def _feed(bi: BoundInputs, kind: str, sat, msg) -> None:
    if bi.wants(kind, sat):
        bi.add(kind, decode(kind, encode(msg), n_sats=N))


def _recorded(bi: BoundInputs, radio: str) -> None:
    """A run's messages, as the recorder might have written them (observers out of order)."""
    for k in range(K):
        for i in reversed(LIVE[k]):
            _feed(bi, "sensors", i, _sensors(k, i))
            _feed(bi, "meas", i, _meas(k, i))
        if radio == "links":
            for j in LIVE[k]:
                _feed(bi, "rx", j, _rx(k, j, RX_1[k] if j == 1 else []))
        elif radio == "ideal":
            _feed(bi, "batches", None, step_batches_msg([_meas(k, i) for i in reversed(LIVE[k])], run=RUN, k=k, t_s=float(k)))
        else:  # graph: each agent its neighbours' (here 1 hears 0 only)
            _feed(bi, "batches", 1, step_batches_msg([_meas(k, 0)], run=RUN, k=k, t_s=float(k)))
            _feed(bi, "batches", 0, step_batches_msg([_meas(k, 1)] if 1 in LIVE[k] else [], run=RUN, k=k, t_s=float(k)))
    if radio == "links":  # the world's rx/2 of step 3 (2 was dead) must not count for filter 1 either
        _feed(bi, "rx", 2, _rx(3, 2, [(3, 0)]))


def test_centralized_counts_every_batch_in_observer_order_and_every_reading_given():
    bi = BoundInputs(N, K, None)
    _recorded(bi, "links")
    c = Calls()
    bi.count(c)
    want = []
    for k in range(K):
        want += [_own(k, i) for i in LIVE[k]]
        want.append(("abs", k, [i for i in LIVE[k] if i in ANCHORS]))
    assert c.calls == want


def test_a_filter_counts_its_own_then_what_the_links_brought_it_at_the_step_taken():
    bi = BoundInputs(N, K, 1)
    _recorded(bi, "links")
    c = Calls()
    bi.count(c)
    assert c.calls == [
        _own(0, 1), ("abs", 0, [1]),
        _own(1, 1), _own(0, 0), _own(1, 2), ("abs", 1, [1]),  # (step, observer) order; 0's batch of step 0 late
        # step 2: filter 1 dead, nothing (not even what was delivered)
        _own(3, 1), _own(2, 0), _own(3, 0), _own(3, 2), ("abs", 3, [1]),
    ]


@pytest.mark.parametrize("radio", ["ideal", "graph"])
def test_a_filter_on_the_ideal_radio_counts_its_own_then_its_peers_rows(radio):
    bi = BoundInputs(N, K, 1)
    _recorded(bi, radio)
    c = Calls()
    bi.count(c)
    want = []
    for k in (0, 1, 3):
        peers = [i for i in LIVE[k] if i != 1 and (radio == "ideal" or i == 0)]
        want += [_own(k, 1), ("rel", k, [r for i in peers for r in _own(k, i)[2]]), ("abs", k, [1])]
    assert c.calls == want


def _truth_messages(sc: Scenario, steps) -> list:
    wp = world_params(sc)
    tr = initial_truth(sc)
    out = []
    for k in range(K):
        if k:
            tr, _gyro = step_truth(wp, tr)
        if k in steps:
            out.append((KEYS.truth(), truth_msg(tr, run=RUN, k=k)))
    return out


def _mcap_messages(sc: Scenario, truth_steps=range(K), steps: int = K) -> list:
    """The (topic, schema, data, log ns, publish ns) a reader yields, of a run with links
    (that recorded its first ``steps`` steps)."""
    msgs = _truth_messages(sc, [k for k in truth_steps if k < steps])
    for k in range(steps):
        for i in LIVE[k]:
            msgs += [(KEYS.sensors(i), _sensors(k, i)), (KEYS.meas(i), _meas(k, i))]
            msgs.append((KEYS.rx(i), _rx(k, i, RX_1[k] if i == 1 else [])))
    if steps == K:
        msgs.append((KEYS.rx(1), _rx(3, 1, RX_1[3])))  # sent again after a bus gap: read once
    return [(topic, m.DESCRIPTOR.full_name, encode(m), 1000 + t, 1000 + t) for t, (topic, m) in enumerate(msgs)]


def _expected_bound(sc: Scenario, truth, steps: int):
    """The bound of filter 1 from what test_a_filter_counts... says it counts."""
    rel: list[list] = [[] for _ in range(steps)]
    absolute = np.zeros((steps, N), dtype=bool)
    for k in (0, 1, 3):
        if k >= steps:
            continue
        rel[k].append(_meas_rel(k, 1))
        for s, o in sorted(RX_1[k]):
            rel[s].append(_meas_rel(s, o))
        absolute[k, 1] = True
    return posterior_crlb(sc, truth, [RelativeMeasurements.concat(b) for b in rel], absolute, gyros=[1], kind="filter 1")


def test_load_recording_computes_the_bound_of_what_was_recorded():
    sc = _sc(bound={"filter": 1}, links={"enabled": True})
    r = load_recording("mem", N, K, messages=_mcap_messages(sc), scenario=sc)
    assert r.bound is not None and r.bound.kind == "filter 1"
    want = _expected_bound(sc, r.truth, K)
    for name in ("att_rad2", "pos_m2", "rel_pos_m2", "att_axes_rad2", "pos_axes_m2"):
        assert np.array_equal(getattr(r.bound, name), getattr(want, name)), name
    # Without its scenario, or with the bound off: no bound (and nothing gathered for it).
    assert load_recording("mem", N, K, messages=_mcap_messages(sc)).bound is None
    assert load_recording("mem", N, K, messages=_mcap_messages(sc), scenario=_sc(bound={"enabled": False})).bound is None
    s = r.summary()
    assert s["bound"]["kind"] == "filter 1" and np.isfinite(s["bound"]["rms"]["pos_m"])


def test_a_recording_that_misses_a_truth_has_the_bound_up_to_it():
    sc = _sc(bound={"filter": 1}, links={"enabled": True})
    r = load_recording("mem", N, K, messages=_mcap_messages(sc, truth_steps=[0, 1, 3]), scenario=sc)
    assert r.bound is not None
    whole = load_recording("mem", N, K, messages=_mcap_messages(sc), scenario=sc).bound
    assert np.array_equal(r.bound.pos_m2[:2], whole.pos_m2[:2]) and np.isnan(r.bound.pos_m2[2:]).all()
    assert np.isfinite(r.summary()["bound"]["rms"]["pos_m"])


def test_an_interrupted_run_has_the_bound_of_the_steps_it_recorded():
    sc = _sc(bound={"filter": 1}, links={"enabled": True})
    r = load_recording("mem", N, None, messages=_mcap_messages(sc, steps=3), scenario=sc)  # K from the truth, as outcome.py
    assert r.K == 3 and r.bound is not None and r.bound.pos_m2.shape == (3, N)
    assert np.isfinite(r.bound.pos_m2).all()
    whole = load_recording("mem", N, K, messages=_mcap_messages(sc), scenario=sc).bound
    # Steps 0 and 1 had everything they ever get by step 2 (step 2's late batch came at step 3).
    assert np.array_equal(r.bound.pos_m2[:2], whole.pos_m2[:2]) and not np.array_equal(r.bound.pos_m2[2], whole.pos_m2[2])
    assert np.array_equal(r.bound.pos_m2, _expected_bound(sc, r.truth, 3).pos_m2)
