"""The committed fuzz corpus (fuzz/corpus/<harness>/: the seeds and every input a fuzzer
found) replayed through each harness's target: nothing but the documented errors, fast.
The seeds are what the project's builders make today (a seed that no longer decodes, or a
missing one, fails here)."""

import json
import os
import subprocess
import sys
import time

import pytest

from fuzz.runner import CORPUS, ROOT, harnesses
from fuzz.targets import TARGETS, seeds
from swarmrt.bus import messages as M

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def test_every_harness_has_a_target_and_a_corpus():
    assert set(harnesses()) == set(TARGETS)
    assert {f"msg_{k}" for k in M.MODELS} <= set(TARGETS)
    for h in harnesses():
        assert any((CORPUS / h).iterdir()), f"no corpus for {h}"


@pytest.mark.parametrize("harness", harnesses())
def test_corpus_replays_clean(harness):
    target = TARGETS[harness]
    files = sorted(p for p in (CORPUS / harness).iterdir() if p.is_file())
    for p in files:
        t0 = time.perf_counter()
        target(p.read_bytes())  # raises on anything but the loader's documented error
        assert time.perf_counter() - t0 < 10, f"{p}: {time.perf_counter() - t0:.1f} s"


def test_committed_seeds_are_what_the_builders_make():
    for harness, items in seeds().items():
        for name, data in items:
            p = CORPUS / harness / name
            assert p.is_file(), f"missing seed {p} (python scripts/fuzz.py --seeds)"
            if not name.endswith(".mcap"):  # recordings: same messages, the compressor's bytes may differ
                assert p.read_bytes() == data, f"{p} is not what the builders make now (python scripts/fuzz.py --seeds)"


@pytest.mark.parametrize("kind", sorted(M.MODELS))
def test_message_seeds_are_valid_on_their_keys(kind):
    from fuzz.targets import receive

    for p in sorted((CORPUS / f"msg_{kind}").glob("valid-*")):
        receive(kind, p.read_bytes())


def test_the_mcap_harness_instruments_what_its_target_imports():
    # atheris instruments only the modules imported while fuzz() sets a harness up. The
    # recording reader, the loader and the mcap library were first imported by mcap_target's
    # first call, after it: plain bytecode, their branches invisible to the fuzzer (181
    # edges covered by the seeds; 642 with them instrumented).
    code = f"""
import importlib, pathlib, sys
from fuzz_mcap import IMPORTS
from _harness import NEVER
from fuzz.targets import mcap_target
for m in IMPORTS:
    importlib.import_module(m)
before = set(sys.modules)
for p in sorted(pathlib.Path({str(CORPUS / "mcap")!r}).iterdir()):
    mcap_target(p.read_bytes())
late = [m for m in set(sys.modules) - before if m.split(".")[0] in ("swarm", "swarmrt", "mcap")
        and not any(m == n or m.startswith(n + ".") for n in NEVER)]
print(sorted(late))
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT / "fuzz", capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", f"imported by mcap_target after the harness's set-up (add them to fuzz_mcap.IMPORTS): {out.stdout}"


def test_scratch_folders_of_gone_fuzzers_are_swept(tmp_path):
    # libFuzzer ends a harness with exit(): no atexit handler of Python's removes its folder.
    from fuzz.targets import _sweep

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    for name in (f"swarm-fuzz-{gone}-abc", f"swarm-fuzz-{os.getpid()}-def", "swarm-fuzz-xyz", "other"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "run.mcap").write_bytes(b"x")
    _sweep(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f"swarm-fuzz-{os.getpid()}-def", "swarm-fuzz-xyz", "other"])


@pytest.mark.slow
def test_a_short_coverage_guided_run_of_every_harness_finds_nothing(tmp_path):
    """The CI's short fuzz run: every atheris harness, 300 executions each, from the
    committed corpus (long runs: scripts/fuzz.py --runs 1000000; docs/testing.md, "Hostile input")."""
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "fuzz.py"), "--runs", "300", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=900)
    rows = json.loads((tmp_path / "fuzz.json").read_text())
    found = [f"{r['harness']}: {r['crashes']} crash(es), artifacts {r['artifacts']}; its log ends:\n"
             + "\n".join((tmp_path / "logs" / f"{r['harness']}.log").read_text(errors="replace").splitlines()[-40:])
             for r in rows if r["crashes"]]
    assert p.returncode == 0, "\n\n".join(found) or (p.stdout[-3000:], p.stderr[-3000:])
    assert sorted(r["harness"] for r in rows) == sorted(harnesses()), rows
    assert all(r["executions"] >= 300 and r["crashes"] == 0 for r in rows), rows
