#!/usr/bin/env bash
# `make test` (what CI runs): the house rules (scripts/check.sh), then every test, slow and
# container ones included, on two pytest-xdist workers. The container image builds in the
# background meanwhile (scripts/docker-build.sh, when a Docker daemon answers): cold it is
# ~10 min of mostly I/O, and the container tests' fixtures, which run the same script, would
# otherwise start it late and hold both workers on its lock. They still run it: it waits for
# this build (a machine-wide lock), then finds the image current. The build is this script's:
# it is stopped when the tests end, whatever ends them (and it is in this script's process
# group, so a signal to the group reaches it too).
# Usage: scripts/test.sh [pytest arguments]   (logs of the build: runs/image-build.log)
set -euo pipefail
cd "$(dirname "$0")/.."
build_pid=
stop_build() {
  if [ -n "$build_pid" ] && kill -0 "$build_pid" 2>/dev/null; then
    pkill -TERM -P "$build_pid" 2>/dev/null || true  # docker build's client (the daemon then cancels it)
    kill -TERM "$build_pid" 2>/dev/null || true
    wait "$build_pid" 2>/dev/null || true
  fi
}
trap stop_build EXIT
trap 'exit 143' TERM
trap 'exit 130' INT
if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then
  mkdir -p runs
  scripts/docker-build.sh >runs/image-build.log 2>&1 &
  build_pid=$!
  echo "test: building the image in the background (runs/image-build.log)"
fi
scripts/check.sh
.venv/bin/python -m pytest -q -n 2 --dist loadfile --durations=30 "$@"
