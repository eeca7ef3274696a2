# One command to set up and run the default swarm; one to set up and run the tests.
.PHONY: setup demo sim test test-fast test-loaded check bench soak soak-twice image rust-agent clean

SWARM ?= .venv/bin/swarm
DEMO_OUT ?= runs/demo

setup:
	scripts/setup.sh

# The distributed swarm, no Docker: a Zenoh router, the recorder, the world, the selector
# and one process per satellite on loopback, with scheduled faults (scenarios/demo-faults.yaml:
# the default demo.yaml swarm plus a selector, a camera off, an agent killed and restarted);
# then the summary and fault tables, and the report page.
demo: setup
	rm -rf $(DEMO_OUT)
	$(SWARM) run scenarios/demo-faults.yaml --out $(DEMO_OUT)
	$(SWARM) report $(DEMO_OUT)
	@echo "demo: open $(DEMO_OUT)/report/report.html (recording $(DEMO_OUT)/run.mcap, summary $(DEMO_OUT)/summary.json, logs $(DEMO_OUT)/logs/)"

# The same default swarm in one process (every filter in-process, no bus, no faults).
sim: setup
	$(SWARM) sim scenarios/demo.yaml --out runs/sim

# The house rules as tools (import contracts, ruff, mypy; scripts/check.sh), then every
# test, slow and container ones included (what CI runs), on two workers: the container tests
# as one group on one worker (its first test builds the image), the other files whole and
# longest first (tests/conftest.py; tests/durations.json, refreshed from runs/junit.xml by
# scripts/test_durations.py).
test: setup
	scripts/check.sh
	.venv/bin/python -m pytest -q -n 2 --dist loadgroup --no-loadscope-reorder --durations=30 --junitxml=runs/junit.xml

# The same suite with two busy processes beside it (scripts/test-loaded.sh; BUSY=n for more):
# the periodic check that no test asserts a race or waits on a deadline only a quiet machine meets.
test-loaded: setup
	scripts/check.sh
	scripts/test-loaded.sh

# Skip the slow, rendering and container tests while iterating.
test-fast: setup
	scripts/check.sh
	.venv/bin/python -m pytest -q -n 2 --dist loadgroup --no-loadscope-reorder -m "not slow and not docker"

# Only the house rules: import contracts, the linter and the type checker.
check: setup
	scripts/check.sh

bench: setup
	.venv/bin/swarm bench filter --sats 3,6,12,25,50,100 --graph complete --out runs/bench/filter.json

# The chaos soak: 200 fault episodes of every kind a local run has (agents killed, stopped
# and restarted, cameras off, dropped messages, the selector killed, router restarts, one of
# two meshed routers killed and restarted, stalls of every role, dead, slow and lossy links
# and satellites cut off) over 1800 simulated seconds of the demo swarm at n = 10 with a
# greedy selector and the radio's link model on, every invariant checked (docs/faults-and-chaos.md,
# "Chaos campaigns"); runs/soak/chaos.json.
SOAK_FAULTS ?= 200
SOAK_DURATION ?= 1800
SOAK_SATS ?= 10
soak: setup
	.venv/bin/swarm chaos scenarios/demo.yaml --faults $(SOAK_FAULTS) --duration $(SOAK_DURATION) --set n_sats=$(SOAK_SATS) \
		--set selection.strategy=greedy --set selection.budget=20 \
		--set links.enabled=true --set links.latency.speed_of_light=false \
		--routers 2 --seed 1 --out runs/soak

# The repeat benchmark (issue 35): `swarm chaos --twice` over TWICE_SEEDS, 40 faults of every
# kind a local run has (stalls of every role, link faults, failovers) on the default swarm with
# a greedy selector and the link model on; every invariant of both runs and whether their numbers
# and recordings are equal, one table: runs/soak/twice/twice.json (scripts/twice_soak.py).
TWICE_SEEDS ?= 1-20
TWICE_JOBS ?= 2
soak-twice: setup
	.venv/bin/python scripts/twice_soak.py --seeds $(TWICE_SEEDS) --faults 40 --duration 40 --jobs $(TWICE_JOBS) --out runs/soak/twice

# The container image (makes the local base image and the wheelhouse when needed).
image:
	scripts/docker-build.sh

# The Rust agent (participants/rust-agent), release build, for compose.rust.yaml (needs cargo and protoc).
rust-agent:
	cd participants/rust-agent && cargo build --release --locked --target-dir ../target

clean:
	rm -rf runs .pytest_cache
