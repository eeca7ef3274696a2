"""Run a role so that it ends when the process that started it ends, however that ends.

``python -m swarm.supervise.lifeline --fd N [--grace-s S] MODULE [ARGS...]`` runs ``python -m MODULE
ARGS...`` in this process, after starting a thread that reads file descriptor ``N``: the
read end of a pipe whose write end only the parent (``swarm run``'s supervisor,
:class:`swarm.supervise.launch.LocalSwarm`) holds. The parent never writes to it, so the read blocks
for as long as the parent lives; when the parent dies — SIGTERM, SIGINT, a crash, SIGKILL —
the kernel closes the write end and the read returns EOF. The thread then sends this
process SIGTERM (each role's handler stops it cleanly: the recorder finalises its file)
and, should the role still be here ``grace`` seconds later, ends it with ``os._exit``.

``... --exec PROGRAM [ARGS...]`` runs a program of another language instead (an agent of
``emulator.agent_commands``) as a child in this process's group, passing SIGTERM and SIGINT
on to it and, when the parent is gone, SIGKILLing the group after the grace period.

Why a pipe and not ``prctl(PR_SET_PDEATHSIG)``: the death signal fires when the *thread*
that forked the child exits, not the process (the supervisor can be driven from a worker
thread, and a restart is spawned wherever a fault is executed); setting it needs either a
``preexec_fn`` (not safe in a process that runs Zenoh's threads) or code in every role
plus a ``getppid`` check for the parent that died before the call; it is Linux-only and
its signal (SIGKILL, to be sure) gives the recorder no chance to close its file. The pipe
has none of these holes: the kernel closes it whichever way and from whichever thread
the parent goes, a child that starts after its parent is already gone reads EOF at once,
and it works on any POSIX system. No standard-library or packaged helper does this for
an arbitrary ``python -m`` module, hence these few lines.
"""

from __future__ import annotations

import argparse
import os
import runpy
import shutil
import signal
import sys
import threading

__all__ = ["watch", "main"]


def watch(fd: int, grace_s: float, remove: tuple[str, ...] = (), hard_exit=None) -> threading.Thread:
    """Start the watcher thread on ``fd`` (see the module docstring). ``remove``: paths the
    parent would have deleted at its end (the run's credentials), deleted here when it
    cannot (it was SIGKILLed)."""

    def run() -> None:
        try:
            while os.read(fd, 4096):
                pass  # nobody writes; anything written is ignored
        except OSError:
            pass  # a broken descriptor means the same as EOF: no parent to answer to
        sys.stderr.write(f"lifeline: the parent process is gone; stopping (hard exit in {grace_s:g} s)\n")
        sys.stderr.flush()
        for path in remove:  # every child may try; the first one wins, the others find nothing
            shutil.rmtree(path, ignore_errors=True)
        os.kill(os.getpid(), signal.SIGTERM)
        # A deadline, not a synchronisation: the clean stop above either finishes within it
        # (and the process is gone before this wakes) or is cut short here.
        threading.Event().wait(grace_s)
        if hard_exit is not None:
            hard_exit()
        os._exit(128 + signal.SIGTERM)

    t = threading.Thread(target=run, name="lifeline", daemon=True)
    t.start()
    return t


def _exec(cmd: list[str], fd: int, grace_s: float, remove: tuple[str, ...]) -> int:
    """Run a program of another language (a foreign agent) as this process's child, in
    this process group (a fault that kills the group kills both): SIGTERM and SIGINT are
    passed on to it, and when the parent goes it gets SIGTERM, then SIGKILL with this
    process after ``grace_s``. Returns its exit status."""
    import subprocess

    try:
        child = subprocess.Popen(cmd)
    except OSError as exc:
        sys.stderr.write(f"lifeline: cannot start {cmd[0]!r}: {exc}\n")
        return 127

    def forward(signum, _frame) -> None:
        if child.poll() is None:
            child.send_signal(signum)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    watch(fd, grace_s, remove, hard_exit=lambda: os.killpg(os.getpgid(0), signal.SIGKILL))
    code = child.wait()
    return code if code >= 0 else 128 - code


def main(argv: list[str] | None = None) -> None:
    if argv is None:
        argv = sys.argv[1:]
    if "--exec" in argv:  # lifeline [options] --exec PROGRAM [ARGS...]
        cut = argv.index("--exec")
        q = argparse.ArgumentParser(prog="lifeline --exec")
        q.add_argument("--fd", type=int, required=True)
        q.add_argument("--grace-s", type=float, default=5.0)
        q.add_argument("--remove-when-orphaned", action="append", default=[])
        o = q.parse_args(argv[:cut])
        if len(argv) <= cut + 1:
            q.error("--exec needs a program")
        sys.exit(_exec(argv[cut + 1:], o.fd, o.grace_s, tuple(o.remove_when_orphaned)))
    p = argparse.ArgumentParser(description="run `python -m MODULE ARGS` (or `--exec PROGRAM ARGS`) until the parent that "
                                "holds the pipe's write end goes")
    p.add_argument("--fd", type=int, required=True, help="read end of the parent's lifeline pipe")
    p.add_argument("--grace-s", type=float, default=5.0, help="after the parent is gone, how long a clean stop may take")
    p.add_argument("--remove-when-orphaned", action="append", default=[], metavar="PATH",
                   help="a directory to delete when the parent is gone (repeatable)")
    p.add_argument("module", help="the module to run as __main__, as `python -m MODULE`")
    p.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    a = p.parse_args(argv)
    watch(a.fd, a.grace_s, tuple(a.remove_when_orphaned))
    sys.argv = [a.module, *a.args]
    runpy.run_module(a.module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
