"""The recording survives SIGKILL at any instant, and compacts into a standard MCAP."""

import os
import signal
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
from mcap.reader import make_reader

from swarm.record.mcaplog import CheckpointWriter, compact, iter_messages

WRITER = textwrap.dedent(
    """
    import sys, json
    from swarm.record.mcaplog import CheckpointWriter
    w = CheckpointWriter(sys.argv[1])
    sid = w.schema("s", "jsonschema", b"{}")
    cid = w.channel("swarm/t/x", sid)
    i = 0
    while True:
        for _ in range(50):
            w.add(cid, json.dumps({"i": i, "pad": "x" * (i % 700)}).encode(), i, i)
            i += 1
        w.flush()
        print(i, flush=True)
    """
)


def _read(path):
    with open(path, "rb") as f:
        return [int(__import__("json").loads(m.data)["i"]) for _s, _c, m in make_reader(f).iter_messages()]


def test_readable_after_every_flush_and_compact(tmp_path):
    p = tmp_path / "a.mcap"
    w = CheckpointWriter(p)
    cid = w.channel("swarm/t/x", w.schema("s", "jsonschema", b"{}"))
    assert _read(p) == []  # valid from the first instant
    for i in range(1000):
        w.add(cid, b'{"i": %d}' % i, i)
        if i % 97 == 0:
            w.flush()
            assert _read(p) == list(range(i + 1))
    w.close(finalize=True)
    assert _read(p) == list(range(1000))
    with open(p, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None and summary.statistics.message_count == 1000 and summary.chunk_indexes
    compact(p)  # idempotent
    assert _read(p) == list(range(1000))


@pytest.mark.slow
def test_sigkill_at_random_instants_leaves_a_readable_file(tmp_path):
    rng = np.random.default_rng(7)
    for trial in range(12):
        p = tmp_path / f"k{trial}.mcap"
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(p)], stdout=subprocess.PIPE, text=True)
        flushes: list[int] = []  # completed flushes reported by the writer (read on a thread)
        first = threading.Event()

        def read(proc=proc, flushes=flushes, first=first):
            for x in proc.stdout:
                flushes.append(int(x))
                first.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        # Wait until the writer is writing (its start-up time depends on the machine's load),
        # then kill it at a random instant (not a synchronisation: any instant must be safe).
        assert first.wait(60), "the writer never flushed"
        threading.Event().wait(rng.uniform(0.0, 0.5))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        reader.join(10)
        flushed = flushes[-1]
        got = _read(p)
        assert got[:flushed] == list(range(flushed)), f"trial {trial}: lost flushed messages"
        assert len(got) >= flushed and got == list(range(len(got)))
        assert sum(1 for _ in iter_messages(p)) == len(got)
