"""The malformed and forged messages the kit puts on an agent's inputs (clauses C14–C16).

Every one goes on a key agent i subscribes to (``clock``, ``sat/<i>/sensors``,
``sat/<i>/cam``, ``batches``, ``fault``), published with a credential that may publish
there (the world's: the router lets it through, so only the agent's own checks stand
between it and the filter). Each is stamped with the step after the current one and
says something an agent that believed it would act on: a clock that ends the run, a
drop fault that silences it, sensors and peer batches of the coming step.

*Malformed* ones fail ``swarmrt.bus.messages.decode`` (bytes, schema version, a number,
array lengths, a run id, an enumeration); *forged* ones are valid messages whose sender
or satellite disagrees with the key (``check_key`` raises ``KeyMismatch``).
:func:`injections` checks both of itself before the kit sends anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from swarmrt.bus import messages as M
from swarmrt.bus.receive import receive

__all__ = ["Injection", "injections", "self_check"]


@dataclass(frozen=True)
class Injection:
    name: str
    key: str
    payload: bytes
    forged: bool  # a valid message on a key its sender/satellite may not use (else: malformed)


def _sensors(run: str, k: int, sat: int, **kw) -> M.Sensors:
    base: dict[str, Any] = dict(run=run, sender="world", k=k, t_s=float(k), sat=sat, gyro_rate_B_rad_s=[0.01, -0.02, 0.03],
                q_BI_star=[0.0, 0.0, 0.0, 1.0], r_H_gps_m=[100.0, 200.0, 300.0], sigma_star_rad=1e-4, sigma_gps_m=1.0)
    base.update(kw)
    return M.Sensors(**base)


def _batches(run: str, k: int, observer: int, target: int, **kw) -> M.StepBatches:
    base: dict[str, Any] = dict(run=run, sender="world", k=k, t_s=float(k), observers=[observer], counts=[1], target=[target], camera=[0],
                q_BjBi=[0.0, 0.0, 0.0, 1.0], r_ij_Bi_m=[1.0, 2.0, 3.0],
                R_Bi=M.Matrix(shape=[1, 6, 6], data=(np.eye(6) * 1e-4).ravel().tolist()))
    base.update(kw)
    return M.StepBatches(**base)


def _enc(msg) -> bytes:
    return M.encode(msg)


def injections(run: str, sat: int, n: int, k: int, radio: str | None = None) -> list[Injection]:
    """What the kit puts on agent ``sat``'s inputs when the run is at step ``k`` (a swarm
    of ``n``; the peer it names is ``(sat + 1) % n``). ``radio``: the key its ideal radio
    delivers on (default ``batches``; ``batches/<sat>`` for an estimator that hears its
    graph neighbours)."""
    keys = M.Keys(run)
    radio = radio or keys.batches()
    peer = (sat + 1) % n
    nxt = k + 1
    sensors_v2 = _sensors(run, nxt, sat)
    sensors_v2.schema_version = 2
    cam_nan = M.CameraOutput(run=run, sender="world", k=nxt, t_s=float("nan"), sat=sat)
    out = [
        # -- malformed: decode refuses them
        Injection("sensors: bytes that are no protobuf", keys.sensors(sat), b"\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\x01", False),
        Injection("sensors: schema_version 2", keys.sensors(sat), sensors_v2.SerializeToString(), False),
        Injection("cam: t_s not finite", keys.cam(sat), _enc(cam_nan), False),
        Injection("batches: counts that do not add up", radio,
                  _enc(_batches(run, nxt, peer, sat, counts=[2])), False),
        Injection("clock: another run's id, done", keys.clock(),
                  _enc(M.Clock(run="not-this-run", sender="world", k=nxt, t_s=float(nxt), live_agents=[sat], mode="lockstep",
                               done=True)), False),
        Injection("fault: an unknown action", keys.fault(),
                  _enc(M.Fault(run=run, sender="cli", k=k, t_s=float(k), action="explode", phase="command", target=sat)), False),
        # -- forged: valid, but the sender or the satellite is not the key's
        Injection("sensors naming another satellite", keys.sensors(sat), _enc(_sensors(run, nxt, peer)), True),
        Injection(f"clock from agent-{peer}: done", keys.clock(),
                  _enc(M.Clock(run=run, sender=f"agent-{peer}", k=nxt, t_s=float(nxt), live_agents=[sat], mode="lockstep",
                               done=True)), True),
        Injection(f"fault command from agent-{peer}: drop all of {sat}'s messages", keys.fault(),
                  _enc(M.Fault(run=run, sender=f"agent-{peer}", k=k, t_s=float(k), action="drop", phase="command", target=sat,
                               rate=1.0)), True),
        Injection(f"batches from agent-{peer}", radio,
                  _enc(_batches(run, nxt, peer, sat, sender=f"agent-{peer}")), True),
    ]
    return out


def self_check(items: list[Injection], n: int) -> None:
    """Every malformed injection fails the receive path every node runs
    (:func:`swarmrt.bus.receive.receive`) but not as a key mismatch; every forged one
    passes every check but the last and fails it with ``KeyMismatch``."""
    for it in items:
        run = M.parse_key(it.key)[0]
        try:
            receive(it.key, it.payload, run, n_sats=n)
        except M.KeyMismatch:
            if not it.forged:
                raise AssertionError(f"{it.name}: a key mismatch, meant as malformed") from None
            continue
        except M.MessageError:
            if it.forged:
                raise AssertionError(f"{it.name}: refused as malformed, meant as forged") from None
            continue
        raise AssertionError(f"{it.name}: accepted by the checks every receiver makes")
