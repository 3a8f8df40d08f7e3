#!/usr/bin/env bash
# Make everything a GPU round needs on this machine's CPUs, from nothing: the rendered scenes, the packs, the
# pieces, and the folders of the calls that carry them to a GPU machine, each within one call's 64 MiB (docs/
# TRAINING.md, "A whole round on a GPU machine"). Start it at the very beginning of a session that has a GPU (or
# the session before): on 2 cores with AVX-512 the 7,022 seed-7 scenes take ~80 minutes (1.5 scenes/s), the 900
# seed-8 ones ~10 minutes, the test split 4; on an AVX2-only CPU ~0.5 scenes/s, three times as long (docs/DATA.md;
# SCENES=N then packs the first N). Every step is deterministic and resumes where it stopped (render-data skips
# finished scenes; a pack or the pieces are made again only when missing), so run it again after a stop.
#   bash scripts/prepare_gpu_round.sh      # → ~/.cache/unirelight-studio/gpu-calls/{c1..cN, calls.md}
#   SCENES=3000 PIECES="58 40" bash scripts/prepare_gpu_round.sh
#   LOSSLESS=1 bash scripts/prepare_gpu_round.sh   # the same scenes packed as PNG → gpu-calls-lossless/ (beside the JPEG set)
# Settings (environment): UNIRELIGHT_CACHE, PYTHON, SEED (7), SCENES (7022), WORKERS (nproc), VAL (128 scenes kept
# out as val.npz), TEST_SCENES (200), PIECES (each piece's largest size, MB), REFIT_SEED (8), REFIT_SCENES (900,
# the last REFIT_VAL (128) of them the refiners' validation), CALL_MB (58: what a call carries besides the working tree),
# LOSSLESS (1: every pack PNG, the rendered pixels exactly, ~2.5× the bytes of JPEG 92, so ~2.5× the calls for the
# same scenes; the packs, pieces and calls get a "-lossless" suffix, so both sets can be made from one rendering),
# PICK_ON (dev: the round picks the DiT and each refiner's best EMA on DEV_SCENES (128) scenes of the *test* split
# drawn with seed DEV_SEED (2) — its held-out probes, meshes and textures, scenes neither the usual test items (seed 0)
# nor the fresh ones (seed 1) hold — packed lossless as `dev-s2.npz`, since held-out scenes of the training engine
# have rewarded what the test split punished (docs/QUALITY.md, 2026-12-07); train: on those held-out training
# scenes, as before; its calls go to gpu-calls-trainval).
# Then follow gpu-calls/calls.md: one call at a time, the last runs scripts/gpu_whole_round.sh (the DiT, then
# both refiners fitted again to it).
set -euo pipefail
cd "$(dirname "$0")/.."
cache=${UNIRELIGHT_CACHE:-$HOME/.cache/unirelight-studio}
python=${PYTHON:-.venv/bin/python}
seed=${SEED:-7}
scenes=${SCENES:-7022}
workers=${WORKERS:-$(nproc)}
data="$cache/data$seed"
val=${VAL:-128}
test_scenes=${TEST_SCENES:-200}
read -r -a pieces <<< "${PIECES:-58 58 58 40}"
refit_seed=${REFIT_SEED:-8}
refit_scenes=${REFIT_SCENES:-900}
refit_val=${REFIT_VAL:-128}
refit_data="$cache/data$refit_seed"
suffix="" pack_args=()
if [[ "${LOSSLESS:-0}" == 1 ]]; then suffix="-lossless" pack_args=(--lossless); fi
pack="$cache/train-s$seed-all$suffix.npz"
pieces_dir="$cache/gpu-pieces-s$seed$suffix"
refit_dir="$cache/refit-s$refit_seed$suffix"
pick_on=${PICK_ON:-dev}
dev_seed=${DEV_SEED:-2}
dev_data="$cache/data-dev$dev_seed"
dev_pack="$cache/dev-s$dev_seed.npz"
case $pick_on in
  dev) calls_dir="$cache/gpu-calls$suffix" ;;
  train) calls_dir="$cache/gpu-calls$suffix-trainval" ;;
  *) echo "PICK_ON is dev or train, not $pick_on"; exit 2 ;;
esac

