"""Application layer: scenario files, outputs, the ``swarm`` CLI, bus and process roles.

The numeric core lives in :mod:`swarmcore` (pure). Small dense linear algebra (12n×12n)
runs fastest single-threaded; multi-threaded BLAS on two cores is several times slower
at these sizes, so unless the user says otherwise, BLAS gets one thread per process.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import swarmcore  # noqa: E402, F401  (pins the BLAS kernels before numpy loads: see swarmcore._pin_blas_kernel)

__version__ = "0.1.0"
