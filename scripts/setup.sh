#!/usr/bin/env bash
# One-time (and idempotent) setup: system libraries, a virtual environment in .venv, the project.
# Usage: bash scripts/setup.sh        (re-running is fast: it skips what is already done)
set -euo pipefail
cd "$(dirname "$0")/.."

# System libraries the open3d wheel links against (it fails to import without libusb-1.0-0), and
# Debian's chromium for the browser tests.
APT_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libgomp1 libx11-6 chromium)
missing=()
for p in "${APT_PACKAGES[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing system packages: ${missing[*]}"
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
    echo "setup: please install these Debian/Ubuntu packages as root: ${missing[*]}" >&2; exit 1; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for c in python3.11 python3.12 python3; do
    if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then PY="$c"; break; fi
  done
fi
[ -n "$PY" ] || { echo "setup: Python 3.11 or newer is needed (set PYTHON=/path/to/python3.11)" >&2; exit 1; }

stamp=.venv/.apose-setup
want="$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -c1-16)"
if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
echo "setup: installing Python packages into .venv (first time: a few minutes)"
# torch first and pinned: 2.13.0 is the CPU build; an unpinned torch pulls a multi-GB CUDA build
.venv/bin/python -m pip install -q --disable-pip-version-check "torch==2.13.0"
# the RealSense SDK (pyrealsense2) has wheels for x86_64 Linux, Windows and some macOS only: elsewhere the studio and
# the core install without it and say so when a live camera is asked for
if ! .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test,realsense]"; then
  echo "setup: pyrealsense2 is not available for this platform; installing without live RealSense support"
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
fi
echo "$want" > "$stamp"
echo "setup: done ($(du -sh .venv | cut -f1) in .venv)"
