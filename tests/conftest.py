import os

# Small dense linear algebra runs fastest single-threaded (see swarm/__init__.py).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import swarmcore  # noqa: E402, F401  (the BLAS kernel family, before numpy loads)
