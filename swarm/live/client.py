"""A minimal Foxglove WebSocket client: what the tests, ``swarm bench live`` and the README's
screenshot use to read the live view, with nothing of the project's but this file.

The protocol as served by foxglove-sdk 0.30: the subprotocol is ``foxglove.sdk.v1`` (the SDK
answers HTTP 400 to the older ``foxglove.websocket.v1``); text frames are JSON with an
``op`` (``serverInfo`` first, then ``advertise``: each channel's id, topic, encoding,
schemaName, schemaEncoding and schema, base64 of the FileDescriptorSet); the client sends
``{"op": "subscribe", "subscriptions": [{"id": ..., "channelId": ...}]}``; a binary frame is
opcode 0x01, a u32 LE subscription id, a u64 LE log time (ns) and the payload. Payloads are
decoded with classes built from the *advertised* schemas (a fresh descriptor pool), not
from any generated code.

    python -m swarm.live.client ws://127.0.0.1:8765 --seconds 30 [--json stats.json]

reads every topic for 30 s and prints (and writes) how many messages and bytes came.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import struct
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

__all__ = ["SUBPROTOCOL", "Received", "message_class", "collect", "watch", "main"]

SUBPROTOCOL = "foxglove.sdk.v1"
_HDR = struct.Struct("<BIQ")  # opcode, subscription id, log time (ns)


def message_class(schema_name: str, fds_bytes: bytes):
    """The protobuf class of ``schema_name`` built from a serialized FileDescriptorSet, in a
    pool of its own (files added dependencies first, whatever their order in the set)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(fds_bytes)
    pool = descriptor_pool.DescriptorPool()
    files = {f.name: f for f in fds.file}
    added: set[str] = set()

    def add(name: str) -> None:
        if name in added:
            return
        added.add(name)
        for dep in files[name].dependency:
            add(dep)
        pool.Add(files[name])

    for name in files:
        add(name)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


@dataclass
class Received:
    topic: str
    schema_name: str
    log_ns: int
    data: bytes
    msg: object  # decoded with the advertised schema (None when not asked to decode)


@dataclass
class Session:
    """What a :func:`watch` saw: the server's info, the advertised channels, per-topic counts."""

    server_info: dict = field(default_factory=dict)
    channels: dict[int, dict] = field(default_factory=dict)  # channel id → advertised channel
    counts: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)

    @property
    def topics(self) -> dict[str, dict]:
        return {c["topic"]: c for c in self.channels.values()}


async def watch(url: str, on_message: Callable[[Received], bool | None], topics: Iterable[str] | None = None,
                timeout_s: float = 30.0, decode: bool = True, session: Session | None = None) -> Session:
    """Connect, subscribe to ``topics`` (every advertised topic when None; ones advertised
    later too) and hand each message to ``on_message`` until it returns True or
    ``timeout_s`` passes (then :class:`TimeoutError`, unless ``on_message`` is never meant to
    stop: pass ``timeout_s`` as the duration and catch it)."""
    import websockets
    from websockets.typing import Subprotocol

    want = None if topics is None else set(topics)
    ses = session or Session()
    subs: dict[int, tuple[dict, object]] = {}
    next_sub = 1
    deadline = time.monotonic() + timeout_s
    async with websockets.connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)], max_size=None, open_timeout=timeout_s) as ws:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{url}: timed out after {timeout_s:.0f} s; received {ses.counts}")
            frame = await asyncio.wait_for(ws.recv(), left)
            if isinstance(frame, str):
                m = json.loads(frame)
                op = m.get("op")
                if op == "serverInfo":
                    ses.server_info = m
                elif op == "advertise":
                    new = []
                    for c in m["channels"]:
                        ses.channels[c["id"]] = c
                        if want is None or c["topic"] in want:
                            cls = None
                            if decode and c.get("schemaEncoding") == "protobuf":
                                cls = message_class(c["schemaName"], base64.b64decode(c["schema"]))
                            subs[next_sub] = (c, cls)
                            new.append({"id": next_sub, "channelId": c["id"]})
                            next_sub += 1
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif op == "unadvertise":
                    for cid in m.get("channelIds", []):
                        ses.channels.pop(cid, None)
                continue
            if frame[0] != 0x01:
                continue
            _op, sub, log_ns = _HDR.unpack_from(frame)
            if sub not in subs:
                continue
            ch, cls = subs[sub]
            payload = bytes(frame[_HDR.size:])
            topic = ch["topic"]
            ses.counts[topic] = ses.counts.get(topic, 0) + 1
            ses.bytes[topic] = ses.bytes.get(topic, 0) + len(payload)
            msg = cls.FromString(payload) if cls is not None else None  # type: ignore[attr-defined]
            if on_message(Received(topic, ch["schemaName"], log_ns, payload, msg)):
                return ses


def collect(url: str, topics: Iterable[str] | None = None, until: Callable[[list[Received]], bool] | None = None,
            timeout_s: float = 30.0, ok_if_closed: bool = False) -> list[Received]:
    """Every message received (decoded) until ``until(received)`` is true; raises
    :class:`TimeoutError` after ``timeout_s``. ``ok_if_closed``: the server closing the
    connection (its run is over) ends the collection too."""
    from websockets.exceptions import ConnectionClosed

    got: list[Received] = []

    def on(m: Received) -> bool:
        got.append(m)
        return bool(until(got)) if until is not None else False

    try:
        asyncio.run(watch(url, on, topics, timeout_s))
    except ConnectionClosed:
        if not ok_if_closed:
            raise
    return got


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="read a Foxglove WebSocket server: counts per topic")
    p.add_argument("url")
    p.add_argument("--seconds", type=float, default=30.0, help="how long to read")
    p.add_argument("--decode", action="store_true", help="decode every message with its advertised schema too")
    p.add_argument("--json", default=None, help="write the counts here")
    p.add_argument("--connect-timeout", type=float, default=60.0, help="keep trying to connect this long")
    a = p.parse_args(argv)
    from websockets.exceptions import ConnectionClosed

    ses = Session()
    t0 = time.monotonic()
    while True:  # the server may not be up yet
        try:
            asyncio.run(watch(a.url, lambda m: False, None, a.seconds, a.decode, ses))
        except (TimeoutError, ConnectionClosed):  # read long enough, or the server went away
            break
        except OSError:
            if time.monotonic() - t0 > a.connect_timeout:
                raise
            time.sleep(0.2)
            continue
        break
    out = {"url": a.url, "seconds": a.seconds, "messages": sum(ses.counts.values()), "bytes": sum(ses.bytes.values()),
           "per_topic": ses.counts, "cpu_s": time.process_time()}
    print(json.dumps(out), flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
