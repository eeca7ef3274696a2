"""A Dask scheduler and workers on this machine, as real processes started with Dask's own
commands — for the tests and ``swarm bench cluster``, and what docs/deployment.md's manual steps do
by hand::

    python -m dask scheduler --host 127.0.0.1 --port P --no-dashboard
    python -m dask worker tcp://127.0.0.1:P --nworkers 1 --nthreads 1 --no-nanny --name w0 ...

Each worker is one process with one thread (``--no-nanny``: the process started here *is*
the worker, so killing it kills the worker, and no nanny brings it back). Everything
listens on loopback only. The processes are this process's: each is killed by the kernel
when its parent dies (``PR_SET_PDEATHSIG``), workers also leave by themselves when the
scheduler is gone (``--death-timeout``), and :meth:`LocalDaskProcesses.stop` ends them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from distributed.diagnostics.plugin import WorkerPlugin

from swarm.studies.executor import ALLOWED_FAILURES

__all__ = ["LocalDaskProcesses", "TaskEvents", "TASK_TOPIC", "parse_key", "scheduler_task_count"]

#: the event topic of :class:`TaskEvents`
TASK_TOPIC = "swarm-task"


def _die_with_parent() -> None:  # runs in the child between fork and exec
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


class TaskEvents(WorkerPlugin):
    """A worker plugin that logs an event on topic ``swarm-task`` —
    ``{"key", "name", "state"}`` (the scheduler adds ``worker``, the address) — when a task starts executing (``state: executing``)
    and when it stops (the state it leaves for). A client subscribed to the topic
    (``Client.subscribe_topic``) can wait on a task starting on a given worker instead of
    guessing with a delay (the tests kill a worker that way, mid-task)."""

    name = "swarm-task-events"
    idempotent = True

    def setup(self, worker) -> None:
        self.worker = worker

    def transition(self, key, start, finish, **kwargs) -> None:
        if finish == "executing" or start == "executing":
            self.worker.log_event(TASK_TOPIC, {"key": str(key), "name": str(self.worker.name), "state": str(finish)})


def scheduler_task_count(dask_scheduler) -> int:
    """How many tasks the scheduler holds (for ``Client.run_on_scheduler``)."""
    return len(dask_scheduler.tasks)


def parse_key(key: str) -> tuple[str, str]:
    """(function name, study key) of a task key made by :class:`swarm.studies.executor.DaskCluster`."""
    fn, rest = key.split("-", 1)
    return fn, rest.rsplit("-", 1)[0]


class LocalDaskProcesses:
    """``n_workers`` single-threaded workers and their scheduler on 127.0.0.1.

    ``with LocalDaskProcesses(2) as c: c.address`` — waits (``Client.wait_for_workers``)
    until every worker has joined; logs go to ``<workdir>/<name>.log``."""

    def __init__(self, n_workers: int = 2, workdir: Path | None = None, python: str = sys.executable, timeout_s: float = 120.0,
                 env: dict[str, str] | None = None, nanny: bool = False, worker_args: tuple[str, ...] = ()):
        """``env``: the processes' environment (default: this process's); ``nanny``: workers
        under Dask's nanny, as ``dask worker`` starts them by default; ``worker_args``: more
        arguments for ``dask worker`` (``--preload-nanny swarm.studies.dask_preload``)."""
        self.n_workers = n_workers
        self.base_env = env
        self.nanny = nanny
        self.worker_args = list(worker_args)
        self._tmp = None
        if workdir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="swarm-dask-")
            workdir = Path(self._tmp.name)
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.python = python
        self.timeout_s = timeout_s
        from swarm.supervise.launch import free_port

        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.scheduler: subprocess.Popen | None = None
        self.workers: dict[str, subprocess.Popen] = {}

    def _env(self) -> dict:
        base = os.environ if self.base_env is None else self.base_env
        env = dict(base, PYTHONUNBUFFERED="1", DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=str(ALLOWED_FAILURES))
        if self.base_env is None:
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
                env.setdefault(var, "1")
        return env

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        with open(self.workdir / f"{name}.log", "wb") as logf:
            return subprocess.Popen([self.python, "-m", "dask", *args], stdout=logf, stderr=subprocess.STDOUT,
                                    env=self._env(), cwd=self.workdir, preexec_fn=_die_with_parent)

    def start_worker(self, name: str) -> subprocess.Popen:
        p = self._spawn(name, ["worker", self.address, "--nworkers", "1", "--nthreads", "1", *([] if self.nanny else ["--no-nanny"]),
                               "--name", name, "--host", "127.0.0.1", "--no-dashboard", "--death-timeout", "30",
                               "--local-directory", str(self.workdir / name), *self.worker_args])
        self.workers[name] = p
        return p

    def start(self) -> LocalDaskProcesses:
        from distributed import Client

        self.scheduler = self._spawn("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(self.port), "--no-dashboard"])
        for i in range(self.n_workers):
            self.start_worker(f"w{i}")
        try:
            with Client(self.address, timeout=self.timeout_s, set_as_default=False) as c:
                c.wait_for_workers(self.n_workers, timeout=self.timeout_s)
        except Exception as exc:
            self.stop()
            logs = "\n".join(f"--- {p.name}\n{p.read_text()[-1500:]}" for p in sorted(self.workdir.glob("*.log")))
            raise RuntimeError(f"the local Dask cluster did not come up: {exc}\n{logs}") from None
        return self

    def worker_address(self, name: str) -> str:
        """The address the scheduler knows worker ``name`` by."""
        from distributed import Client

        with Client(self.address, timeout=30, set_as_default=False) as c:
            for addr, w in c.scheduler_info(n_workers=-1)["workers"].items():
                if w.get("name") == name:
                    return addr
        raise KeyError(f"no worker named {name!r} at {self.address}")

    def kill_worker(self, name: str, sig: int = signal.SIGKILL) -> None:
        p = self.workers[name]
        p.send_signal(sig)
        p.wait(30)

    def stop(self) -> None:
        """SIGTERM (a worker closes once its running task returns), SIGKILL after 5 s."""
        procs = [*self.workers.values(), *([self.scheduler] if self.scheduler else [])]
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(15)
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> LocalDaskProcesses:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
