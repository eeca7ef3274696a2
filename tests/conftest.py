# Before any test imports numpy: one BLAS thread, the project's OpenBLAS kernel family and
# malloc settings, as in every process of the project (swarmrt/tuning.py).
from swarmrt import tuning

tuning.tune_process()

import json  # noqa: E402  (after the tuning: nothing here imports numpy)
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

# ------------------------------------------------------------------ the CI's two workers
# `make test` runs `pytest -n 2 --dist loadgroup --no-loadscope-reorder`, with the scheduler
# below: every test belongs to a group, a group runs whole on one worker, and groups are
# handed out in the order of the collection, which the workers sort (longest first). The
# groups:
#   - "docker": every container test, first. Its first test builds the image (cold: 6 min on
#     a quiet machine, ~9 under the other worker's load), and every other container test
#     needs it; spread over both workers, the second sat on the build's lock for up to 15
#     minutes (junit of a cold CI run).
#   - one group per file for the rest (module fixtures run once), longest first (LPT), by the
#     seconds per group in tests/durations.json (from a CI run's junit:
#     scripts/test_durations.py); a group it does not know counts 3 s a test.
# Why a scheduler of our own: xdist's loadgroup puts a test in a group by suffixing its
# node id (item._nodeid), which pytest 9.2 no longer reads (Node.nodeid is str(self._id)):
# xdist_group marks group nothing there, every test is scheduled alone.
DOCKER_GROUP = "docker"
#: The container tests (marked docker), by node id prefix: the scheduler on the controller
#: sees node ids only, not marks; the workers check that every test marked docker is here.
DOCKER_TESTS = ("tests/test_docker_image.py::", "tests/test_compose.py::",
                "tests/test_cluster.py::test_compose_cluster_profile_runs_a_study")
_DURATIONS = Path(__file__).with_name("durations.json")
_DEFAULT_S_PER_TEST = 3.0


def group_of(nodeid: str) -> str:
    """The group of a test (its node id): "docker", or its file's name."""
    if nodeid.startswith(DOCKER_TESTS):
        return DOCKER_GROUP
    return nodeid.split("::", 1)[0].rsplit("/", 1)[-1]


def _grouped(config: pytest.Config) -> bool:
    # On the controller --dist is loadgroup; on a worker xdist has set dist to "no" and
    # loadgroup to True (xdist.remote.setup_config). Without xdist there is no such option.
    return config.getoption("dist", default=None) == "loadgroup" or bool(getattr(config.option, "loadgroup", False))


@pytest.hookimpl(optionalhook=True)  # xdist's hook: unknown when xdist is not loaded
def pytest_xdist_make_scheduler(config, log):
    """(Controller) xdist's scope scheduling, a scope being a group of :func:`group_of`."""
    if config.getoption("dist", default=None) != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid)

    return GroupScheduling(config, log)


@pytest.hookimpl(trylast=True)  # after pytest's own reordering by fixture scope
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """(Workers) The docker group first, then the other groups longest first; within a group
    the order pytest chose."""
    if not _grouped(config):
        return
    stray = [it.nodeid for it in items if it.get_closest_marker("docker") and group_of(it.nodeid) != DOCKER_GROUP]
    if stray:
        raise pytest.UsageError(f"tests marked docker outside tests/conftest.py's DOCKER_TESTS (add them there): {stray}")
    known = json.loads(_DURATIONS.read_text()) if _DURATIONS.is_file() else {}
    counts: dict[str, int] = {}
    for it in items:
        counts[group_of(it.nodeid)] = counts.get(group_of(it.nodeid), 0) + 1
    cost = {g: float(known.get(g, _DEFAULT_S_PER_TEST * n)) for g, n in counts.items()}
    position = {id(it): i for i, it in enumerate(items)}
    items.sort(key=lambda it: (group_of(it.nodeid) != DOCKER_GROUP, -cost[group_of(it.nodeid)], group_of(it.nodeid),
                               position[id(it)]))
