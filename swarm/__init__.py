"""swarm-coloc's application: the Python API, the ``swarm`` CLI, supervision of a
distributed run (``supervise``), recording (``record``), the live view (``live``), studies
(``studies``), benchmarks (``bench``) and the in-process simulation of a scenario
(``simulation``).

The API (:mod:`swarm.api`; every name in ``__all__`` is stable)::

    import swarm
    sc = swarm.load_scenario("scenarios/demo.yaml", duration_s=20)
    res = swarm.simulate(sc)           # in-process; res.errors, res.nees, ... are DataFrames
    res = swarm.run(sc)                # distributed (real processes), read from the recording
    mc = swarm.monte_carlo(sc, runs=10)
    cmp = swarm.compare(sc, estimators=["full", "ci"], runs=5)

``import swarm`` is an entry point of the project like the CLI: it applies the
process-wide numeric settings (:func:`swarmrt.tuning.tune_process`) before anything
loads numpy, so that a notebook computes the same bits as ``swarm sim``. It loads nothing
else: the API's names are imported when first used.
"""

from typing import TYPE_CHECKING

from swarmrt import tuning as _tuning

_tuning.tune_process()

__version__ = "0.1.0"

__all__ = ["load_scenario", "simulate", "run", "monte_carlo", "compare", "Result", "MonteCarlo", "Comparison", "Scenario",
           "__version__"]

if TYPE_CHECKING:
    from swarm.api import Comparison, MonteCarlo, Result, Scenario, compare, load_scenario, monte_carlo, run, simulate

_LAZY = frozenset(__all__) - {"__version__"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module("swarm.api"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'swarm' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
