"""The gate's Zenoh message counter (swarm.supervise.zenoh_wire): it must find every message a
real Zenoh session sends, whatever its kind, never lose its place in the stream, and charge
what it cannot read at the worst case.

Unit: hand-built batches (variable-length integers, a batch split over reads, a truncated
batch). Integration: a real Zenoh router on a Unix socket behind a real gate, a real client
session through the gate putting, deleting, querying, answering queries, declaring tokens and
subscribers, with tiny and fragmented payloads: the counter finds exactly the puts and
deletes made, every other kind the session used, and no batch it could not read.
"""

from __future__ import annotations

import json
import threading

import pytest
import zenoh

from swarm.supervise.gate import Entry, Gate
from swarm.supervise.zenoh_wire import MIN_MESSAGE_BYTES, WireCounter, _vle, open_syn_user


def _enc_vle(v: int) -> bytes:
    out = bytearray()
    for _ in range(8):
        if v < 0x80:
            out.append(v)
            return bytes(out)
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


@pytest.mark.parametrize("v", [0, 1, 127, 128, 300, 2**32 + 5, 2**56 - 1, 2**56, 2**64 - 1])
def test_variable_length_integers_read_back(v):
    b = _enc_vle(v) + b"\xff"
    assert _vle(b, 0) == (v, len(b) - 1)


def _put(key_id: int, payload: bytes) -> bytes:
    return bytes([0x1D]) + _enc_vle(key_id) + bytes([0x01]) + _enc_vle(len(payload)) + payload


def _batch(body: bytes) -> bytes:
    return len(body).to_bytes(2, "little") + body


def _frame(*msgs: bytes, sn: int = 7) -> bytes:
    return _batch(bytes([0x25]) + _enc_vle(sn) + b"".join(msgs))


def _zbytes(b: bytes) -> bytes:
    return _enc_vle(len(b)) + b


def _open_syn(user: bytes | None, before: bytes = b"", ack: bool = False) -> bytes:
    """An OPEN (T and Z flags; A for an OpenAck): lease 10 s, sn, a cookie, then ``before``
    (other extensions, each marked "more follows") and the auth extension (id 3, bytes)
    holding user/password's (id 2, bytes: the user name and the HMAC)."""
    auth = b""
    if user is not None:
        usrpwd = _zbytes(user) + _zbytes(b"\xaa" * 32)
        auth = bytes([0x43]) + _zbytes(bytes([0x42]) + _zbytes(usrpwd))
    head = 0x02 | 0x40 | (0x20 if ack else 0) | (0x80 if before or auth else 0)
    return bytes([head]) + _enc_vle(10) + _enc_vle(12345) + _zbytes(b"\x07" * 40) + before + auth


def test_the_handshake_says_who_connects():
    assert open_syn_user(_open_syn(b"agent-12")) == "agent-12"
    # Other extensions before it (a unit, an integer, bytes that look like a user): skipped.
    others = bytes([0x81]) + bytes([0xA2]) + _enc_vle(99) + bytes([0xC4]) + _zbytes(bytes([0x42]) + _zbytes(_zbytes(b"world")))
    assert open_syn_user(_open_syn(b"agent-3", before=others)) == "agent-3"
    # No user/password authentication, the router's OpenAck, another message, a truncated one: nobody.
    assert open_syn_user(_open_syn(None)) is None
    assert open_syn_user(_open_syn(b"world", ack=True)) is None
    assert open_syn_user(bytes([0x25]) + _enc_vle(1)) is None
    assert open_syn_user(_open_syn(b"agent-1")[:-40]) is None
    # Fed as a stream, the counter keeps the first OPEN's user (a later one changes nothing).
    w = WireCounter()
    w.feed(_batch(_open_syn(b"agent-1")) + _batch(_open_syn(b"world")))
    assert w.user == "agent-1" and w.unparsed == 0


def test_a_frame_of_puts_split_over_reads_counts_each_put_once():
    stream = _frame(*[_put(3, b"x" * k) for k in range(20)]) + _frame(_put(1, b""), _put(2, b"hello"))
    w = WireCounter()
    batches = [b for i in range(0, len(stream), 5) for b in w.feed(stream[i:i + 5])]
    assert [n for _, n in batches] == [20, 2] and b"".join(b for b, _ in batches) == stream and w.pending == 0
    assert w.messages == 22 and w.by_kind == {"push": 22} and w.unparsed == 0 and w.batches == 2


def test_extensions_and_a_named_key_are_skipped():
    # a push with a named key ("a/b"), a unit, an integer and a bytes extension; a put with an encoding
    # (id 2 without a schema: 2 << 1) and an extension
    push = (bytes([0x1D | 0x20 | 0x80]) + _enc_vle(0) + _enc_vle(3) + b"a/b"
            + bytes([0x80 | 0x01]) + bytes([0x80 | 0x20 | 0x02]) + _enc_vle(999) + bytes([0x40 | 0x03]) + _enc_vle(2) + b"zz"
            + bytes([0x01 | 0x40 | 0x80]) + _enc_vle(4) + bytes([0x40 | 0x01]) + _enc_vle(1) + b"q" + _enc_vle(3) + b"abc")
    w = WireCounter()
    assert [n for _, n in w.feed(_frame(push, _put(1, b"y")))] == [2] and w.unparsed == 0


