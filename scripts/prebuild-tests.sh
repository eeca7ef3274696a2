#!/usr/bin/env bash
# What the tests run but do not time: the container image (scripts/docker-build.sh, when a
# Docker daemon answers) and the Rust participants (cargo, dev profile, into the target
# directory the Rust tests share, participants/target). `make test` runs this before pytest so
# that a cold build (minutes: the base image, the wheelhouse, a cold zenoh crate tree) is not
# charged to whichever test happens to ask for it first, under that test's timeout; the tests'
# own build calls then find everything current and return in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
t0=$(date +%s)
cargo_bin=$(command -v cargo || echo "$HOME/.cargo/bin/cargo")
if [ -x "$cargo_bin" ] && command -v protoc >/dev/null 2>&1; then
  for crate in rust-watch rust-agent; do
    (cd "participants/$crate" && "$cargo_bin" build -q --locked --target-dir ../target)
  done
  echo "prebuild: Rust participants built in $(( $(date +%s) - t0 )) s"
else
  echo "prebuild: no cargo or protoc: the Rust tests will say so" >&2
fi
t1=$(date +%s)
if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then
  scripts/docker-build.sh
  echo "prebuild: image built in $(( $(date +%s) - t1 )) s"
else
  echo "prebuild: no Docker daemon: the container tests will skip and say why" >&2
fi
