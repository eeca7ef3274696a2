"""The committed fuzz corpus (fuzz/corpus/<harness>/: the seeds and every input a fuzzer
found) replayed through each harness's target: nothing but the documented errors, fast.
The seeds are what the project's builders make today (a seed that no longer decodes, or a
missing one, fails here)."""

import time

import pytest

from swarm.bench.fuzz import CORPUS, harnesses
from swarm.bench.fuzz_targets import TARGETS, seeds
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
    from swarm.bench.fuzz_targets import receive

    for p in sorted((CORPUS / f"msg_{kind}").glob("valid-*")):
        receive(kind, p.read_bytes())
