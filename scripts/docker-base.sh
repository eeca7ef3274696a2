#!/usr/bin/env bash
# Make the base image of docker/Dockerfile locally, for machines that have no
# container registry (nothing can be pulled). Idempotent: does nothing when the
# image already exists (pulled, or made earlier from the same package list); a
# locally made one whose package list differs from today's is made again (the
# build has no network for apt, so the base must already hold every package).
#
# What it makes: a minimal Debian bookworm root file system (debootstrap
# --variant=minbase) that already holds the run-time packages the Dockerfile
# would otherwise apt-get install (python3, python3-venv, ca-certificates,
# openssl, tini, and the Mesa/EGL/OSMesa libraries of scripts/apt-packages.txt
# less the host-only ones such as chromium), trimmed like Debian's "slim" images and
# loaded with `docker import` under the tag the Dockerfile's FROM names. The
# Dockerfile then finds every package present and needs no network for apt.
#
# The Debian mirror is read from this machine's own apt sources at run time
# (never written into the repository); MIRROR=... overrides it.
#
# Usage: scripts/docker-base.sh            (needs root and a running Docker)
#   BASE_IMAGE=debian:bookworm-slim   tag to create (the Dockerfile's default)
#   FORCE=1                           rebuild even when the tag exists
#   MIRROR=<url>                      Debian mirror (default: from apt sources)
#   KEEP_ROOTFS=1                     keep the root file system folder
set -euo pipefail
cd "$(dirname "$0")/.."

BASE_IMAGE=${BASE_IMAGE:-debian:bookworm-slim}
SUITE=${SUITE:-bookworm}
# Packages of scripts/apt-packages.txt that only the host needs.
EXCLUDE_RE=${EXCLUDE_RE:-'^(chromium.*)$'}
# libglu1-mesa: pyglet (imported by `import pyrender`) loads libGLU at import.
# openssl: compose's keys service makes the TLS certificates with it (swarm keys).
EXTRA_PKGS=(python3 python3-venv ca-certificates openssl tini libglu1-mesa)

log() { echo "docker-base: $*" >&2; }

mapfile -t pkgs < <(grep -v '^\s*#' scripts/apt-packages.txt | grep -v '^\s*$' | awk '{print $1}' | grep -Ev "$EXCLUDE_RE")
# What this base must hold, as a label on the image: a locally made base with another
# list (an older one, without a package added since) is made again.
pkgs_id=$(printf '%s\n' "${pkgs[@]}" "${EXTRA_PKGS[@]}" | sort -u | sha256sum | cut -c1-16)
if [ "${FORCE:-0}" != "1" ] && docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
  have=$(docker image inspect -f '{{index .Config.Labels "org.swarm-coloc.base-packages"}}' "$BASE_IMAGE" 2>/dev/null || true)
  desc=$(docker image inspect -f '{{index .Config.Labels "org.opencontainers.image.description"}}' "$BASE_IMAGE" 2>/dev/null || true)
  if [ "$have" = "$pkgs_id" ]; then
    log "$BASE_IMAGE already exists with today's packages; nothing to do"
    exit 0
  elif [[ "$desc" != "Local stand-in for "* ]]; then
    # Pulled from a registry: the Dockerfile apt-gets what it lacks (a registry means network).
    log "$BASE_IMAGE already exists (not made here); nothing to do"
    exit 0
  fi
  log "$BASE_IMAGE was made from another package list (${have:-none} != $pkgs_id): making it again"
fi
if [ "$(id -u)" != "0" ]; then
  log "debootstrap needs root"; exit 1
fi
start=$(date +%s)

