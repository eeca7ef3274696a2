"""Dask preload that makes a hand-started worker compute the project's numbers.

``dask worker tcp://HOST:8786 --preload-nanny swarm.studies.dask_preload ...``: the nanny
imports this module before it starts its worker processes, which inherit the environment
it sets (:func:`swarmrt.tuning.tune_process`: the pinned OpenBLAS kernel family, one BLAS
thread), so that OpenBLAS loads in each worker with the kernels every other process of
the project uses. (``--preload`` alone runs in the worker after Dask has imported numpy:
too late for the kernels; such a worker refuses every task, naming this fix.)
"""

from swarmrt import tuning

tuning.tune_process()


def dask_setup(service) -> None:
    """Dask's preload hook: nothing more to do once the module is imported."""
