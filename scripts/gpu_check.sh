#!/usr/bin/env bash
# The released UniRelight weights on this machine's GPU, against the paper's runtime, in one table:
#
#   scripts/gpu_check.sh MODEL_DIR    # a folder made by `python -m relight_core import-released`
#   scripts/gpu_check.sh tiny         # the tiny preset: checks this script on any GPU in seconds
#
# Relights one bundled image and a 57-frame example at 480×848 with 35 steps and prints network
# calls, seconds per call, total seconds and peak GPU memory beside the paper's 445.5 s per clip
# on an A100. Refuses in one sentence (exit 2) without a CUDA GPU, or when the GPU is too small
# for its memory estimate. The logic lives in relight_core/gpu_check.py.
set -euo pipefail

if [ "$#" -ne 1 ]; then
    echo "usage: scripts/gpu_check.sh MODEL_DIR (a folder made by import-released, or the preset tiny)" >&2
    exit 2
fi
model="$1"
if [ -d "$model" ]; then
    model="$(cd "$model" && pwd)"   # the folder as the user named it, before we move to the repository
fi
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
    echo "error: $(pwd)/.venv is missing; run scripts/setup.sh first." >&2
    exit 2
fi
exec .venv/bin/python -m relight_core.gpu_check "$model"
