# Before any test imports numpy: one BLAS thread, the project's OpenBLAS kernel family and
# malloc settings, as in every process of the project (swarmrt/tuning.py).
from swarmrt import tuning

tuning.tune_process()


# The long files first, in this order. pytest-xdist's loadfile hands files out in collection
# order, one at a time as a worker frees, so a long file handed out last decides when the
# run ends (measured per file in a cold CI run on 2 cores: test_compose 590 s of tests,
# test_rust_agent 360 s and its cold cargo build, test_conformance 331 s, test_cluster 320 s,
# test_integration_swarm 281 s, test_stall 243 s). The container files come after ten minutes
# or so of other work: scripts/test.sh builds the image in the background from the start, and
# a container test handed out before it is built only waits for it.
_LONG_FIRST = ("test_rust_agent.py", "test_conformance.py", "test_integration_swarm.py", "test_stall.py", "test_report.py",
               "test_run_signals.py", "test_router_faults.py", "test_compose.py", "test_docker_image.py", "test_cluster.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: r for r, name in enumerate(_LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(_LONG_FIRST)))  # stable: the rest keep their order
