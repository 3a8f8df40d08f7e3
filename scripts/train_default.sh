#!/usr/bin/env bash
# Render, pack, train and export the default model within a time budget — rendering with Mitsuba's CUDA variant
# and training on a CUDA GPU when one is present, else on the CPU. Data and packs live in the cache (regenerated
# from the seed when lost); the model folder and the training log go where the flags say.
#   SCENES=2000 MINUTES=8 bash scripts/train_default.sh            # → runs/default-pixel/model
#   SCENES=20000 RENDER_MINUTES=5 MINUTES=8 bash scripts/train_default.sh   # ~13 minutes whatever the machine:
#                                                                  # as many scenes as 5 minutes render, then 8 of training
#   INIT=models/default MINUTES=30 bash scripts/train_default.sh   # continue from the shipped weights
#   EXTRA="--residual --p-sigma-max 0.75" bash scripts/train_default.sh   # the shipped residual model's recipe
# RENDER_DEVICE: auto (default: the GPU where Mitsuba renders on it), cpu or cuda. The test split always renders
# on the CPU, so its files — and every score on them — are the same on every machine.
set -euo pipefail
cd "$(dirname "$0")/.."
cache=${UNIRELIGHT_CACHE:-$HOME/.cache/unirelight-studio}
python=${PYTHON:-.venv/bin/python}
scenes=${SCENES:-2000}
minutes=${MINUTES:-8}
out=${OUT_DIR:-runs/default-pixel}
workers=$(nproc)

"$python" -m relight_core render-data --out "$cache/data" --split test --scenes 40 --frames 1 --size 128 \
  --spp 32 --workers "$workers" --device cpu
# scenes at once: one per CPU, or on a GPU 4 (render-data --gpus-per-worker)
"$python" -m relight_core render-data --out "$cache/data" --split train --scenes "$scenes" --frames 1 --size 128 \
  --spp 32 --device "${RENDER_DEVICE:-auto}" ${RENDER_MINUTES:+--minutes "$RENDER_MINUTES"}
"$python" -m relight_core.training.pack --data "$cache/data" --split train --out "$cache/train.npz"
"$python" -m relight_core.training.pack --data "$cache/data" --split test --out "$cache/test.npz"
"$python" -m relight_core.training.fast --pack "$cache/train.npz" --test-pack "$cache/test.npz" \
  --out "$out" --device auto --minutes "$minutes" ${INIT:+--init "$INIT"} ${COMPILE:+--compile} ${EXTRA:-}
