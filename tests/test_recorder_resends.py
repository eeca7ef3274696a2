"""The recorder's flood cap tells a resend from a flood (issue 37): a message sent again with
the same key, step and content (each role sends its step again when the bus comes back) is
written once and counted apart; messages of different content on one key and step are cut at
the cap and counted as a flood. Drives a real recorder on a real (loopback) Zenoh session,
feeding it samples the way its inbox does."""

from __future__ import annotations

import time

import pytest

from swarm.record.recorder import FLOOD_CAP_PER_STEP, Recorder
from swarm.record.recording import load_recording
from swarm.supervise.launch import free_port
from swarmcore.scenario import Scenario
from swarmrt.bus import messages as M
from swarmrt.bus.session import BusConfig, Sample

pytestmark = [pytest.mark.integration]

RUN = "resend-test"


def clock(k: int, live: list[int]) -> bytes:
    return M.encode(M.Clock(run=RUN, sender="world", k=k, t_s=float(k), live_agents=live, mode="lockstep"))


def test_resends_are_written_once_and_counted_apart_from_a_flood(tmp_path):
    sc = Scenario(n_sats=2, duration_s=10.0)
    bus = BusConfig(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    out = tmp_path / "run.mcap"
    rec = Recorder(RUN, str(out), bus, derive_foxglove=False, scenario=sc)
    key = M.Keys(RUN).clock()

    def feed(payload: bytes) -> None:
        rec.record(Sample(key, payload, "put", time.time_ns(), time.time_ns()))

    try:
        feed(clock(1, [0, 1]))
        for _ in range(25):  # the bus came back: the world's clock of step 1 again, the same bytes
            feed(clock(1, [0, 1]))
        distinct = FLOOD_CAP_PER_STEP + 5
        for j in range(distinct):  # step 2: messages of different content on one key and step: a flood
            feed(clock(2, [0, 1, 100 + j]))
        for _ in range(3):  # a copy of a flood message already written is a resend too
            feed(clock(2, [0, 1, 100]))
        assert rec.resent == {key: 28} and rec.not_recorded == {key: distinct - FLOOD_CAP_PER_STEP}
    finally:
        rec.close()
    res = load_recording(out, n=sc.n_sats, K=sc.steps)
    assert res.bus.counts.get("clock") == 1 + FLOOD_CAP_PER_STEP  # written: one of step 1, the cap of step 2
    assert res.bus.resent_not_written == {key: 28}
    assert res.bus.not_recorded == {key: distinct - FLOOD_CAP_PER_STEP}
    summary = res.summary(sc)
    assert summary["messages"]["resent_not_written"] == {key: 28}
    assert summary["messages"]["not_recorded_over_the_flood_cap"] == {key: distinct - FLOOD_CAP_PER_STEP}
