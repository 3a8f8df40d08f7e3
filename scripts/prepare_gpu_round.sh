#!/usr/bin/env bash
# Make everything a GPU round needs on this machine's CPUs, from nothing: the rendered scenes, the packs and the
# pieces that each fit one call to a GPU machine (docs/TRAINING.md, "A round on a GPU machine"). Start it at the
# very beginning of a session that has a GPU (or the session before): on 2 cores the 7,022 seed-7 scenes take
# about an hour, the test split 4 minutes. Every step is deterministic and resumes where it stopped (render-data
# skips finished scenes; a pack or the pieces are made again only when missing), so run it again after a stop.
#   bash scripts/prepare_gpu_round.sh                  # → ~/.cache/unirelight-studio/gpu-pieces-s7/{p1..p4,val,test}.npz + init/
#   SCENES=3000 PIECES="58 40" bash scripts/prepare_gpu_round.sh
# Settings (environment): UNIRELIGHT_CACHE, PYTHON, SEED (7), SCENES (7022), WORKERS (nproc), VAL (128 scenes kept
# out as val.npz), TEST_SCENES (200), PIECES (each piece's largest size, MB).
# Then, one call at a time: carry each piece to the GPU machine (copy it into .dev/, which .git/info/exclude
# ignores) and run scripts/gpu_round.sh with the last one (docs/TRAINING.md has the calls).
set -euo pipefail
cd "$(dirname "$0")/.."
cache=${UNIRELIGHT_CACHE:-$HOME/.cache/unirelight-studio}
python=${PYTHON:-.venv/bin/python}
seed=${SEED:-7}
scenes=${SCENES:-7022}
workers=${WORKERS:-$(nproc)}
data="$cache/data$seed"
pack="$cache/train-s$seed-all.npz"
pieces_dir="$cache/gpu-pieces-s$seed"
val=${VAL:-128}
test_scenes=${TEST_SCENES:-200}
read -r -a pieces <<< "${PIECES:-58 58 58 40}"

echo "$(date +%H:%M:%S) test split ($test_scenes scenes) → $cache/data"
"$python" -m relight_core render-data --out "$cache/data" --split test --scenes "$test_scenes" --frames 1 --size 128 \
  --spp 32 --workers "$workers"
echo "$(date +%H:%M:%S) $scenes seed-$seed training scenes → $data"
"$python" -m relight_core render-data --out "$data" --split train --scenes "$scenes" --frames 1 --size 128 \
  --spp 32 --seed "$seed" --workers "$workers"
if [[ ! -f "$pack" ]]; then
  echo "$(date +%H:%M:%S) packing → $pack"
  "$python" -m relight_core.training.pack --data "$data" --split train --out "$pack.partial.npz"
  mv "$pack.partial.npz" "$pack"
fi
if [[ ! -f "$pieces_dir/val.npz" ]]; then
  echo "$(date +%H:%M:%S) cutting pieces of at most ${pieces[*]} MB → $pieces_dir"
  rm -rf "$pieces_dir.partial"
  "$python" -m relight_core.training.pieces --pack "$pack" --val "$val" --pieces "${pieces[@]}" \
    --out "$pieces_dir.partial"
  "$python" -m relight_core.training.pack --data "$cache/data" --split test --out "$pieces_dir.partial/test.npz"
  mkdir -p "$pieces_dir.partial/init"
  cp models/default/config.json models/default/dit.safetensors "$pieces_dir.partial/init/"
  mv "$pieces_dir.partial" "$pieces_dir"
fi
echo "$(date +%H:%M:%S) ready:"
ls -l "$pieces_dir" "$pieces_dir/init"
