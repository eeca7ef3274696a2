"""What every harness of this folder shares: instrument the project's modules for
atheris's coverage, then fuzz one target of :mod:`fuzz.targets` (this folder's targets.py;
the repository root is put on ``sys.path``, so ``fuzz`` is this folder, imported as a package).

A harness is ``python fuzz/fuzz_<x>.py [harness options] [libFuzzer/atheris arguments]``
(corpus folders, ``-runs=N``, ``-max_total_time=S``, ``-timeout=S``...); ``scripts/fuzz.py``
runs them all and reports.
"""

from __future__ import annotations

import importlib
import os
import shlex
import sys
import warnings

import atheris  # type: ignore[import-untyped]  # no types, no stub package (fuzz/ is outside mypy's files)

# Libraries first, uninstrumented (only our modules' branches guide the fuzzer; numba's
# compiled checks must stay plain Python bytecode for numba to compile them).
import numpy  # noqa: F401
import yaml  # noqa: F401
from google.protobuf import message  # noqa: F401

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

NEVER = ["swarmrt.bus.fastcheck", "swarmcore.kernels", "swarmcore.mekf"]  # numba-compiled: left as they are


def fuzz(name: str, argv: list[str], include: tuple[str, ...] = (), own: tuple[str, ...] = (),
         imports: tuple[str, ...] = ()) -> None:
    """Fuzz target ``name`` with atheris; ``include``: more packages to instrument (beyond
    swarmrt, swarm and the targets' own package, fuzz); ``own``: the harness's own options (what libFuzzer must repeat when it
    starts the harness again itself, as ``-merge=1`` and ``-fork`` do); ``imports``: more
    modules the target imports when first called (see below)."""
    with atheris.instrument_imports(include=["swarmrt", "swarm", "fuzz", *include], exclude=NEVER):
        # What the targets import when first called: instrumented too. Only a module
        # imported inside this block is: one the target imports at its first call is plain
        # bytecode, its branches invisible to the fuzzer.
        import swarmrt.netem
        import swarmrt.scenario_files
        import swarmrt.security  # noqa: F401
        from fuzz.targets import target

        for module in imports:
            importlib.import_module(module)

        fn = target(name)
    # numpy's warnings are findings too: an overflowing cast, an invalid value.
    warnings.filterwarnings("error", category=RuntimeWarning)
    # libFuzzer restarts "argv[0] options" through the shell: this interpreter, this script.
    prog = shlex.join([sys.executable, os.path.abspath(sys.argv[0]), *own])
    atheris.Setup([prog, *argv], lambda data: fn(bytes(data)))
    atheris.Fuzz()
