#!/usr/bin/env bash
# The whole test suite on a busy machine (make test-loaded): BUSY processes (default 2) burn a
# core each beside pytest's two workers for the whole run, as on a developer's machine that is
# doing other work. A test that fails here and passes on a quiet machine asserts a race or
# waits on a deadline too tight: fix the test (or the product), do not skip it.
# Each busy process checks its parent every 0.2 s and ends when the parent is gone (this
# script killed, even by SIGKILL), and the trap below ends them on any exit of the script.
set -euo pipefail
cd "$(dirname "$0")/.."
BUSY=${BUSY:-2}
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; }
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
for _ in $(seq "$BUSY"); do
  .venv/bin/python -c '
import os, time
parent = os.getppid()
t = time.monotonic()
while True:
    if time.monotonic() - t > 0.2:
        if os.getppid() != parent:
            raise SystemExit(0)
        t = time.monotonic()
' &
  pids+=("$!")
done
echo "test-loaded: ${#pids[@]} busy processes beside the suite (pids ${pids[*]})"
.venv/bin/python -m pytest -q -n 2 --dist loadgroup --no-loadscope-reorder --durations=30 --junitxml=runs/junit-loaded.xml "$@"
