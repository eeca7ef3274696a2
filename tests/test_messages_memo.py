"""The memo of validated arrays (``swarmrt.bus.messages._Memo``): bounded in entries and in
bytes, so a receiver flooded with the largest messages it accepts holds a bounded amount."""

from __future__ import annotations

import numpy as np

from swarmrt.bus.messages import _Memo


class _Msg:
    """Stands for a decoded message: only its identity matters to the memo."""


def test_a_kept_value_is_given_back_once_for_that_very_message():
    memo = _Memo(size=4, max_bytes=1 << 20)
    m, other = _Msg(), _Msg()
    value = (np.zeros(3), np.ones((2, 4)))
    memo.put(m, value)
    assert memo.take(other) is None
    got = memo.take(m)
    assert got is value
    assert memo.take(m) is None
    assert memo.bytes == 0 and len(memo) == 0


def test_bounded_in_bytes_oldest_first_out():
    a = np.zeros(1000)  # 8,000 bytes, counted twice (the message holds the same numbers)
    memo = _Memo(size=1000, max_bytes=50_000)
    msgs = [_Msg() for _ in range(10)]
    for m in msgs:
        memo.put(m, (a.copy(),))
        assert memo.bytes <= 50_000
    assert len(memo) == 3 and memo.bytes == 48_000
    assert all(memo.take(m) is None for m in msgs[:7])
    assert all(memo.take(m) is not None for m in msgs[7:])
    assert memo.bytes == 0


def test_bounded_in_entries():
    memo = _Memo(size=5, max_bytes=1 << 30)
    msgs = [_Msg() for _ in range(8)]
    for m in msgs:
        memo.put(m, (np.zeros(1),))
    assert len(memo) == 5
    assert memo.take(msgs[0]) is None and memo.take(msgs[-1]) is not None


def test_a_value_over_the_byte_bound_is_not_kept_and_evicts_nothing():
    memo = _Memo(size=10, max_bytes=10_000)
    small, big = _Msg(), _Msg()
    memo.put(small, (np.zeros(10),))
    memo.put(big, (np.zeros(10_000),))
    assert memo.take(big) is None
    assert memo.take(small) is not None


def test_putting_the_same_message_again_replaces_it():
    memo = _Memo(size=10, max_bytes=1 << 20)
    m = _Msg()
    memo.put(m, (np.zeros(10),))
    memo.put(m, (np.zeros(20),))
    assert len(memo) == 1 and memo.bytes == 2 * 20 * 8
    assert memo.take(m)[0].size == 20
