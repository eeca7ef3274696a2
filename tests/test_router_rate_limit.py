"""Why the router has no rate limit (docs/security.md, "Size limits on the router"): Zenoh's
``downsampling``, the rate limit a router offers, passes a message on a rule only if 1/freq
has gone by since the last it passed, with no allowance for a burst; a role whose bus came
back sends its last two steps' messages back to back on the same key
(:class:`swarmrt.protocol.Outbox`), so the second of them, the step's own, would be
dropped. A real router on loopback, configured with :func:`swarmrt.security.rate_limits`:
if Zenoh ever lets a burst through, this test fails and the decision is to be made again.
"""

from __future__ import annotations

import json

import pytest
import zenoh
from forgery import Witness

from swarm.supervise.launch import free_port
from swarmrt.bus import messages as M
from swarmrt.security import rate_limits

pytestmark = pytest.mark.integration

RUN = "rate"


def _config(mode: str, endpoint: str) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints" if mode == "router" else "connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


def test_a_rate_limit_drops_the_second_message_of_a_burst_whatever_its_rate():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = _config("router", endpoint)
    # 1 Hz on every agent key; the test's puts are far apart from anything else on theirs.
    cfg.insert_json5("downsampling", json.dumps(rate_limits(RUN, 2, False, 1.0)))
    k = M.Keys(RUN)
    with zenoh.open(cfg), zenoh.open(_config("client", endpoint)) as sub_s, zenoh.open(_config("client", endpoint)) as pub_s:
        w = Witness(sub_s, f"swarm/{RUN}/**")
        # The subscription reaches the router: a put on a key without a rule, until seen.
        for _ in range(100):
            pub_s.put(k.clock(), b"ready")
            if w.wait_for(lambda key, p: p == b"ready", 0.1):
                break
        else:
            pytest.fail("the subscription never reached the router")
        # What a role sends when the bus comes back: its estimate of the step before, then
        # this step's, back to back; then a control on a key without a rule (a session's puts
        # reach a subscriber in order: once it is in, so is whatever passed before it).
        pub_s.put(k.est(1), b"estimate of k-1")
        pub_s.put(k.est(1), b"estimate of k")
        pub_s.put(k.clock(), b"control")
        assert w.wait_for(lambda key, p: p == b"control", 10.0)
        got = [p for key, p in w.got if key == k.est(1)]
    assert got == [b"estimate of k-1"], got