# --- the mirror, from this machine's apt sources ---------------------------
find_mirror() {
  local f
  # deb822 files: a stanza whose Types has deb, Suites has $SUITE exactly and
  # Components has main; first URI wins.
  for f in /etc/apt/sources.list.d/*.sources; do
    [ -f "$f" ] || continue
    awk -v suite="$SUITE" '
      function flush() {
        if (types ~ /(^| )deb( |$)/ && (" " suites " ") ~ (" " suite " ") &&
            (" " comps " ") ~ / main / && enabled != "no" && uris != "") {
          split(uris, u, " "); print u[1]; found = 1; exit
        }
        types = suites = comps = uris = ""; enabled = ""
      }
      /^[ \t]*#/ { next }
      /^[ \t]*$/ { flush(); next }
      { key = tolower($1); sub(/:$/, "", key); $1 = ""; sub(/^ +/, "")
        if (key == "types") types = $0; else if (key == "suites") suites = $0
        else if (key == "components") comps = $0; else if (key == "uris") uris = $0
        else if (key == "enabled") enabled = tolower($0) }
      END { if (!found) flush() }' "$f" | head -n1
  done
  # one-line format: deb [options] URI SUITE COMPONENTS...
  for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
    [ -f "$f" ] || continue
    awk -v suite="$SUITE" '
      $1 == "deb" { i = 2; if ($2 ~ /^\[/) { while (i <= NF && $i !~ /\]$/) i++; i++ }
        if ($(i + 1) == suite) { for (j = i + 2; j <= NF; j++) if ($j == "main") { print $i; exit } } }' "$f"
  done
}
MIRROR=${MIRROR:-$(find_mirror | head -n1)}
if [ -z "$MIRROR" ]; then
  log "no Debian '$SUITE' source with 'main' in /etc/apt; set MIRROR=<url>"; exit 1
fi
log "mirror taken from this machine's apt sources"

# --- debootstrap (install it if absent) -------------------------------------
if ! command -v debootstrap >/dev/null 2>&1; then
  log "installing debootstrap"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends debootstrap >/dev/null
fi

include=$(printf '%s,' "${pkgs[@]}" "${EXTRA_PKGS[@]}"); include=${include%,}
log "packages: $include"

work=$(mktemp -d /var/tmp/swarm-base.XXXXXX)
cleanup() { if [ "${KEEP_ROOTFS:-0}" != "1" ]; then rm -rf "$work"; else log "root fs kept in $work/rootfs"; fi; }
trap cleanup EXIT
rootfs=$work/rootfs
debootstrap --variant=minbase --include="$include" "$SUITE" "$rootfs" "$MIRROR" >"$work/debootstrap.log" 2>&1 || {
  tail -n 30 "$work/debootstrap.log" >&2; log "debootstrap failed"; exit 1; }
log "debootstrap done in $(( $(date +%s) - start )) s"

# --- trim it the way Debian's slim images are trimmed -----------------------
# Later `apt-get install`s in the image keep docs, man pages and locales out
# too (the same dpkg path excludes the official slim image carries).
cat >"$rootfs/etc/dpkg/dpkg.cfg.d/docker" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/lintian/*
path-exclude /usr/share/linda/*
path-exclude /usr/share/locale/*
EOF
cat >"$rootfs/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache ""; Dir::Cache::srcpkgcache "";
EOF
echo 'APT::Install-Recommends "false";' >"$rootfs/etc/apt/apt.conf.d/docker-no-recommends"
find "$rootfs/usr/share/doc" -mindepth 2 ! -name copyright ! -type d -delete 2>/dev/null || true
find "$rootfs/usr/share/doc" -mindepth 1 -type d -empty -delete 2>/dev/null || true
rm -rf "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/* "$rootfs"/usr/share/locale/* \
       "$rootfs"/usr/share/groff/* "$rootfs"/usr/share/lintian/* \
       "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/cache/apt/*.bin \
       "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/log/* "$rootfs"/tmp/* \
       "$rootfs"/var/cache/debconf/*-old "$rootfs"/var/lib/dpkg/*-old
: >"$rootfs/etc/machine-id" 2>/dev/null || true
rm -f "$rootfs/etc/hostname" "$rootfs/etc/resolv.conf"

# --- load it into Docker ------------------------------------------------------
tar -C "$rootfs" --numeric-owner -c . | docker import \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["bash"]' \
  --change "LABEL org.opencontainers.image.description=\"Local stand-in for $BASE_IMAGE (debootstrap $SUITE minbase + swarm-coloc run-time packages), made by scripts/docker-base.sh\"" \
  --change "LABEL org.swarm-coloc.base-packages=$pkgs_id" \
  - "$BASE_IMAGE" >/dev/null
log "made $BASE_IMAGE ($(docker image inspect -f '{{.Size}}' "$BASE_IMAGE" | awk '{printf "%.0f MB", $1/1e6}')) in $(( $(date +%s) - start )) s"
