"""Where a study's runs execute: a local process pool (the default) or a Dask cluster.

A *study* (``swarm mc``, ``swarm compare``, ``swarm characterize``) is a set of independent
tasks, each a picklable top-level function applied to plain values (a scenario as a dict, a
seed, a strategy name, …) that returns plain values. Both backends behind :class:`Executor`
run the same function on the same arguments, and every random draw inside is keyed by the
seed (:func:`swarmcore.streams.stream`), so a task's result does not depend on which process
or host ran it, nor in which order tasks finished: the same seed gives the same numbers on
the local pool and on any Dask worker running the same code.

* :class:`LocalPool` — ``concurrent.futures.ProcessPoolExecutor`` (spawned processes, each
  killed with its parent), or this process alone for ``workers=1``. No Dask process needed.
* :class:`DaskCluster` — a ``distributed.Client`` connected to a running scheduler
  (``dask scheduler`` / ``dask worker``, see docs/deployment.md, "Studies on a cluster").

:func:`run_study` adds what both share:

* results stream to disk as each task finishes (:class:`ResultStore`, ``results.jsonl``);
* ``resume`` reuses every stored result whose task is unchanged — same function, same
  arguments, compared by fingerprint — and says how many it skipped;
* a task that raises is reported by key with its error; the rest of the study completes.

Failure semantics on Dask:

* a worker that dies mid-task (SIGKILL, out of memory, a lost host) costs only that task:
  the scheduler runs it again on another worker. Only a task that was running on more than
  ``distributed.scheduler.allowed-failures`` dying workers (the project sets 3, Dask's
  default: a fourth death in a row means the task itself is killing them, e.g. by
  exhausting memory) fails, as ``KilledWorker``, and is reported like an exception;
* a task that raises is not retried (``retries=0``): the same arguments raise again (every
  draw is keyed by seed), so a retry would only cost time.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
import traceback
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from concurrent.futures import Future, ProcessPoolExecutor

__all__ = [
    "Outcome",
    "Executor",
    "LocalPool",
    "DaskCluster",
    "ClusterError",
    "connect",
    "open_executor",
    "ResultStore",
    "StudyResult",
    "StudyMapper",
    "run_study",
    "fingerprint",
    "noop",
]

#: What a Dask scheduler for swarm studies should be started with (compose.yaml, docs/deployment.md).
ALLOWED_FAILURES = 3


class ClusterError(RuntimeError):
    """The Dask scheduler cannot be used (unreachable, malformed address)."""


@dataclass(frozen=True)
class Outcome:
    """One finished task: its key and either its result or its error (one line or a few)."""

    key: str
    result: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _describe(exc: BaseException) -> str:
    """``Type: message`` plus the innermost frame of the task's own code when known."""
    text = f"{type(exc).__name__}: {exc}".strip()
    tb = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ is not None else []
    if tb:
        f = tb[-1]
        text += f"\n[raised at {Path(f.filename).name}:{f.lineno} in {f.name}]"
    return text


def checked(fn: Callable, *args):
    """Run one study task after checking that this process computes the project's numbers
    (:func:`swarmrt.tuning.check_numbers`: the pinned OpenBLAS kernels, one BLAS thread).
    A worker that cannot — a Dask worker started by hand without the project's preload
    imports numpy before our code runs — refuses every task with a message that names
    the fix, instead of returning numbers that differ in the last bits."""
    from swarmrt.tuning import check_numbers

    check_numbers()
    return fn(*args)


def noop(x):
    """A task that does nothing: the round trip of the scheduling machinery alone."""
    return x


