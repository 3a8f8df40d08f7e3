#!/usr/bin/env bash
# After a GPU round changed the DiT (scripts/gpu_round.sh): fit the model's two refiners again to what the new
# DiT makes, on the GPU, side by side, within MINUTES — so that the round hands back a whole model rather than a
# DiT whose refiners were fitted to the one before. scripts/gpu_whole_round.sh runs it after the round; alone:
#   DIT=/tmp/gpu/work/round PACKS="/tmp/gpu/refit/*.npz" VAL=/tmp/gpu/aux/refit-val.npz LIKE=/tmp/gpu/aux/model \
#     OUT=$OUT bash scripts/gpu_refine.sh 2.5
# DIT: the round's shards + config.json (or a model folder); LIKE: the model whose settings and refiners carry
# over (models/default); PACKS: scenes the new DiT never trained on (the refiners learn its errors on new photos);
# VAL: held-out scenes neither ever saw. Each refiner starts from LIKE's (training.refine --refit), keeps its best
# EMA on VAL (the start counts) and goes to $OUT in bf16 (≤ 16 MiB a file) with its best.json and log; locally,
# training.assemble --like LIKE --dit SHARDS --refiner ... --relit-refiner ... makes the model folder, then
# calibrate (--write, --strengths) and evaluate as usual. DEVICE=cpu runs the same on a CPU; REFINE_LR (3e-4),
# REFINE_BATCH (16), SAME (80 items relit to their own light), THREADS (4) and VAL_EVERY (0.5 min) tune the runs.
# HAND_BACK=1 trains nothing: it hands back what runs stopped early (by a time limit) left in $RUNS_DIR, the best
# EMA each kept so far (gpu_whole_round.sh does this when the refit ran out of time).
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}   # keeps a caller's (carried wheels in /tmp/site)
minutes=${1:?usage: gpu_refine.sh MINUTES}
python=${PYTHON:-python3}
like=${LIKE:-models/default}
dit=${DIT:?DIT: the shards + config.json of the GPU round, or a model folder}
val=${VAL:?VAL: a pack of held-out scenes}
out=${OUT:-runs/gpu-refine}
runs=${RUNS_DIR:-/tmp/gpu-refine}
mkdir -p "$out" "$runs"
# shellcheck disable=SC2086  # $PACKS is a glob, expanded here
packs=$(ls ${PACKS:?PACKS: packs of scenes the new DiT never trained on})
echo "packs: $packs"
status=0
if [[ ${HAND_BACK:-0} != 1 ]]; then
"$python" -m relight_core.training.assemble --like "$like" --dit "$dit" --out "$runs/cand" || exit 1
pids=()
for slot in refiner relit_refiner; do
  extra=()
  [[ $slot == relit_refiner ]] && extra=(--same-scenes "${SAME:-80}")   # ~5 % of the items relit to their own light
  # shellcheck disable=SC2086
  "$python" -m relight_core.training.refine --model "$runs/cand" --pack $packs --val-pack "$val" --refit \
    --slot "$slot" "${extra[@]}" --permute-colours --lr "${REFINE_LR:-3e-4}" --batch "${REFINE_BATCH:-16}" \
    --device "${DEVICE:-cuda}" --threads "${THREADS:-4}" --minutes "$minutes" \
    --val-every-minutes "${VAL_EVERY:-0.5}" --out "$runs/$slot" > "$out/log-$slot.txt" 2>&1 &
  pids+=("$!")
done
# a run that died after saving its start would look like a refit that changed nothing: its exit status says
slots=(refiner relit_refiner)
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { echo "the ${slots[$i]} run failed (exit status $?): see $out/log-${slots[$i]}.txt" \
                            | tee -a "$out/failures.txt"; status=1; }
done
fi
[[ -d $runs/cand ]] || { echo "no refit to hand back: $runs/cand is missing"; exit 1; }
parts=()
for slot in refiner relit_refiner; do
  if [[ -f $runs/$slot/refiner.safetensors ]]; then
    parts+=("--${slot//_/-}" "$runs/$slot/refiner.safetensors")
    cp "$runs/$slot/best.json" "$out/best-$slot.json"
  else
    echo "no $slot came out of its run: see $out/log-$slot.txt"
    status=1
  fi
done
# the whole model once, in bf16 as it ships (checked to load); its refiners go to $OUT (the DiT came back already)
"$python" -m relight_core.training.assemble --like "$runs/cand" "${parts[@]}" --bf16 --out "$runs/model" || exit 1
for slot in refiner relit_refiner; do
  [[ -f $runs/$slot/refiner.safetensors ]] && cp "$runs/model/$slot.safetensors" "$out/"
done
ls -l "$out"
exit $status
