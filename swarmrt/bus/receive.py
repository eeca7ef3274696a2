"""The one receive path: a bus sample (its key and payload) becomes a checked message, or a
:class:`~swarmrt.bus.messages.MessageError` that names what is wrong.

Every reader of the bus calls :func:`receive` and nothing else to open a sample: the roles'
:class:`swarmrt.node.Node` (subscriptions and query replies), the recorder, the live view,
the conformance kit, the chaos checks, the supervisor's router watch and the fuzz harnesses
(``fuzz/targets.py``: the 10⁶-input campaigns run this very function).
``tests/test_receive_path.py`` fails if a module outside this one and the codec
(:mod:`swarmrt.bus.messages`) calls ``decode``, ``validate`` or ``check_key`` itself.

In order (the first failure is the error):

1. the key: a key of the key space (:func:`~swarmrt.bus.messages.parse_key`), of this run,
   and of the kind the reader expects (a query's reply);
2. liveliness tokens (``alive/<role>/<id>``) stop here: no payload to read;
3. a delete is refused; a satellite the key names must be one of the swarm's;
4. decode and validate (:func:`~swarmrt.bus.messages.decode`: the size limit of the kind,
   the protobuf parse, the checks the schema cannot make, every satellite id below the
   swarm's size), shallow where the reader asks (:data:`~swarmrt.bus.messages.SHALLOW_KINDS`:
   estimates read for their header, an agent's ``batches`` whose estimator messages it checks
   one by one as it reads them, :func:`~swarmrt.bus.messages.check_estimator_message`);
5. the message's run id is the key's;
6. an estimate (``est``, ``full_est``) has one row per satellite of the swarm, or per
   satellite of its ``ids`` list when it carries one;
7. the key agrees with the content: the satellite it names, the role that may publish on it
   (:func:`~swarmrt.bus.messages.check_key`, :class:`~swarmrt.bus.messages.KeyMismatch`).

``n_sats`` is the swarm's size when the reader knows it (the roles, the conformance kit);
the recorder and the live view take any swarm (ids up to ``MAX_SAT_ID``), and then the
checks that need the size (3, 6) are not made.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any, NamedTuple

from swarmrt.bus.messages import MessageError, check_key, decode, parse_key

__all__ = ["Received", "receive"]


class Received(NamedTuple):
    """A sample that passed every check."""

    kind: str  # the message kind (``est``, ``clock``, ..., ``alive``)
    sat: int | None  # the satellite the key names (``sat/<i>/...``, ``est/<i>``, ...), else None
    msg: Any = None  # the message (None for a liveliness token)
    role: str | None = None  # a liveliness token's role (``world``, ``agent``, ...)
    alive: bool | None = None  # a liveliness token: declared (True) or gone (False)


_ROWS_KINDS = ("est", "full_est")


def receive(key: str, payload: bytes | bytearray | memoryview | None, run: str | None, *, n_sats: int | None = None,
            shallow: bool | Collection[str] = False, expect: str | None = None, delete: bool = False) -> Received:
    """Open one sample (see the module doc for the checks, in order).

    ``run``: the swarm's run id (None: whichever run the key names, for a recording read back).
    ``n_sats``: the swarm's size, if the reader knows it. ``shallow``: decode shallowly (True), or
    the kinds to decode shallowly (a role's subscriptions: :meth:`swarmrt.node.Node.subscribe`);
    a kind without a shallow reading is always read in full. ``expect``: the kind the reader asked for (a
    query's reply). ``delete``: the sample is a delete (liveliness: the token went)."""
    key = str(key)
    key_run, kind, sat = parse_key(key)
    if run is not None and key_run != run:
        raise MessageError(f"run id {key_run!r} is not this swarm's ({run!r})")
    if expect is not None and kind != expect:
        raise MessageError(f"a {kind} key ({key[:200]}) where a {expect} message was expected")
    if kind == "alive":
        return Received("alive", sat, None, role=key.split("/")[3], alive=not delete)
    if delete:
        raise MessageError("unexpected delete")
    if n_sats is not None and sat is not None and sat >= n_sats:
        raise MessageError(f"unknown satellite {sat} in the key (swarm has 0..{n_sats - 1})")
    if payload is None:
        raise MessageError(f"a {kind} sample without a payload")
    # Every satellite id the message names is checked against the swarm's size there.
    msg = decode(kind, payload, shallow=shallow if isinstance(shallow, bool) else kind in shallow, n_sats=n_sats)
    if msg.run != key_run:
        raise MessageError(f"message run id {msg.run!r} is not this swarm's")
    if n_sats is not None and kind in _ROWS_KINDS:
        rows = len(msg.ids) or n_sats
        if len(msg.q_BI) != 4 * rows:
            raise MessageError(f"an estimate of {len(msg.q_BI) // 4} satellites (this swarm has {n_sats}"
                               + (f", its ids list {rows})" if rows != n_sats else ")"))
    check_key(key, kind, sat, msg)
    return Received(kind, sat, msg)