def test_what_does_not_parse_is_charged_at_the_worst_case():
    body = bytes([0x25]) + _enc_vle(1) + _put(1, b"ok") + bytes([0x1D, 0x01, 0x09]) + b"\x00" * 40  # a push whose body id is 9
    w = WireCounter()
    [(_, n)] = w.feed(_batch(body))
    assert w.unparsed == 1 and "push body id 0x9" in w.first_error
    assert n >= 1 + 40 // MIN_MESSAGE_BYTES  # the good put, then the rest at the worst case
    assert [n for _, n in w.feed(_frame(_put(1, b"next")))] == [1]  # and the next batch is read normally


def test_a_put_in_shared_memory_carries_slices():
    # the batch a real client sent through the gate for a 200 kB put to a router on its host:
    # a put with the shared-memory extension (0x12: unit, mandatory, id 2), one slice, a pointer of 7 bytes
    key = b"w/data/big"
    shm_put = bytes([0x7D, 0x00, len(key)]) + key + bytes([0x81, 0x12, 0x01, 0x01, 0x07]) + bytes.fromhex("c19a0ca3320000")
    raw_put = bytes([0x1D, 0x02, 0x81, 0x12, 0x02, 0x00, 0x03]) + b"abc" + bytes([0x01, 0x02]) + b"\x00\x01"  # two slices
    w = WireCounter()
    assert [n for _, n in w.feed(_frame(shm_put, raw_put, _put(1, b"z")))] == [3] and w.unparsed == 0


def test_a_fragmented_message_counts_at_its_last_fragment():
    frag = lambda more: _batch(bytes([0x26 | (0x40 if more else 0)]) + _enc_vle(9) + b"\x00" * 100)  # noqa: E731
    w = WireCounter()
    assert [n for _, n in w.feed(frag(True) + frag(True))] == [0, 0]
    assert [n for _, n in w.feed(frag(False))] == [1] and w.by_kind == {"fragmented": 1}


def _session(endpoint: str, mode: str = "client") -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints" if mode == "router" else "connect/endpoints", json.dumps([endpoint]))
    if mode == "router":
        cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


@pytest.mark.integration
def test_a_real_session_through_the_gate_is_counted_message_for_message(tmp_path):
    sock = tmp_path / "r.sock"
    router = _session(f"unixsock-stream/{sock}", "router")
    gate = Gate([Entry("client", 0, float("inf"), float("inf"), 1e9, 1e9)], str(sock))
    gate.start()
    try:
        port = gate.entries[0].port
        other = _session(f"unixsock-stream/{sock}")  # beside the gate: the other end of everything
        got: list[int] = []
        done = threading.Event()
        n_tiny, n_big, n_del = 500, 3, 7
        expected = n_tiny + n_big + n_del

        def on(sample: zenoh.Sample) -> None:
            got.append(len(sample.payload.to_bytes()))
            if len(got) == expected:
                done.set()

        sub = other.declare_subscriber("w/data/**", on)
        qa = other.declare_queryable("w/ask", lambda q: q.reply("w/ask", b"answer"))
        client = _session(f"tcp/127.0.0.1:{port}")
        block = zenoh.CongestionControl.BLOCK  # never dropped by the client's queue: every put reaches the gate
        token = client.liveliness().declare_token("w/alive/client")
        qc = client.declare_queryable("w/client/ask", lambda q: q.reply("w/client/ask", b"from the client"))
        client_sub = client.declare_subscriber("w/news", lambda s: None)
        pub_ready = threading.Event()
        live = other.liveliness().declare_subscriber("w/alive/**", lambda s: pub_ready.set(), history=True)
        assert pub_ready.wait(10), "the client's token never reached the router"
        for k in range(n_tiny):
            client.put(f"w/data/{k % 5}", bytes([k % 256]), congestion_control=block)
        for k in range(n_big):
            # Over a batch: fragmented, or in shared memory (Zenoh's choice on one host)
            client.put("w/data/big", b"b" * (200_000 + k), congestion_control=block)
        for k in range(n_del):
            client.delete(f"w/data/{k}", congestion_control=block)
        replies = list(client.get("w/ask", timeout=10.0))
        assert [r.ok.payload.to_bytes() for r in replies] == [b"answer"]
        answers = list(other.get("w/client/ask", timeout=10.0))
        assert [r.ok.payload.to_bytes() for r in answers] == [b"from the client"]
        assert done.wait(20), f"{len(got)} of {expected} samples arrived"
        for x in (qc, client_sub, token):
            x.undeclare()
        client.close()
        for x in (live, sub, qa):
            x.undeclare()
        other.close()
    finally:
        gate.stop()
        router.close()
    c = gate.counts()["client"]
    assert c["unparsed"] == 0, c
    kinds = {k: c["messages_by_kind"].get(k, 0) for k in ("push", "fragmented", "request", "response", "response_final", "declare")}
    assert kinds["push"] + kinds["fragmented"] == n_tiny + n_big + n_del, kinds  # every put and delete, each once
    assert kinds["request"] >= 1 and kinds["response"] >= 1 and kinds["response_final"] >= 1 and kinds["declare"] >= 3, kinds
    assert c["messages_in"] == sum(c["messages_by_kind"].values())
