"""Application layer: scenario files, outputs, the ``swarm`` CLI, bus and process roles.

The numeric core lives in :mod:`swarmcore` (pure). Importing it first sets up how every
process of the project does its linear algebra, before numpy loads: one BLAS thread per
process (12n×12n problems run several times slower multi-threaded on two cores), one
OpenBLAS kernel family, malloc keeping the filter's freed arrays (see its ``__init__``).
"""

import swarmcore  # noqa: F401  (before anything imports numpy)

__version__ = "0.1.0"
