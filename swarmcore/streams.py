"""Deterministic random streams keyed by (seed, purpose, keys...).

Every random draw in the project comes from a generator made here, so that arrival
order, process boundaries and which subset of measurements is taken cannot change the
numbers: the same (seed, purpose, step, ...) always yields the same stream.
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["stream", "purpose_code"]


def purpose_code(purpose: str) -> int:
    """A stable 32-bit code for a purpose name (``zlib.crc32``; Python's ``hash`` is salted)."""
    return zlib.crc32(purpose.encode("utf-8"))


def stream(seed: int, purpose: str, *keys: int) -> np.random.Generator:
    """A PCG64 generator for ``(seed, purpose, *keys)`` (keys are non-negative ints)."""
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    ss = np.random.SeedSequence(entropy=int(seed), spawn_key=(purpose_code(purpose), *[int(k) for k in keys]))
    return np.random.Generator(np.random.PCG64(ss))
