#!/usr/bin/env bash
# The compose deployment for real, on a machine without Docker and without a container registry (CI):
# installs rootful podman (runc runtime, catatonit for `init: true`, netavark + aardvark-dns for service names),
# podman-compose (in its own venv) and debootstrap, builds a Debian bookworm base image once, then runs
# tests/compose (image build, `ground`+`drone`+`sim` up, one task over HTTP, down, volumes checked).
# Idempotent: installed packages, the venv and the base image are reused. Needs root (or sudo) for apt and podman.
# Usage: scripts/compose_test.sh [pytest args]
# Environment: AERMANI_COMPOSE_BASE=<image> uses that base instead (e.g. python:3.11-slim-bookworm where a
# registry is reachable); CONTAINERS_CONF=<file> replaces the containers.conf written here.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-$( [[ -x .venv/bin/python ]] && echo .venv/bin/python || echo python3 )}"
STATE="${AERMANI_COMPOSE_STATE:-/var/tmp/aermani-compose}"
BASE="${AERMANI_COMPOSE_BASE:-localhost/aermani-base:bookworm}"
SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
mkdir -p "$STATE"

pkgs=(podman runc catatonit netavark aardvark-dns debootstrap)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "compose_test: installing ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# crun cannot set RLIMIT_NOFILE above the hard limit of a VM/container like this one and refuses cgroup v1
# hybrid mode; runc with no default ulimits works. Netavark gives compose networks DNS for service names.
if [[ -z "${CONTAINERS_CONF:-}" ]]; then
  export CONTAINERS_CONF="$STATE/containers.conf"
  cat > "$CONTAINERS_CONF" <<'CONF'
[containers]
default_ulimits = []
[engine]
runtime = "runc"
[network]
network_backend = "netavark"
CONF
fi

if [[ ! -x "$STATE/venv/bin/podman-compose" ]]; then
  echo "compose_test: installing podman-compose"
  python3 -m venv "$STATE/venv"
  "$STATE/venv/bin/python" -m pip install -q podman-compose
fi
export AERMANI_PODMAN_COMPOSE="$STATE/venv/bin/podman-compose"

if [[ "$BASE" == localhost/aermani-base:bookworm ]] && ! $SUDO podman image exists "$BASE"; then
  echo "compose_test: building $BASE with debootstrap (a few minutes, once)"
  root="$STATE/rootfs"
  $SUDO rm -rf "$root"
  $SUDO debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm "$root" \
    "${AERMANI_DEBIAN_MIRROR:-http://deb.debian.org/debian}" >"$STATE/debootstrap.log"
  $SUDO rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
  $SUDO tar -C "$root" -c . | $SUDO podman import - "$BASE" >/dev/null
  $SUDO rm -rf "$root"
fi
export AERMANI_COMPOSE_BASE="$BASE"

exec ${SUDO:+$SUDO --preserve-env} "$PYTHON" -m pytest -m compose -s tests/compose "$@"
