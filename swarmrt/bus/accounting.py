"""CPU time spent on messages, per process (:func:`counted`, :func:`codec_cpu_ms`): what
``swarm bench run`` sets against the filter's own CPU time. Owns nothing else."""

from __future__ import annotations

import functools
import threading
import time


# -- CPU time spent on messages ---------------------------------------------------------
# Building, encoding, decoding, validating and converting messages, per process: what
# `swarm bench run` sets against the filter's own CPU time. Thread CPU time, counted once
# for nested calls (a conversion that encodes), from any thread (queryables reply on
# Zenoh's threads).
class _Tally(threading.local):
    """Per thread: whether a counted call is under way, and the nanoseconds counted
    (each thread adds to its own cell; :func:`codec_cpu_ms` sums them: no lock per call)."""

    def __init__(self):
        self.busy = False
        self.cell = [0]
        with _cells_lock:
            _cells.append(self.cell)


_cells: list[list[int]] = []
_cells_lock = threading.Lock()
_tally = _Tally()


def counted(fn):
    """Add the thread CPU time of ``fn`` to the process's message-handling total."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        t = _tally
        if t.busy:
            return fn(*args, **kwargs)
        t.busy = True
        t0 = time.thread_time_ns()
        try:
            return fn(*args, **kwargs)
        finally:
            t.cell[0] += time.thread_time_ns() - t0
            t.busy = False

    return wrapper


def codec_cpu_ms(reset: bool = True) -> float:
    """CPU time (ms) this process spent on messages since the last reset."""
    with _cells_lock:
        ns = 0
        for c in _cells:
            v = c[0]
            ns += v
            if reset:
                c[0] -= v  # a concurrent add on another thread is kept, not lost
    return ns / 1e6
