#!/usr/bin/env bash
# Idempotent set-up: apt packages, .venv, torch (CPU build first), gearscan with test extras.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PKGS=(gir1.2-aravis-0.8 libaravis-0.8-0 aravis-tools aravis-tools-cli libgirepository1.0-dev
          libcairo2-dev pkg-config gcc g++ python3-dev socat libgl1 libegl1 libusb-1.0-0 chromium)
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
missing=()
for p in "${APT_PKGS[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if ! python3 -m venv --help >/dev/null 2>&1; then missing+=(python3-venv); fi
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing apt packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv; fi
# torch first, spelled exactly so: the CPU build (any other spelling pulls GBs of CUDA wheels)
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e ".[test]"
