#!/usr/bin/env bash
# Build the swarm-coloc image in one command, on a machine with no container
# registry and no usable network inside build containers:
#   1. base image, when missing (scripts/docker-base.sh: debootstrap + docker import)
#   2. wheelhouse in docker/.cache/wheels, when pyproject.toml/constraints.txt changed
#      (host pip, which has the machine's network and CA set up)
#   3. docker build -t swarm-coloc:latest .   with the wheelhouse served on
#      127.0.0.1 to the build (--network host, PIP_FIND_LINKS, PIP_NO_INDEX=1)
#
# Why a wheelhouse served over loopback rather than pip inside the build:
#   - build containers here reach the network, but TLS to the package index is
#     re-signed by a CA that only the host trusts, so `pip install` inside
#     `docker build` fails certificate checks; baking a host's CA into an image
#     is not something a Dockerfile should do;
#   - the engine has the classic builder only (no BuildKit/buildx, so no
#     RUN --mount): COPYing the ~570 MB wheelhouse would send it as build
#     context on every build (about 4 s even when nothing changed) and leave it
#     in a layer; served over loopback it is read once, by the step that needs it;
#   - builds need no network at all once the wheelhouse exists.
# OFFLINE=0 skips the wheelhouse and lets pip in the build use its default
# index (a normal machine with working network).
#
# Usage: scripts/docker-build.sh
#   IMAGE=swarm-coloc:latest  BASE_IMAGE=debian:bookworm-slim
#   WHEELS_PORT=38517 (loopback port of the wheelhouse server: the first free one of it
#   and the nine after it, else any free one)  OFFLINE=1
#   DOCKER_BUILD_ARGS="--no-cache ..." (extra arguments for docker build)
set -euo pipefail
cd "$(dirname "$0")/.."

IMAGE=${IMAGE:-swarm-coloc:latest}
BASE_IMAGE=${BASE_IMAGE:-debian:bookworm-slim}
OFFLINE=${OFFLINE:-1}
WHEELS=docker/.cache/wheels
# The port is part of a build argument (PIP_FIND_LINKS), and a build argument whose value
# changed invalidates the cache of every RUN after it: a port picked afresh by the kernel
# rebuilt the 2 GB dependency layer at every call (measured: the image rebuilt inside the
# first compose test, 8 min into a CI run, after the image test's fixture had built it). So
# the same port every time: WHEELS_PORT, or the next of ten when it is held (the cache then
# misses once); only when all ten are held, any free port.
WHEELS_PORT=${WHEELS_PORT:-38517}
# The interpreter of the image (Debian bookworm): wheels are picked for it,
# whatever Python the host has.
TARGET_PY=3.11
TARGET_GLIBC_MINOR=36

log() { echo "docker-build: $*" >&2; }
# One build at a time on this machine (the wheelhouse port, the image tag).
exec 9>"${TMPDIR:-/tmp}/swarm-coloc-docker-build.lock"
if ! flock -n 9; then log "waiting for another build to finish"; flock 9; fi
t0=$(date +%s)
PY=python3
[ -x .venv/bin/python ] && PY=.venv/bin/python

# 1. base image --------------------------------------------------------------
BASE_IMAGE="$BASE_IMAGE" scripts/docker-base.sh
t1=$(date +%s)

build_args=(--build-arg "BASE_IMAGE=$BASE_IMAGE")
server_pid=
# The wheelhouse server ends at the end of its stdin (below): close it, then wait.
cleanup() {
  if [ -n "$server_pid" ]; then
    if [ -n "${WHEELSRV[1]:-}" ]; then eval "exec ${WHEELSRV[1]}>&-"; fi
    wait "$server_pid" 2>/dev/null || true
  fi
}
trap cleanup EXIT

