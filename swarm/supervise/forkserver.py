"""Python agents started from one process that has already imported and compiled
everything they need: a fork server, so that n agents do not pay n cold interpreters.

A ``sat_agent`` started cold imports numpy, scipy, numba, zenoh and the project (about
1.4 s of CPU) and compiles its numba kernels, and holds ~100 MB of its own; at n = 100 that
is minutes of start-up on 2 cores and more memory than the machine has. Here the standard
library's ``multiprocessing`` fork server (``forkserver`` start method) is started once per
``swarm run`` with :mod:`swarm.supervise.agent_zygote` preloaded (imports, the process
tuning of :mod:`swarmrt.tuning`, the kernels compiled, the heap frozen for the collector);
each agent is then a ``fork()`` of that server: its start-up is opening its bus session
and asking for its prior, and the pages of the libraries and compiled code stay shared
(their proportional set size, PSS, is split between the agents).

What a forked agent keeps of a started one (:class:`swarm.supervise.launch.LocalSwarm`
treats both alike through :class:`ForkedAgent`'s ``Popen``-like surface):

* its own session and process group (``setsid``): a fault kills only it;
* its log: stdout and stderr to its log file;
* its lifeline: a thread waits on the multiprocessing parent sentinel (readable when the
  supervisor is gone, however it went) and then, as :mod:`swarm.supervise.lifeline` does,
  deletes the run's credentials, SIGTERMs the agent and hard-exits after a grace period;
* its exit status (reported by the fork server, as ``Popen.returncode`` is: negative for a
  signal).

No Zenoh session may exist in the server before it forks (a session's runtime threads do
not survive ``fork``): the preload imports modules only.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

__all__ = ["AgentForkServer", "ForkedAgent"]

PRELOAD = "swarm.supervise.agent_zygote"


def _agent_main(argv: list[str], env: dict[str, str], log_path: str, grace_s: float, remove: tuple[str, ...]) -> None:
    """The forked child: become its own session, log to its file, watch the supervisor,
    run ``python -m sat_agent ARGV`` in this process and exit with its status."""
    os.setsid()
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.close(devnull)
    os.environ.update(env)
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    parent = mp.parent_process()
    if parent is not None:
        sentinel = parent.sentinel

        def watch() -> None:
            from multiprocessing.connection import wait

            wait([sentinel])
            sys.stderr.write(f"forkserver: the supervisor is gone; stopping (hard exit in {grace_s:g} s)\n")
            sys.stderr.flush()
            import shutil

            for path in remove:
                shutil.rmtree(path, ignore_errors=True)
            os.kill(os.getpid(), signal.SIGTERM)
            threading.Event().wait(grace_s)
            os._exit(128 + signal.SIGTERM)

        threading.Thread(target=watch, name="lifeline", daemon=True).start()
    sys.argv = ["sat_agent", *argv]
    from sat_agent.__main__ import main

    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if not isinstance(exc.code, int) and exc.code is not None:
            sys.stderr.write(f"{exc.code}\n")
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(int(code or 0))


class ForkedAgent:
    """A forked agent seen as a ``subprocess.Popen`` (what the supervisor uses of one)."""

    def __init__(self, proc):
        self._p = proc
        self.pid: int = proc.pid

    @property
    def returncode(self) -> int | None:
        return self._p.exitcode

    def poll(self) -> int | None:
        return self._p.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._p.join(timeout)
        if self._p.exitcode is None:
            raise subprocess.TimeoutExpired(f"agent pid {self.pid}", timeout or 0.0)
        return self._p.exitcode

    def send_signal(self, sig: int) -> None:
        if self._p.exitcode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class AgentForkServer:
    """The run's fork server (started on the first :meth:`spawn`)."""

    def __init__(self) -> None:
        self.ctx = mp.get_context("forkserver")
        self.ctx.set_forkserver_preload([PRELOAD])

    def spawn(self, argv: list[str], log_path: Path, env: dict[str, str] | None = None, grace_s: float = 5.0,
              remove_when_orphaned: tuple[str, ...] = ()) -> ForkedAgent:
        p = self.ctx.Process(target=_agent_main, args=(list(argv), dict(env or {}), str(log_path), grace_s, tuple(remove_when_orphaned)),
                             name=f"sat_agent {' '.join(argv[:2])}", daemon=False)
        p.start()
        return ForkedAgent(p)

    def close(self) -> None:
        """Stop the fork server. The standard library keeps one per process for the life of
        the process, so in a long-lived caller (a notebook, a test session, ``swarm.run``
        called twice) it would outlive the run that started it; the run stops it instead.
        ``multiprocessing`` has no public call for it: ``ForkServer._stop`` is what its own
        tests use (present in every Python this project supports, 3.11 on)."""
        from multiprocessing import forkserver

        server = getattr(forkserver, "_forkserver", None)
        if server is not None and getattr(server, "_forkserver_pid", None) is not None:
            server._stop()
