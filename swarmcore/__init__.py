"""The pure numeric core: quaternions, dynamics, sensors, the cooperative MEKF, graphs,
selection, metrics, scenario model and the in-process simulator. No bus, no files.

The filter's dense algebra is small (12n×12n); multi-threaded BLAS is several times
slower than one thread at these sizes on few cores, so unless the caller has chosen,
BLAS gets one thread (this must happen before numpy is first imported).
"""

import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
