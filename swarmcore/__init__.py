"""The pure numeric core: quaternions, dynamics, sensors, the cooperative MEKF, graphs,
selection, metrics, scenario model and the in-process simulator. No bus, no files.

The filter's dense algebra is small (12n×12n); multi-threaded BLAS is several times
slower than one thread at these sizes on few cores, so unless the caller has chosen,
BLAS gets one thread (this must happen before numpy is first imported).
"""

import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")


def _pin_blas_kernel() -> None:
    """One OpenBLAS kernel family wherever the numbers are computed.

    OpenBLAS picks its kernels by CPU (and by ``OPENBLAS_CORETYPE``); Cholesky, solves and
    dot products from its Haswell (AVX2) and SkylakeX (AVX-512) kernels differ in the last
    bits. A host shell that had ``OPENBLAS_CORETYPE=Haswell`` set ran ``swarm sim`` with one,
    its containers (without that variable) with the other, and their numbers differed from
    step 0 on. So unless the user chose, every process of the project uses the Haswell
    kernels, which every AVX2+FMA CPU runs: the same bits on a host, in its containers and
    on machines with or without AVX-512. Must run before numpy is first imported.
    """
    if _os.environ.get("OPENBLAS_CORETYPE"):  # the user's choice (compose passes the host's, or "")
        return
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return
    if "avx2" in flags and "fma" in flags:
        _os.environ["OPENBLAS_CORETYPE"] = "Haswell"


_pin_blas_kernel()


def _keep_freed_memory() -> None:
    """Let glibc's malloc keep the filter's freed arrays for reuse instead of handing them
    back to the kernel after every step.

    At n = 40 the filter's covariance and its temporaries are 1-2 MB each: above glibc's
    initial mmap threshold, so each one was mapped, unmapped and its pages faulted in again
    every step (perf of an agent at n = 40: 13 % of its CPU samples in page faults, 3 % in
    munmap). With the thresholds raised (mallopt: no library offers this), a 10 s
    in-process run at n = 40 takes 41,000 page faults instead of 420,000 and 14 % less CPU;
    the peak RSS is unchanged.
    Arithmetic is untouched. Skipped when the user tunes malloc themselves
    (``GLIBC_TUNABLES``, ``MALLOC_*``), off glibc, or with ``SWARM_MALLOC_DEFAULTS=1``.
    """
    if _os.environ.get("SWARM_MALLOC_DEFAULTS") == "1" or "GLIBC_TUNABLES" in _os.environ:
        return
    if any(k.startswith("MALLOC_") for k in _os.environ):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 16 << 20)  # M_MMAP_THRESHOLD: blocks below 16 MB come from the heap
        libc.mallopt(-1, 128 << 20)  # M_TRIM_THRESHOLD: keep up to 128 MB free at the heap's top
    except (OSError, AttributeError):
        pass  # not glibc: its allocator keeps its own counsel


_keep_freed_memory()
