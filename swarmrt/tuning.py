"""Process-wide settings under the numbers, applied explicitly by every entry point.

Importing the core does nothing but define. The settings that decide *which bits* a
process computes, or how fast, are made here, once, first thing in each entry point that
computes numbers (the ``swarm`` CLI, ``import swarm`` for the Python API, every role's
``__main__``, the recorder, the fork server, a Dask worker through
:mod:`swarm.studies.dask_preload`, the test session), and checked where a result must be
bit-equal to another process's (:func:`check_numbers`, run before every study task):

* **One OpenBLAS kernel family.** OpenBLAS picks its kernels by CPU when it is loaded
  (and by ``OPENBLAS_CORETYPE``); Cholesky, solves and dot products from its Haswell
  (AVX2) and SkylakeX (AVX-512) kernels differ in the last bits. A host shell with
  ``OPENBLAS_CORETYPE=Haswell`` and its containers without it gave different numbers from
  step 0. So unless the user chose, every process uses the Haswell kernels, which every
  AVX2+FMA CPU runs. This only works before numpy (or scipy) loads OpenBLAS: a process
  that imported numpy first keeps the kernels its CPU chose, and :func:`check_numbers`
  then refuses to compute, naming the fix.
* **One BLAS thread.** The filter's algebra is small (12n × 12n); multi-threaded BLAS is
  several times slower at these sizes on few cores. Set by environment before numpy
  loads, and through threadpoolctl after.
* **malloc keeps the filter's freed arrays.** At n = 40 the covariance and its
  temporaries are 1-2 MB each: above glibc's initial mmap threshold, so each one was
  mapped, unmapped and its pages faulted in again every step (perf of an agent at n = 40:
  13 % of its CPU samples in page faults, 3 % in munmap). With the thresholds raised
  (mallopt: no library offers this) a 10 s in-process run at n = 40 takes 41,000 page
  faults instead of 420,000 and 14 % less CPU; the peak RSS is unchanged. Arithmetic is
  untouched. Skipped when the user tunes malloc (``GLIBC_TUNABLES``, ``MALLOC_*``), off
  glibc, or with ``SWARM_MALLOC_DEFAULTS=1``.
"""

from __future__ import annotations

import os
import sys

__all__ = ["tune_process", "numbers_environment", "check_numbers", "NumbersEnvironmentError", "PINNED_KERNEL", "WORKER_FIX"]

#: The OpenBLAS kernel family every process of the project uses on an AVX2+FMA CPU.
PINNED_KERNEL = "Haswell"
#: How to start a Dask worker by hand so that it computes the project's numbers.
WORKER_FIX = ("start the worker with `dask worker --preload-nanny swarm.studies.dask_preload ...` "
              "(or export OPENBLAS_CORETYPE=Haswell before starting it)")

_BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_tuned = False


class NumbersEnvironmentError(RuntimeError):
    """This process would not compute the same bits as the project's other processes."""


def _cpu_has_avx2_fma() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return False
    return "avx2" in flags and "fma" in flags


def _blas_loaded() -> bool:
    return "numpy" in sys.modules or "scipy" in sys.modules


def _keep_freed_memory() -> None:
    if os.environ.get("SWARM_MALLOC_DEFAULTS") == "1" or "GLIBC_TUNABLES" in os.environ:
        return
    if any(k.startswith("MALLOC_") for k in os.environ):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 16 << 20)  # M_MMAP_THRESHOLD: blocks below 16 MB come from the heap
        libc.mallopt(-1, 128 << 20)  # M_TRIM_THRESHOLD: keep up to 128 MB free at the heap's top
    except (OSError, AttributeError):
        pass  # not glibc: its allocator keeps its own counsel


def tune_process() -> None:
    """Apply the settings of the module docstring to this process (idempotent). Call it
    first thing, before anything imports numpy; the environment it sets also reaches every
    process this one starts."""
    global _tuned
    if _tuned:
        return
    _tuned = True
    for var in _BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")
    if "OPENBLAS_CORETYPE" not in os.environ and _cpu_has_avx2_fma():
        # An empty value (compose passes the host's, possibly empty) is the user's choice too.
        os.environ["OPENBLAS_CORETYPE"] = PINNED_KERNEL
    if _blas_loaded():
        _limit_threads()
    _keep_freed_memory()


def _limit_threads() -> None:
    n = int(os.environ.get("OPENBLAS_NUM_THREADS") or 1)
    from threadpoolctl import threadpool_limits

    threadpool_limits(n, user_api="blas")


def numbers_environment() -> dict:
    """What decides this process's bits: the BLAS libraries loaded, their kernel family and
    thread count, and the kernel family asked for (``OPENBLAS_CORETYPE``)."""
    libs = []
    if _blas_loaded():
        from threadpoolctl import threadpool_info

        libs = [{"api": i.get("internal_api"), "architecture": i.get("architecture"), "threads": i.get("num_threads"),
                 "prefix": i.get("prefix")} for i in threadpool_info() if i.get("user_api") == "blas"]
    return {"blas": libs, "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE"), "tuned": _tuned}


def check_numbers() -> dict:
    """Refuse to compute with another kernel family than the one this process asked for.

    The kernel is chosen when OpenBLAS loads; a process that imported numpy before
    :func:`tune_process` (a Dask worker started by hand, a notebook that imported numpy
    first) keeps its CPU's choice. Returns :func:`numbers_environment`; raises
    :class:`NumbersEnvironmentError` naming the fix."""
    tune_process()
    import numpy  # noqa: F401  (loads OpenBLAS, if nothing has yet)

    env = numbers_environment()
    want = (env["openblas_coretype"] or "").strip().lower()
    for lib in env["blas"]:
        arch = (lib["architecture"] or "").lower()
        if lib["api"] == "openblas" and want and arch and arch != want:
            raise NumbersEnvironmentError(
                f"this process's OpenBLAS ({lib['prefix']}) runs its {lib['architecture']} kernels, not the project's "
                f"{env['openblas_coretype']}: numpy was loaded before swarm could choose them, so its numbers would differ "
                f"from every other process's in the last bits; {WORKER_FIX}")
    return env
