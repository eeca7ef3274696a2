# One command to set up and run the default swarm; one to set up and run the tests.
.PHONY: setup demo test test-fast bench image clean

setup:
	scripts/setup.sh

demo: setup
	.venv/bin/swarm sim scenarios/demo.yaml --out runs/demo

# Every test, slow and container ones included (what CI runs).
test: setup
	.venv/bin/python -m pytest -q

# Skip the slow, rendering and container tests while iterating.
test-fast: setup
	.venv/bin/python -m pytest -q -m "not slow and not docker"

bench: setup
	.venv/bin/swarm bench filter --sats 3,6,12,25,50,100 --graph complete --out runs/bench/filter.json

# The container image (makes the local base image and the wheelhouse when needed).
image:
	scripts/docker-build.sh

clean:
	rm -rf runs .pytest_cache
