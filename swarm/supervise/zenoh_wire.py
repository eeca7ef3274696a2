"""Counting Zenoh messages in a TCP byte stream: what the ingress gate charges its message
bucket with (issue 35: a flood of tiny puts stays under any byte rate an honest role needs).

What it reads: Zenoh 1.x's unicast wire format over a streamed link (protocol 0x09, as in
Zenoh's ``zenoh-codec`` crate): every batch is prefixed by its length (two bytes, little
endian); a batch holds transport messages (``FRAME``, ``FRAGMENT``, ``KEEP_ALIVE``, and the
handshake's ``INIT``/``OPEN``/``CLOSE``); a ``FRAME`` holds network messages back to back
(``PUSH``, ``REQUEST``, ``RESPONSE``, ``RESPONSE_FINAL``, ``INTEREST``, ``DECLARE``, ``OAM``)
with no length of their own, so finding where one ends means reading its fields: key
expressions, flags, variable-length integers and extensions (whose encoding, unit, integer
or length-prefixed bytes, is in their header, so unknown ones are skipped). A fragmented
message counts once, at its last fragment. A put whose payload is in shared memory (Zenoh
negotiates it with a router on the same host, even over TCP, for payloads of a few kB and
more) carries slices instead of bytes: counted like any other.

Why by hand: no library parses Zenoh's wire format outside Zenoh's own Rust crates, and
Zenoh's Python API has no hook on what a router receives. It reads only lengths and flags,
never payloads, and it never changes a byte: the gate relays the stream as it came.

What it cannot read it charges at the worst case: the rest of a batch it fails to parse
counts as one message per :data:`MIN_MESSAGE_BYTES` (the smallest a put can be), and the
batch is counted in ``unparsed``. So a sender gains nothing by sending what this does not
understand; an honest run has ``unparsed`` 0 (``tests/test_router_gate.py`` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

MIN_MESSAGE_BYTES = 4  # the smallest put: a PUSH header, a key id, a PUT header, a payload length

# transport message ids (the low five bits of a header byte)
_T_INIT, _T_OPEN, _T_CLOSE, _T_KEEP_ALIVE, _T_FRAME, _T_FRAGMENT = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
# network message ids
_N_INTEREST, _N_RESPONSE_FINAL, _N_RESPONSE, _N_REQUEST, _N_PUSH, _N_DECLARE, _N_OAM = 0x19, 0x1A, 0x1B, 0x1C, 0x1D, 0x1E, 0x1F
NETWORK_KINDS = {_N_PUSH: "push", _N_REQUEST: "request", _N_RESPONSE: "response", _N_RESPONSE_FINAL: "response_final",
                 _N_INTEREST: "interest", _N_DECLARE: "declare", _N_OAM: "oam"}
# zenoh (payload) message ids
_Z_PUT, _Z_DEL, _Z_QUERY, _Z_REPLY, _Z_ERR = 0x01, 0x02, 0x03, 0x04, 0x05
_D_FINAL = 0x1A  # a declaration's "final"; the other declaration ids are 0..7

_SHM_EXT = 0x02  # a put's or an error's extension: the payload is in shared memory (a local peer)
_MID = 0x1F
_Z = 0x80  # "extensions follow", in every header
_VLE_LEN_MAX = 9


class Unparsed(Exception):
    """A batch does not follow the format (truncated, an unknown id or encoding)."""


def _vle(b: bytes, i: int) -> tuple[int, int]:
    """A variable-length integer (7 bits a byte, least significant first; the ninth byte
    whole) at ``i``: its value and the offset after it."""
    v = 0
    shift = 0
    for _ in range(_VLE_LEN_MAX - 1):
        x = b[i]
        i += 1
        v |= (x & 0x7F) << shift
        if not x & 0x80:
            return v, i
        shift += 7
    return v | (b[i] << shift), i + 1


def _bytes(b: bytes, i: int) -> int:
    """Skip a length-prefixed byte string (a key suffix, a payload, an id)."""
    n, i = _vle(b, i)
    return i + n


def _body(b: bytes, i: int, enc: int) -> int:
    """Skip a body by its encoding (bits 5-6 of its header): nothing, an integer, or a
    length-prefixed byte string (an extension's, a network OAM's)."""
    if enc == 0x20:
        _, i = _vle(b, i)
    elif enc == 0x40:
        i = _bytes(b, i)
    elif enc != 0x00:
        raise Unparsed(f"body encoding {enc:#x}")
    return i


def _payload_exts(b: bytes, i: int, more: int) -> tuple[int, bool]:
    """Skip extensions while the previous header said more follow; say whether one was
    shared memory (id 2, on a put or an error: its payload is then in slices, not one byte
    string)."""
    shm = False
    while more:
        h = b[i]
        i = _body(b, i + 1, h & 0x60)
        shm = shm or (h & 0x60 == 0x00 and h & 0x0F == _SHM_EXT)
        more = h & _Z
    return i, shm


def _exts(b: bytes, i: int, more: int) -> int:
    """Skip extensions (of any message but a put or an error)."""
    return _payload_exts(b, i, more)[0]


def _payload(b: bytes, i: int, shm: bool) -> int:
    """Skip a payload: one byte string, or (shared memory) a count of slices, each a kind
    byte (raw bytes or a pointer into shared memory) and a byte string."""
    if not shm:
        return _bytes(b, i)
    n, i = _vle(b, i)
    for _ in range(n):
        if b[i] not in (0, 1):
            raise Unparsed(f"payload slice kind {b[i]:#x}")
        i = _bytes(b, i + 1)
    return i


def _key(b: bytes, i: int, named: int) -> int:
    """Skip a key expression: a declared id, then (named) a suffix."""
    _, i = _vle(b, i)
    return _bytes(b, i) if named else i


def _timestamp(b: bytes, i: int) -> int:
    _, i = _vle(b, i)
    return _bytes(b, i)


def _encoding(b: bytes, i: int) -> int:
    eid, i = _vle(b, i)
    return _bytes(b, i) if eid & 1 else i


def _push_body(b: bytes, i: int) -> int:
    """A PUT or a DEL (the body of a push and of a reply)."""
    h = b[i]
    i += 1
    mid = h & _MID
    if mid == _Z_PUT:
        if h & 0x20:
            i = _timestamp(b, i)
        if h & 0x40:
            i = _encoding(b, i)
        i, shm = _payload_exts(b, i, h & _Z)
        return _payload(b, i, shm)
    if mid == _Z_DEL:
        if h & 0x20:
            i = _timestamp(b, i)
        return _exts(b, i, h & _Z)
    raise Unparsed(f"push body id {mid:#x}")


def _routed_head(b: bytes, i: int, h: int) -> tuple[int, int]:
    """A request's or a response's request id, key and extensions (header ``h`` at
    ``i - 1``): where its body begins after the body's header byte, and that byte."""
    _, i = _vle(b, i)
    i = _key(b, i, h & 0x20)
    i = _exts(b, i, h & _Z)
    return i + 1, b[i]


