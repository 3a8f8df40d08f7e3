#!/usr/bin/env bash
# Set up UniRelight Studio on a fresh Debian 12 machine: system packages, the .venv virtual
# environment, and the pinned Python packages (torch first, so nothing pulls a CUDA build).
# Usage: bash scripts/setup.sh          everything the app needs
#        bash scripts/setup.sh --test   plus what the test suite needs (Chromium for the UI tests)
# Safe to run again: it skips what is already in place.
set -euo pipefail
cd "$(dirname "$0")/.."

apt_packages=(libegl1 libgl1 libgomp1 libllvm19)   # pyvista off-screen (EGL), Mitsuba's LLVM backend
if [[ "${1:-}" == "--test" ]]; then
  apt_packages+=(chromium)                          # the real browser the UI tests drive
fi
missing=()
for package in "${apt_packages[@]}"; do
  dpkg -s "$package" >/dev/null 2>&1 || missing+=("$package")
done
if (( ${#missing[@]} )); then
  sudo=""
  [[ $(id -u) -ne 0 ]] && sudo="sudo"
  echo "Installing system packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi

[[ -x .venv/bin/python ]] || python3 -m venv .venv
stamp=".venv/.installed-$(sha1sum requirements.txt | cut -c1-12)"
if [[ ! -f "$stamp" ]]; then
  .venv/bin/pip install -q torch==2.13.0
  .venv/bin/pip install -q -r requirements.txt
  touch "$stamp"
fi
echo "Set up: .venv ready ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))."