echo "$(date +%H:%M:%S) test split ($test_scenes scenes) → $cache/data"
"$python" -m relight_core render-data --out "$cache/data" --split test --scenes "$test_scenes" --frames 1 --size 128 \
  --spp 32 --workers "$workers"
if [[ $pick_on == dev ]]; then
  echo "$(date +%H:%M:%S) ${DEV_SCENES:-128} test-split scenes of seed $dev_seed for the round's choices → $dev_data"
  "$python" -m relight_core render-data --out "$dev_data" --split test --scenes "${DEV_SCENES:-128}" --frames 1 \
    --size 128 --spp 32 --seed "$dev_seed" --workers "$workers"
  if [[ ! -f "$dev_pack" ]]; then
    "$python" -m relight_core.training.pack --data "$dev_data" --split test --lossless --names-prefix "test-s$dev_seed/" \
      --out "$dev_pack.partial.npz"
    mv "$dev_pack.partial.npz" "$dev_pack"
  fi
fi
echo "$(date +%H:%M:%S) $scenes seed-$seed training scenes → $data"
"$python" -m relight_core render-data --out "$data" --split train --scenes "$scenes" --frames 1 --size 128 \
  --spp 32 --seed "$seed" --workers "$workers"
if [[ ! -f "$pack" ]]; then
  echo "$(date +%H:%M:%S) packing → $pack"
  "$python" -m relight_core.training.pack --data "$data" --split train --out "$pack.partial.npz" "${pack_args[@]}"
  mv "$pack.partial.npz" "$pack"
fi
if [[ ! -f "$pieces_dir/val.npz" ]]; then
  echo "$(date +%H:%M:%S) cutting pieces of at most ${pieces[*]} MB → $pieces_dir"
  rm -rf "$pieces_dir.partial"
  "$python" -m relight_core.training.pieces --pack "$pack" --val "$val" --pieces "${pieces[@]}" \
    --out "$pieces_dir.partial"
  "$python" -m relight_core.training.pack --data "$cache/data" --split test --out "$pieces_dir.partial/test.npz" \
    "${pack_args[@]}"
  mv "$pieces_dir.partial" "$pieces_dir"
fi
echo "$(date +%H:%M:%S) $refit_scenes seed-$refit_seed scenes for the refiners (no model has seen them) → $refit_data"
"$python" -m relight_core render-data --out "$refit_data" --split train --scenes "$refit_scenes" --frames 1 --size 128 \
  --spp 32 --seed "$refit_seed" --workers "$workers"
if [[ ! -f "$refit_dir/val.npz" ]]; then
  rm -rf "$refit_dir.partial"
  "$python" -m relight_core.training.pack --data "$refit_data" --split train --out "$refit_dir.partial/all.npz" \
    "${pack_args[@]}"
  "$python" -m relight_core.training.pieces --pack "$refit_dir.partial/all.npz" --val "$refit_val" --pieces 58 \
    --out "$refit_dir.partial/cut"
  mkdir -p "$refit_dir"
  mv "$refit_dir.partial/cut/p1.npz" "$refit_dir/refit.npz"
  mv "$refit_dir.partial/cut/val.npz" "$refit_dir/val.npz"
  rm -rf "$refit_dir.partial"
fi
echo "$(date +%H:%M:%S) the calls' folders → $calls_dir"
files=()
for piece in "$pieces_dir"/p*.npz; do files+=("packs/$(basename "$piece")=$piece"); done
files+=("aux/test.npz=$pieces_dir/test.npz" "aux/model=models/default" "refit/refit.npz=$refit_dir/refit.npz")
if [[ $pick_on == dev ]]; then
  files+=("aux/val.npz=$dev_pack")       # the DiT's pick and the refiners' choice alike (no aux/refit-val.npz)
else
  files+=("aux/val.npz=$pieces_dir/val.npz" "aux/refit-val.npz=$refit_dir/val.npz")
fi
"$python" -m relight_core.training.calls "${files[@]}" --limit "${CALL_MB:-58}" --out "$calls_dir" \
  --run 'OUT=$OUT COMPILE=1 bash scripts/gpu_whole_round.sh DIT_MINUTES REFIT_MINUTES'
echo "$(date +%H:%M:%S) ready: $calls_dir/calls.md"
