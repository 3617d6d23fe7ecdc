#!/usr/bin/env bash
# Idempotent set-up for a fresh machine: system libraries, the virtual environment, Python dependencies.
# Usage: scripts/setup.sh [--browser]   (--browser also installs Debian's chromium for the web-page test)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${VENV:-.venv}"
PYTHON="${PYTHON:-python3}"
want_browser=0
[[ "${1:-}" == "--browser" ]] && want_browser=1

# Open3D links libusb, libGL/EGL and X11 even headless; OpenCV and Open3D want libgomp. The simulator renders
# with MuJoCo headless: EGL through Mesa's software rasterizer (libegl-mesa0 + libgl1-mesa-dri), or OSMesa
# (libosmesa6) with MUJOCO_GL=osmesa.
pkgs=(libusb-1.0-0 libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libgomp1 libx11-6)
[[ $want_browser == 1 ]] && pkgs+=(chromium)
# A bare Debian or Ubuntu has no python3, or python3 without venv/ensurepip (Debian splits them out).
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  pkgs+=(python3 python3-venv)
elif ! "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1; then
  pkgs+=(python3-venv)
fi
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  SUDO=""
  if [[ $(id -u) -ne 0 ]]; then
    if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else SUDO="none"; fi
  fi
  if [[ $SUDO == none ]] || ! command -v apt-get >/dev/null 2>&1; then
    echo "setup: please install these system packages (as root): ${missing[*]}" >&2
    [[ " ${missing[*]} " == *" python3"* ]] && exit 1
  else
    echo "setup: installing system packages: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
  echo "setup: aermani needs Python >= 3.11 ($PYTHON is $("$PYTHON" -V 2>&1)); set PYTHON=python3.11 or newer" >&2
  exit 1
fi

stamp="$VENV/.aermani-installed"
if [[ ! -x "$VENV/bin/python" ]]; then
  echo "setup: creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
if [[ ! -f "$stamp" || pyproject.toml -nt "$stamp" ]]; then
  echo "setup: installing Python dependencies (first run takes a few minutes)"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -e ".[dev]"
  touch "$stamp"
fi