if [ "$OFFLINE" = "1" ]; then
  # 2. wheelhouse --------------------------------------------------------------
  stamp_want=$(cat pyproject.toml constraints.txt docker/requirements.py | sha256sum | cut -d' ' -f1)-py$TARGET_PY-glibc2.$TARGET_GLIBC_MINOR
  if [ ! -f "$WHEELS/.stamp" ] || [ "$(cat "$WHEELS/.stamp")" != "$stamp_want" ]; then
    log "preparing the wheelhouse in $WHEELS"
    plat=()
    for i in $(seq 17 "$TARGET_GLIBC_MINOR"); do plat+=(--platform "manylinux_2_${i}_x86_64"); done
    plat+=(--platform manylinux2014_x86_64 --platform manylinux2010_x86_64 --platform manylinux1_x86_64)
    target=(--only-binary=:all: "${plat[@]}" --python-version "$TARGET_PY" --implementation cp --abi "cp${TARGET_PY/./}")
    tmp=$(mktemp -d docker/.cache/wheels.new.XXXXXX 2>/dev/null || { mkdir -p docker/.cache; mktemp -d docker/.cache/wheels.new.XXXXXX; })
    "$PY" docker/requirements.py pyproject.toml >"$tmp/requirements.txt"
    # Dependencies + the build backend the project's wheel needs (pyproject's
    # build-system), then pyrender alone (see Dockerfile).
    build_reqs=$("$PY" -c 'import tomllib; print("\n".join(tomllib.load(open("pyproject.toml","rb"))["build-system"]["requires"]))')
    mapfile -t build_reqs <<<"$build_reqs"
    PIP_FIND_LINKS= "$PY" -m pip download -q -d "$tmp" "${target[@]}" -c constraints.txt \
      -r "$tmp/requirements.txt" "${build_reqs[@]}"
    PIP_FIND_LINKS= "$PY" -m pip download -q -d "$tmp" "${target[@]}" --no-deps -c constraints.txt pyrender==0.1.45
    rm -f "$tmp/requirements.txt"
    echo "$stamp_want" >"$tmp/.stamp"
    rm -rf "$WHEELS"; mv "$tmp" "$WHEELS"
    log "wheelhouse: $(ls "$WHEELS" | wc -l) files, $(du -sh "$WHEELS" | cut -f1)"
  fi
  # Serve it on loopback for the build (the build's RUN steps share the host's network
  # namespace through --network host), on the first free port of WHEELS_PORT and the nine
  # after it (above: why a fixed one), else one the kernel picks. The server reads its
  # stdin, a pipe from this script, and exits at its end: whatever ends this script, a
  # signal or SIGKILL included, the server goes with it.
  coproc WHEELSRV { "$PY" -c '
import functools, http.server, sys, threading
handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=sys.argv[1])
handler.log_message = lambda *a: None
first = int(sys.argv[2])
for port in [*range(first, first + 10), 0] if first else [0]:
    try:
        srv = http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
        break
    except OSError:
        continue
print(srv.server_address[1], flush=True)
threading.Thread(target=srv.serve_forever, daemon=True).start()
sys.stdin.read()
' "$WHEELS" "$WHEELS_PORT" 2>/dev/null 9>&-; }
  server_pid=$WHEELSRV_PID
  if ! read -r -t 30 WHEELS_PORT <&"${WHEELSRV[0]}"; then
    log "the wheelhouse server did not start"; exit 1
  fi
  log "wheelhouse served on 127.0.0.1:$WHEELS_PORT"
  build_args+=(--network host --build-arg "PIP_FIND_LINKS=http://127.0.0.1:$WHEELS_PORT/" --build-arg PIP_NO_INDEX=1)
fi
t2=$(date +%s)

# 3. the image -----------------------------------------------------------------
old_id=$(docker image inspect -f '{{.Id}}' "$IMAGE" 2>/dev/null || true)
log "docker build -t $IMAGE ."
# shellcheck disable=SC2086
docker build --force-rm "${build_args[@]}" ${DOCKER_BUILD_ARGS:-} -t "$IMAGE" . 2> >(grep -v -e 'DEPRECATED: The legacy builder' -e 'BuildKit is currently disabled' -e 'Install the buildx component' -e 'docs.docker.com/go/buildx' -e '^ *$' >&2)
t3=$(date +%s)
# The image this build replaced, now untagged: remove it (its layers shared
# with the new image stay), so rebuilds do not pile up old images.
new_id=$(docker image inspect -f '{{.Id}}' "$IMAGE")
if [ -n "$old_id" ] && [ "$old_id" != "$new_id" ] && [ -z "$(docker image inspect -f '{{join .RepoTags ""}}' "$old_id" 2>/dev/null)" ]; then
  docker rmi "$old_id" >/dev/null 2>&1 || true
fi
# Older results of the wheel stage (untagged; the newest one is this build's
# cache): removing them frees the dependency layers of earlier builds too.
mapfile -t stale < <(docker images -q -f dangling=true -f label=org.swarm-coloc.stage=wheel | tail -n +2)
if [ ${#stale[@]} -gt 0 ]; then docker rmi "${stale[@]}" >/dev/null 2>&1 || true; fi
log "built $IMAGE ($(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1/1e6}')): base $((t1 - t0)) s, wheelhouse $((t2 - t1)) s, docker build $((t3 - t2)) s, total $((t3 - t0)) s"