def _network(b: bytes, i: int, h: int) -> int:
    """Skip one network message whose header ``h`` was at ``i - 1``."""
    mid = h & _MID
    if mid == _N_PUSH:
        i = _key(b, i, h & 0x20)
        i = _exts(b, i, h & _Z)
        return _push_body(b, i)
    if mid == _N_REQUEST:
        i, q = _routed_head(b, i, h)
        if q & _MID != _Z_QUERY:
            raise Unparsed(f"request body id {q & _MID:#x}")
        if q & 0x20:
            _, i = _vle(b, i)  # consolidation
        if q & 0x40:
            i = _bytes(b, i)  # parameters
        return _exts(b, i, q & _Z)
    if mid == _N_RESPONSE:
        i, r = _routed_head(b, i, h)
        if r & _MID == _Z_REPLY:
            if r & 0x20:
                _, i = _vle(b, i)  # consolidation
            i = _exts(b, i, r & _Z)
            return _push_body(b, i)
        if r & _MID == _Z_ERR:
            if r & 0x40:
                i = _encoding(b, i)
            i, shm = _payload_exts(b, i, r & _Z)
            return _payload(b, i, shm)
        raise Unparsed(f"response body id {r & _MID:#x}")
    if mid == _N_RESPONSE_FINAL:
        _, i = _vle(b, i)
        return _exts(b, i, h & _Z)
    if mid == _N_INTEREST:
        _, i = _vle(b, i)
        if (h >> 5) & 0b11:  # not a "final" interest: its options, maybe a key
            opts = b[i]
            i += 1
            if opts & 0x10:
                i = _key(b, i, opts & 0x20)
        return _exts(b, i, h & _Z)
    if mid == _N_DECLARE:
        if h & 0x20:
            _, i = _vle(b, i)  # the interest it answers
        i = _exts(b, i, h & _Z)
        d = b[i]
        i += 1
        did = d & _MID
        if did == _D_FINAL:
            return _exts(b, i, d & _Z)
        if did > 0x07:
            raise Unparsed(f"declaration id {did:#x}")
        _, i = _vle(b, i)  # the declared entity's id
        if did % 2 == 0:  # a declaration (key expression, subscriber, queryable, token) names a key
            i = _key(b, i, d & 0x20)
        return _exts(b, i, d & _Z)
    if mid == _N_OAM:
        _, i = _vle(b, i)
        i = _exts(b, i, h & _Z)
        return _body(b, i, h & 0x60)
    raise Unparsed(f"network message id {mid:#x}")


_OPEN_ACK = 0x20  # OPEN's A flag: an OpenAck (the router's answer), not the client's OpenSyn
_EXT_AUTH, _AUTH_USRPWD = 0x03, 0x02  # OpenSyn's auth extension; in it, user/password authentication's


