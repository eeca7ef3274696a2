#!/usr/bin/env bash
# Set up everything the project needs on a fresh Debian 12 machine (idempotent).
#   - Debian packages from scripts/apt-packages.txt and scripts/apt-packages-dev.txt
#     (when root and apt-get exists)
#   - a virtualenv in .venv with the project, its extras and pinned versions
#   - a check that cargo (the Rust toolchain, from rustup) is there for the Rust
#     participant (participants/rust-watch, built by tests/test_rust_participant.py)
# Usage: scripts/setup.sh            (SKIP_APT=1 to skip the system packages)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

if [ "${SKIP_APT:-0}" != "1" ] && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = "0" ]; then
  mapfile -t pkgs < <(cat scripts/apt-packages.txt scripts/apt-packages-dev.txt | grep -v '^\s*#' | grep -v '^\s*$')
  missing=()
  for p in "${pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing Debian packages: ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.setup-stamp
want=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[test,vision]"
  # pyrender 0.1.45 pins PyOpenGL==3.1.0, which has no working OSMesa; its real
  # dependencies come from the "vision" extra above, so install it without deps.
  .venv/bin/python -m pip install -q --no-deps -c constraints.txt "pyrender==0.1.45"
  echo "$want" > "$stamp"
fi
if ! command -v cargo >/dev/null 2>&1 && [ ! -x "$HOME/.cargo/bin/cargo" ]; then
  echo "setup: warning: cargo not found; the Rust participant test needs the Rust toolchain (rustup)" >&2
fi
echo "setup: ok ($(.venv/bin/python --version), venv in .venv)"