class Executor(ABC):
    """Submit tasks by key; get every one back once, in the order they finish."""

    #: human-readable description, e.g. "local pool (2 processes)"
    description: str = ""

    @abstractmethod
    def submit(self, key: str, fn: Callable, *args) -> None: ...

    @abstractmethod
    def as_completed(self) -> Iterator[Outcome]:
        """Every task submitted so far (and not yet returned), as each finishes."""

    def close(self) -> None:  # noqa: B027 - optional hook: most executors hold nothing to release
        """Release what the executor holds (nothing, unless a subclass says otherwise)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _die_with_parent(parent_pid: int) -> None:
    """Pool-process initializer: the kernel kills this process when its parent dies
    (``PR_SET_PDEATHSIG``), so a study killed with SIGKILL leaves no orphaned workers."""
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: nothing to set
        return
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


class LocalPool(Executor):
    """``workers`` spawned processes (``workers=1``: this process, one task at a time)."""

    def __init__(self, workers: int = 2):
        self.workers = max(1, int(workers))
        self.description = "this process" if self.workers == 1 else f"local pool ({self.workers} processes)"
        self._pending: dict[Future, str] = {}
        self._queue: list[tuple[str, Callable, tuple]] = []
        self._pool: ProcessPoolExecutor | None = None  # started at the first task (workers > 1)

    def submit(self, key: str, fn: Callable, *args) -> None:
        if self.workers == 1:
            self._queue.append((key, fn, args))
            return
        if self._pool is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                             initializer=_die_with_parent, initargs=(os.getpid(),))
        self._pending[self._pool.submit(checked, fn, *args)] = key

    def as_completed(self) -> Iterator[Outcome]:
        while self._queue:
            key, fn, args = self._queue.pop(0)
            try:
                yield Outcome(key, checked(fn, *args))
            except Exception as exc:  # reported by key; the study goes on
                yield Outcome(key, error=_describe(exc))
        if not self._pending:
            return
        from concurrent.futures import as_completed
        from concurrent.futures.process import BrokenProcessPool

        for fut in as_completed(list(self._pending)):
            key = self._pending.pop(fut)
            err = fut.exception()
            if err is None:
                yield Outcome(key, fut.result())
            elif isinstance(err, BrokenProcessPool):
                yield Outcome(key, error=f"a pool process died while this task was pending ({err}); run again with --resume")
            else:
                yield Outcome(key, error=_describe(err))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def connect(address: str, timeout_s: float = 10.0, **kw):
    """A ``distributed.Client`` for the scheduler at ``address``, trying until ``timeout_s``.

    Dask retries a refused connection by itself, but not one that is accepted and then
    closed before the handshake — what a published container port does while the
    scheduler inside is still starting (``docker compose up -d`` has just returned) — so
    such attempts are repeated here, a quarter second apart."""
    try:
        from distributed import Client
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise ClusterError(f"--cluster needs dask[distributed] ({exc})") from None
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while True:
        try:
            return Client(address, timeout=max(1.0, deadline - time.monotonic()), set_as_default=False, **kw)
        except ValueError as exc:  # a malformed address
            raise ClusterError(f"--cluster {address!r}: {exc}") from None
        except (OSError, TimeoutError) as exc:
            if time.monotonic() >= deadline:
                raise ClusterError(f"cannot reach the Dask scheduler at {address!r} within {timeout_s:g} s: {exc}") from None
            pause.wait(0.25)


class DaskCluster(Executor):
    """Tasks go to the Dask scheduler at ``address`` (``tcp://host:8786``).

    Every task gets a unique key (``<module>.<function>-<study key>-<token>``) so that two studies on
    one cluster, or a resumed study, never share results by accident; ``pure=False`` because
    some results carry wall-clock timings."""

    def __init__(self, address: str, *, connect_timeout_s: float = 10.0, name: str = "swarm"):
        self.address = address
        self._token = uuid.uuid4().hex[:8]
        self.client = connect(address, connect_timeout_s, name=f"{name}-{self._token}")
        self._pending: dict = {}
        info = self.client.scheduler_info(n_workers=-1)
        self.workers = len(info.get("workers", {}))
        self.threads = sum(w.get("nthreads", 0) for w in info.get("workers", {}).values())
        self.description = f"Dask scheduler {address} ({self.workers} workers, {self.threads} threads)"
        if not self.workers:
            self.description += "; no worker yet: the runs wait for one"

    def submit(self, key: str, fn: Callable, *args) -> None:
        name = f"{fn.__module__.rsplit('.', 1)[-1]}.{fn.__name__}"  # e.g. mc.run_one
        fut = self.client.submit(checked, fn, *args, key=f"{name}-{key}-{self._token}", pure=False, retries=0)
        self._pending[fut] = key

    def as_completed(self) -> Iterator[Outcome]:
        if not self._pending:
            return
        from distributed import as_completed

        for fut in as_completed(list(self._pending), loop=self.client.loop):
            key = self._pending.pop(fut)
            if fut.status == "finished":
                yield Outcome(key, fut.result())
            elif fut.status == "error":
                exc = fut.exception()
                exc.__traceback__ = fut.traceback()
                yield Outcome(key, error=_describe(exc))
            else:  # cancelled: the scheduler lost it (restarted, or this client was dropped)
                yield Outcome(key, error=f"task {fut.status} by the Dask scheduler; run again with --resume")
            fut.release()

    def close(self) -> None:
        for fut in self._pending:
            fut.cancel()
        self._pending.clear()
        self.client.close(timeout=10)


def open_executor(workers: int = 2, cluster: str | None = None) -> Executor:
    """The local pool of ``workers`` processes, or the Dask scheduler at ``cluster``."""
    return DaskCluster(cluster) if cluster else LocalPool(workers)


# --- results on disk -------------------------------------------------------------------


def _plain(obj):
    tolist = getattr(obj, "tolist", None)  # numpy arrays and scalars
    if tolist is not None:
        return tolist()
    raise TypeError(f"{type(obj).__name__} is not a plain value")


def fingerprint(fn: Callable, args: tuple) -> str:
    """SHA-256 of the function's qualified name and its arguments as canonical JSON: the
    identity of a task. A stored result is reused only for the same fingerprint."""
    doc = json.dumps([f"{fn.__module__}.{fn.__qualname__}", list(args)], sort_keys=True, default=_plain, allow_nan=True)
    return hashlib.sha256(doc.encode()).hexdigest()


class ResultStore:
    """``results.jsonl``: one line per finished task, ``{"key", "fp", "result"}``, written
    (flushed and fsync'ed) the moment the task's result arrives.

    Why by hand and not a database: the store must survive SIGKILL at any instant and stay
    readable with ``jq``; appending one line per result does both, and the only damage a kill
    can do is a torn last line, which :meth:`__init__` cuts off before appending again.

    ``resume=False`` starts afresh (the old file is replaced); ``resume=True`` keeps every
    complete line (the last one wins when a key appears twice)."""

    def __init__(self, path: Path, resume: bool = False):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.stored: dict[str, tuple[str, Any]] = {}
        self.discarded = 0
        if self.path.exists():
            raw = self.path.read_bytes()
            if not resume:
                self.discarded = raw.count(b"\n")
                self.path.write_bytes(b"")
            else:
                end = raw.rfind(b"\n") + 1
                if end < len(raw):  # torn last line (killed mid-write): drop it
                    with open(self.path, "r+b") as f:
                        f.truncate(end)
                for line in raw[:end].splitlines():
                    try:
                        rec = json.loads(line)
                        self.stored[rec["key"]] = (rec["fp"], rec["result"])
                    except (ValueError, KeyError, TypeError):
                        continue
        self._f = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - held open for appends until close()

    def get(self, key: str, fp: str):
        """(True, result) when a result for this key and fingerprint is stored."""
        hit = self.stored.get(key)
        return (True, hit[1]) if hit is not None and hit[0] == fp else (False, None)

    def add(self, key: str, fp: str, result) -> None:
        self._f.write(json.dumps({"key": key, "fp": fp, "result": result}, default=_plain, allow_nan=True) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())
        self.stored[key] = (fp, result)

    def close(self) -> None:
        self._f.close()


@dataclass
class StudyResult:
    """``results`` by key (reused and new), ``errors`` by key, and the counts."""

    results: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)
    skipped: int = 0
    ran: int = 0
    wall_s: float = 0.0


def run_study(
    executor: Executor,
    fn: Callable,
    jobs: Mapping[str, tuple],
    *,
    store: ResultStore | None = None,
    on_result: Callable[[str, Any], Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    log: Callable[[str], None] | None = None,
    noun: str = "runs",
) -> StudyResult:
    """Run ``fn(*jobs[key])`` for every key not already in ``store``.

    ``on_result(key, result)`` runs in this process as each result arrives (e.g. to write a
    run folder) and returns what to keep and store (default: the result itself); it runs
    before the result is stored, so a stored result always has its files on disk.
    ``progress(done, total)`` counts reused results as done."""
    out = StudyResult()
    total = len(jobs)
    fps = {key: fingerprint(fn, args) for key, args in jobs.items()}
    todo = []
    for key in jobs:
        hit, res = store.get(key, fps[key]) if store is not None else (False, None)
        if hit:
            out.results[key] = res
        else:
            todo.append(key)
    out.skipped = total - len(todo)
    if log is not None:
        if store is not None and store.discarded:
            log(f"starting afresh: {store.discarded} results already in {store.path} are replaced (--resume keeps them)")
        if out.skipped and store is not None:  # only a store has results to skip
            log(f"resume: {out.skipped} of {total} {noun} already done in {store.path}; skipped; {len(todo)} to run")
        log(f"{len(todo)} {noun} on {executor.description}")
    done = out.skipped
    if progress is not None:
        progress(done, total)
    t0 = time.perf_counter()
    for key in todo:
        executor.submit(key, fn, *jobs[key])
    for oc in executor.as_completed():
        if oc.ok:
            kept = on_result(oc.key, oc.result) if on_result is not None else oc.result
            if store is not None:
                store.add(oc.key, fps[oc.key], kept)
            out.results[oc.key] = kept
            out.ran += 1
        else:
            out.errors[oc.key] = oc.error
        done += 1
        if progress is not None:
            progress(done, total)
    out.wall_s = time.perf_counter() - t0
    return out


class StudyMapper:
    """An injected map for library code that cuts its work into cells itself
    (:func:`swarmvision.characterize.characterize` takes ``mapper(fn, jobs, progress)``):
    runs them as a study on ``executor`` with ``store``; the :class:`StudyResult` of the
    last call (errors, skipped) is kept in ``self.result``."""

    def __init__(self, executor: Executor, store: ResultStore | None = None, log: Callable[[str], None] | None = None,
                 noun: str = "cells"):
        self.executor, self.store, self.log, self.noun = executor, store, log, noun
        self.result: StudyResult | None = None

    def __call__(self, fn: Callable, jobs: Mapping[str, tuple], progress: Callable[[int, int], None] | None = None) -> dict:
        self.result = run_study(self.executor, fn, jobs, store=self.store, progress=progress, log=self.log, noun=self.noun)
        return self.result.results
