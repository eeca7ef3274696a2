"""The live 3-D view: a running swarm's scene served over the Foxglove WebSocket protocol.

``swarm run --live [HOST:PORT]`` starts it with the run (default ``127.0.0.1:8765``); ``swarm
live attach --run-dir OUT`` joins a run already going; compose has it as the service ``live``
(profile ``live``). Open it in Foxglove (*Open connection* → *Foxglove WebSocket* →
``ws://HOST:PORT``) with the layout ``docs/foxglove-layout.json`` (``swarm live layout``
writes one for another swarm size).

The view is its own process (:mod:`swarm.live.server`) and an observer of the bus: it connects
as the read-only ``viewer`` identity, subscribes to the truth, the estimates, the measurement
batches, the link counters and the faults, builds the scene with the recorder's builder
(:mod:`swarm.record.scene`, so the recording and ``swarm sim``'s ``scene.mcap`` carry the same
channels) and logs it to the Foxglove SDK's server. It puts nothing on the bus, so the lockstep
never waits for it; it builds only what a connected client subscribed to, at most
``--max-rate`` times a wall second (the latest step wins), and clients may come and go.

* :mod:`swarm.live.server` — the process (``python -m swarm.live.server``);
* :mod:`swarm.live.sink` — scene messages onto the SDK's channels;
* :mod:`swarm.live.client` — a minimal WebSocket client (tests, the benchmark, screenshots);
* :mod:`swarm.live.layout` — the Foxglove layout.
"""

__all__ = ["DEFAULT_ADDRESS", "parse_address"]

#: Where ``swarm run --live`` serves when given no address.
DEFAULT_ADDRESS = "127.0.0.1:8765"


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8765`` for IPv6; port 0: any free port) → (host, port);
    ValueError naming what is wrong."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: expected HOST:PORT, e.g. {DEFAULT_ADDRESS}")
    return host.strip("[]"), int(port)
