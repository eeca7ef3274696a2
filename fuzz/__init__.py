"""Fuzzing: what ships no further than the tests (not in the wheel, not in the image; no module
of the application imports it). Importable as the package ``fuzz`` from the repository root.

- :mod:`fuzz.targets` — the fuzz targets: what each harness feeds hostile bytes to (a bus
  message through :func:`swarmrt.bus.receive.receive` and the role's conversions, a scenario
  file, a credential or keys file, an MCAP recording) and the seed inputs they start from;
  also used by ``tests/test_fuzz_*.py`` and ``tests/test_receive_path.py``.
- :mod:`fuzz.runner` — runs the harnesses as processes and reports (``scripts/fuzz.py``).
- ``_harness.py``, ``fuzz_*.py`` — the atheris harnesses, run as scripts
  (``python fuzz/fuzz_messages.py --kind est ...``); ``corpus/`` — their committed corpus.
"""
