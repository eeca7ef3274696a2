"""Run the atheris harnesses of ``fuzz/`` and report: per harness the executions, execs/s,
crashes and peak RSS (``scripts/fuzz.py``; JSON too).

Each harness runs as its own process (``python fuzz/fuzz_<x>.py``, libFuzzer's options)
over a scratch corpus folder seeded from the committed one, ``fuzz/corpus/<harness>/``
(what libFuzzer finds interesting goes to the scratch folder, never into the repository).
A crash or hang leaves its input in ``<out>/artifacts/<harness>/``; with ``keep_going``
the harness is started again until its budget is spent.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

__all__ = ["ROOT", "CORPUS", "harnesses", "command", "run_harness", "write_seeds", "keep_found", "HarnessResult"]

ROOT = Path(__file__).resolve().parents[1]
CORPUS = ROOT / "fuzz" / "corpus"
MESSAGE_KINDS = ("claim", "clock", "sensors", "cam", "img", "meas", "batches", "est", "full_est", "select", "fault", "health",
                 "truth", "rx", "links", "rejoin", "recorded")


def harnesses() -> list[str]:
    """Every harness name: ``msg_<kind>`` per message kind, then the file loaders."""
    return [*(f"msg_{k}" for k in MESSAGE_KINDS), "credentials", "scenario", "mcap"]


def command(harness: str) -> list[str]:
    """The command line of a harness (before libFuzzer's arguments)."""
    if harness.startswith("msg_"):
        return [sys.executable, str(ROOT / "fuzz" / "fuzz_messages.py"), "--kind", harness[4:]]
    if harness not in ("credentials", "scenario", "mcap"):
        raise ValueError(f"unknown harness {harness!r} (one of {', '.join(harnesses())})")
    return [sys.executable, str(ROOT / "fuzz" / f"fuzz_{harness}.py")]


def write_seeds(corpus: Path = CORPUS) -> dict[str, int]:
    """(Re)write the seed files of every harness (``valid-*``, the shipped scenarios, two small
    recordings) made by the project's own builders; found inputs (``crash-*``, ...) are kept."""
    from fuzz.targets import seeds

    out = {}
    for harness, items in seeds().items():
        d = corpus / harness
        d.mkdir(parents=True, exist_ok=True)
        for name, data in items:
            (d / name).write_bytes(data)
        out[harness] = len(items)
    return out


@dataclass
class HarnessResult:
    harness: str
    executions: int = 0
    seconds: float = 0.0
    execs_per_s: float = 0.0
    crashes: int = 0
    peak_rss_mb: float = 0.0
    coverage: int = 0  # libFuzzer's cov: (edges of our instrumented modules)
    corpus_size: int = 0
    artifacts: list[str] = field(default_factory=list)
    runs: int = 0  # processes started (more than one after a crash with keep_going)

    def as_dict(self) -> dict:
        return asdict(self)


_STATS = re.compile(r"^#(\d+)\s+\w+\s+cov: (\d+) .*?corp: (\d+)/")
_DONE = re.compile(r"^Done (\d+) runs in (\d+) second")
_ARTIFACT = re.compile(r"(?:Test unit written to|artifact_prefix='.*?'; Test unit written to) (\S+)")


def run_harness(harness: str, out: Path, runs: int | None = None, seconds: float | None = None, timeout_s: int = 10,
                rss_limit_mb: int = 2048, keep_going: bool = False, extra: list[str] | None = None, log=print) -> HarnessResult:
    """Fuzz one harness for ``runs`` executions or ``seconds`` (whichever ends first)."""
    if runs is None and seconds is None:
        raise ValueError("give runs or seconds")
    res = HarnessResult(harness)
    work = out / "corpus" / harness
    arts = out / "artifacts" / harness
    work.mkdir(parents=True, exist_ok=True)
    arts.mkdir(parents=True, exist_ok=True)
    seeds = CORPUS / harness
    logf = out / "logs" / f"{harness}.log"
    logf.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    t_end = None if seconds is None else time.monotonic() + seconds
    left = runs
    with open(logf, "a") as lf:
        while True:
            args = [*command(harness), str(work), *([str(seeds)] if seeds.is_dir() else []),
                    f"-timeout={timeout_s}", f"-rss_limit_mb={rss_limit_mb}", f"-artifact_prefix={arts}/",
                    "-print_final_stats=1", *(extra or [])]
            if left is not None:
                args.append(f"-runs={left}")
            if t_end is not None:
                args.append(f"-max_total_time={max(1, int(t_end - time.monotonic()))}")
            t0 = time.monotonic()
            proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace", env=env,
                                    cwd=str(out))
            execs = 0
            assert proc.stdout is not None
            for line in proc.stdout:
                lf.write(line)
                if m := _STATS.match(line):
                    execs = int(m[1])
                    res.coverage = max(res.coverage, int(m[2]))
                    res.corpus_size = int(m[3])
                elif m := _DONE.match(line):
                    execs = int(m[1])
                elif m := _ARTIFACT.search(line):
                    res.artifacts.append(m[1])
                    res.crashes += 1
                elif line.startswith("stat::number_of_executed_units:"):
                    execs = int(line.split(":")[-1])
            _pid, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            res.runs += 1
            res.seconds += time.monotonic() - t0
            res.executions += execs
            res.peak_rss_mb = max(res.peak_rss_mb, usage.ru_maxrss / 1024)
            if left is not None:
                left -= execs
            if proc.returncode != 0 and not res.artifacts:
                res.crashes += 1  # died without an artifact (killed, out of memory before libFuzzer saw it)
                res.artifacts.append(f"exit {proc.returncode}: see {logf}")
            crashed = proc.returncode != 0
            done = (left is not None and left <= 0) or (t_end is not None and time.monotonic() >= t_end - 1)
            if not crashed or not keep_going or done:
                break
            log(f"{harness}: crash ({res.artifacts[-1]}); going on")
    res.execs_per_s = round(res.executions / res.seconds, 1) if res.seconds else 0.0
    res.seconds = round(res.seconds, 1)
    res.peak_rss_mb = round(res.peak_rss_mb, 1)
    return res


def clean(out: Path) -> None:
    """Forget a previous run's scratch corpus (its artifacts are kept)."""
    shutil.rmtree(out / "corpus", ignore_errors=True)


def keep_found(harness: str, out: Path, max_bytes: int = 4096) -> list[str]:
    """Add to the committed corpus (``found-<sha1>``) the inputs of a run's scratch corpus that
    reach code the committed corpus does not (libFuzzer's ``-merge=1``), up to ``max_bytes`` each:
    the corpus replay in CI then covers what the fuzzers reached."""
    import tempfile

    work = out / "corpus" / harness
    seeds = CORPUS / harness
    with tempfile.TemporaryDirectory() as d:
        merged = Path(d) / "merged"
        shutil.copytree(seeds, merged)
        before = {p.name for p in merged.iterdir()}
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
        subprocess.run([*command(harness), "-merge=1", f"-max_len={max_bytes}", str(merged), str(work)], env=env, cwd=d,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        added = []
        for p in sorted(merged.iterdir()):
            if p.name not in before and p.stat().st_size <= max_bytes:
                shutil.copy(p, seeds / f"found-{p.name}")
                added.append(p.name)
    return added