def open_syn_user(b: bytes) -> str | None:
    """The user name an ``OpenSyn`` (a batch's first message, without its length prefix)
    authenticates as, or None (another message, no user/password authentication, or not
    readable). Zenoh's user/password authentication sends the user name in clear (only the
    password is a challenge-response): ``OPEN`` header, lease, initial sn, cookie, then its
    extensions; the auth extension (id 3) holds the methods' own extensions, user/password's
    (id 2) a byte string: the user name, then the HMAC (zenoh-transport's
    ``establishment/ext/auth/usrpwd.rs``). The router checks the HMAC against the same
    user name, so a connection the router admits is the identity read here."""
    try:
        h = b[0]
        if h & _MID != _T_OPEN or h & _OPEN_ACK:
            return None
        _, i = _vle(b, 1)  # lease
        _, i = _vle(b, i)  # initial sn
        i = _bytes(b, i)  # cookie
        more = h & _Z
        while more:
            eh = b[i]
            more = eh & _Z
            if eh & 0x0F == _EXT_AUTH and eh & 0x60 == 0x40:
                n, j = _vle(b, i + 1)
                end = j + n
                if end > len(b):
                    return None  # truncated
                sub_more = 1 if n else 0
                while sub_more and j < end:
                    sh = b[j]
                    sub_more = sh & _Z
                    if sh & 0x0F == _AUTH_USRPWD and sh & 0x60 == 0x40:
                        _, k = _vle(b, j + 1)
                        n_user, k = _vle(b, k)
                        if k + n_user > end:
                            return None
                        return bytes(b[k:k + n_user]).decode()
                    j = _body(b, j + 1, sh & 0x60)
                return None
            i = _body(b, i + 1, eh & 0x60)
    except (Unparsed, IndexError, UnicodeDecodeError):
        return None
    return None


@dataclass
class WireCounter:
    """The messages of one connection's inbound stream, fed as it is read."""

    messages: int = 0  # network messages (a fragmented one once), plus the worst case of what did not parse
    by_kind: dict[str, int] = field(default_factory=dict)
    batches: int = 0
    unparsed: int = 0  # batches that did not follow the format (charged at the worst case)
    first_error: str = ""
    user: str | None = None  # the user name its OpenSyn authenticated as (open_syn_user), once read
    _buf: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[tuple[bytes, int]]:
        """Add what was read; return each batch it completed (with its length prefix, as it
        came) and how many messages that batch holds. What is left of a batch stays here
        until the rest of it is read."""
        buf = self._buf
        buf += data
        out = []
        at = 0
        end = len(buf)
        while end - at >= 2:
            n = buf[at] | (buf[at + 1] << 8)
            if end - at - 2 < n:
                break
            framed = bytes(buf[at:at + 2 + n])
            before = self.messages
            self._batch(framed[2:])
            out.append((framed, self.messages - before))
            at += 2 + n
        if at:
            del buf[:at]
        return out

    def release(self) -> None:
        """The connection ended: drop what is buffered (a flooder that reconnects often
        must not leave a half batch behind each time)."""
        self._buf = bytearray()

    def take_pending(self) -> bytes:
        """What is buffered of a batch not yet whole, handed over (the stream goes on
        uncounted from here: the gate relays it as bytes)."""
        rest, self._buf = bytes(self._buf), bytearray()
        return rest

    @property
    def pending(self) -> int:
        """Bytes of a batch not yet whole."""
        return len(self._buf)

    def _batch(self, b: bytes) -> None:
        self.batches += 1
        i = 0
        end = len(b)
        try:
            while i < end:
                h = b[i]
                i += 1
                mid = h & _MID
                if mid == _T_FRAME:
                    _, i = _vle(b, i)
                    i = _exts(b, i, h & _Z)
                    while i < end and (b[i] & _MID) in NETWORK_KINDS:
                        kind = NETWORK_KINDS[b[i] & _MID]
                        i = _network(b, i + 1, b[i])
                        if i > end:
                            raise Unparsed("message runs past its batch")
                        self.messages += 1
                        self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
                elif mid == _T_FRAGMENT:
                    _, i = _vle(b, i)
                    i = _exts(b, i, h & _Z)
                    if not h & 0x40:  # the last fragment: one message
                        self.messages += 1
                        self.by_kind["fragmented"] = self.by_kind.get("fragmented", 0) + 1
                    return  # a fragment's payload is the rest of the batch
                elif mid == _T_KEEP_ALIVE:
                    i = _exts(b, i, h & _Z)
                elif mid in (_T_INIT, _T_OPEN, _T_CLOSE):
                    if mid == _T_OPEN and self.user is None:
                        self.user = open_syn_user(b[i - 1:])
                    return  # the handshake and the goodbye: each in a batch of its own, nothing to count
                else:
                    raise Unparsed(f"transport message id {mid:#x}")
            if i > end:
                raise Unparsed("message runs past its batch")
        except (Unparsed, IndexError) as exc:
            self.unparsed += 1
            if not self.first_error:
                self.first_error = f"{type(exc).__name__}: {exc} at byte {i} of a {end}-byte batch starting {b[:40].hex()}"
            self.messages += max(1, (end - min(i, end)) // MIN_MESSAGE_BYTES)
