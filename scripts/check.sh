#!/usr/bin/env bash
# The house rules, as tools (make test runs this first): import contracts (import-linter),
# the linter (ruff) and the type checker (mypy); their configuration is in pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."
echo "check: import contracts"; .venv/bin/lint-imports --no-cache
echo "check: ruff";             .venv/bin/ruff check .
echo "check: mypy";             .venv/bin/mypy
