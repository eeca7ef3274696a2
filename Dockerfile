# swarm-coloc: one image for every role of the emulator (world simulator,
# satellite agents, selector, recorder, Zenoh router); the command picks the
# role, e.g.
#   docker build -t swarm-coloc:latest .
#   docker run --rm swarm-coloc:latest swarm --help
#   docker run --rm swarm-coloc:latest sat_agent --id 3   (= python -m sat_agent --id 3)
#
# With a registry and network this builds as it stands. On a machine with
# neither, scripts/docker-build.sh first makes the base image locally
# (scripts/docker-base.sh) and serves a wheelhouse prepared on the host to the
# build through PIP_FIND_LINKS + PIP_NO_INDEX=1 (see the ARGs below).
#
# Written for the classic builder as well as BuildKit (no RUN --mount).

ARG BASE_IMAGE=debian:bookworm-slim

# ---- run-time system packages ---------------------------------------------
FROM ${BASE_IMAGE} AS runtime
# Python, tini, the Mesa/EGL/OSMesa libraries headless rendering and
# Open3D need, iproute2 and iptables (swarm fault netem): scripts/apt-packages.txt
# less the host-only ones (chromium),
# plus libGLU, which pyglet loads as soon as pyrender is imported, and openssl,
# with which compose's keys service makes the TLS certificates (`swarm keys`).
# Installs only what the base lacks: the locally made base already has all of
# them, so this step needs no network there.
COPY scripts/apt-packages.txt /tmp/apt-packages.txt
RUN set -eu; \
    pkgs="python3 python3-venv ca-certificates openssl tini libglu1-mesa $(grep -Ev '^[[:space:]]*(#|$)' /tmp/apt-packages.txt | grep -Ev '^chromium')"; \
    missing=""; \
    for p in $pkgs; do \
      dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing="$missing $p"; \
    done; \
    if [ -n "$missing" ]; then \
      apt-get update; \
      DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $missing; \
      rm -rf /var/lib/apt/lists/*; \
    fi; \
    rm /tmp/apt-packages.txt
# The image's metadata and its rarely changed files, here on the small base: the build
# runs on fuse-overlayfs, where every step on top of the 2 GB dependency layer costs a
# container and ~10 s even when it only sets metadata (measured: 8 such steps were 74 s of
# a 294 s cold build on a quiet machine, twice that under load).
# PYOPENGL_PLATFORM=egl: headless Mesa (llvmpipe); osmesa is the fallback.
# OPENBLAS_NUM_THREADS=1: one BLAS thread per process (many processes share
# few cores; a fixed thread count also keeps BLAS reductions in one order).
ENV PATH=/opt/venv/bin:$PATH \
    PYOPENGL_PLATFORM=egl \
    OPENBLAS_NUM_THREADS=1 \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
LABEL org.opencontainers.image.title="swarm-coloc" \
      org.opencontainers.image.description="Cooperative localization of satellite swarms: one image for every role"
ENTRYPOINT ["tini", "--", "swarm-entrypoint"]
CMD ["swarm", "--help"]
COPY docker/entrypoint.sh /usr/local/bin/swarm-entrypoint

# ---- Python dependencies (before the source, so a code change is quick) ----
FROM runtime AS deps
# Where pip finds wheels: unset = the default index. scripts/docker-build.sh
# passes PIP_FIND_LINKS=http://127.0.0.1:PORT/ (the host's wheelhouse, with
# `docker build --network host`) and PIP_NO_INDEX=1.
ARG PIP_FIND_LINKS=
ARG PIP_NO_INDEX=0
COPY pyproject.toml constraints.txt docker/requirements.py /tmp/deps/
# The project's dependencies plus the "vision" extra, pinned by
# constraints.txt; pyrender with --no-deps (it pins PyOpenGL 3.1.0, which has
# no working OSMesa; its real dependencies are in the "vision" extra).
RUN python3 -m venv /opt/venv \
 && python3 /tmp/deps/requirements.py /tmp/deps/pyproject.toml > /tmp/deps/requirements.txt \
 && /opt/venv/bin/pip install -q -c /tmp/deps/constraints.txt -r /tmp/deps/requirements.txt \
 && /opt/venv/bin/pip install -q --no-deps -c /tmp/deps/constraints.txt pyrender==0.1.45 \
 && rm -rf /tmp/deps /root/.cache

# ---- the project as a wheel, with the scenarios (thrown away but for /dist) ----
# On the small base, not on deps: a build venv of its own (setuptools and wheel from
# pip's index, or the wheelhouse) is cheaper than steps on the dependency layer.
FROM runtime AS wheel
# Lets scripts/docker-build.sh find this stage's leftover images.
LABEL org.swarm-coloc.stage=wheel
ARG PIP_FIND_LINKS=
ARG PIP_NO_INDEX=0
COPY . /src
RUN python3 -m venv /tmp/build-venv \
 && /tmp/build-venv/bin/pip wheel -q --no-deps -w /dist /src \
 && cp -r /src/scenarios /dist/scenarios \
 && rm -rf /tmp/build-venv /root/.cache

# ---- the image --------------------------------------------------------------
# Two steps on the dependency layer: after a code change only these rerun.
FROM deps
COPY --from=wheel /dist/ /tmp/dist/
# Install the project (not editable); fail the build, not the first run, when
# a library is missing; and compile every kernel an agent warms up (the filter's,
# the ci estimator's, the orbit propagator's, the bus's batch checks) and run the
# demo once, so numba's compiled kernels are cached in the image (a container
# would otherwise compile at each start: the ci kernel alone is 1.1 s on a quiet
# machine, more under load, and a restarted agent's container came back late; on
# a CPU of another kind numba notices and compiles afresh).
RUN pip install -q --no-deps --no-index /tmp/dist/*.whl \
 && mv /tmp/dist/scenarios /app/scenarios \
 && rm -rf /tmp/dist /root/.cache \
 && python -c "import zenoh, numpy, scipy, cv2, open3d, pyrender, distributed, ray, swarm.cli; from swarmrt.bus import fastcheck; fastcheck.warm_up(); from swarmcore import kernels, orbit; kernels.warm_up(); orbit.warm_up()" \
 && { swarm sim scenarios/demo.yaml --out /tmp/warm --no-arrays >/tmp/warm.log 2>&1 \
      || { cat /tmp/warm.log; exit 1; }; } \
 && rm -rf /tmp/warm /tmp/warm.log
