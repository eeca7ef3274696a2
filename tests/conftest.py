# Before any test imports numpy: one BLAS thread, the project's OpenBLAS kernel family and
# malloc settings, as in every process of the project (see swarmcore/__init__.py).
import swarmcore  # noqa: F401
