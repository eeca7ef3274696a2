"""What the agents' fork server loads once (:mod:`swarm.supervise.forkserver`): the process
tuning, every module a ``sat_agent`` imports, its compiled kernels; then the heap is
frozen for the garbage collector so that the forked agents' collections skip (and do not
write to, which would unshare) these pages. Imports only: no bus session exists here."""

from swarmrt import tuning

tuning.tune_process()

import numpy  # noqa: E402, F401
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402, F401  (ci's ω)
import zenoh  # noqa: E402, F401  (the module only: sessions are opened after the fork)

import sat_agent.__main__  # noqa: E402
import sat_agent.node  # noqa: E402, F401
import swarmcore.estimators  # noqa: E402, F401
import swarmrt.estimators  # noqa: E402, F401
from swarmcore import kernels  # noqa: E402
from swarmrt.node import freeze_startup_objects  # noqa: E402

kernels.warm_up()
freeze_startup_objects()
