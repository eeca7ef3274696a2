# Before any test imports numpy: one BLAS thread, the project's OpenBLAS kernel family and
# malloc settings, as in every process of the project (swarmrt/tuning.py).
from swarmrt import tuning

tuning.tune_process()
