#!/usr/bin/env bash
# One training round on a GPU machine, within a time budget: a run per learning rate in $LRS, side by
# side on the one GPU, each from $INIT on every pack in $PACKS and keeping its best EMA on the
# held-out $VAL scenes (fast --val-pack), then training.pick keeps the best of the runs, their mean
# and their mean with $INIT — as a model folder and ≤ 15 MB shards in $OUT, with the runs' logs.
#   PACKS="/tmp/packs/*.npz" VAL=.dev/last/val.npz TEST=.dev/last/test.npz INIT=.dev/last/init \
#     bash scripts/gpu_round.sh 8.2
# COMPILE=1 adds --compile (torch.compile; a compiler failure falls back to eager). An entry of $LRS may end in
# ":permute": that run also reorders each item's colour channels, its probe's alike (fast --permute-colours), and is
# named lr-<lr>-permute. The default, "2e-4 2e-4:permute", puts the augmentation to the round's own pick.
# Packs too large for one call travel in pieces (python -m relight_core.training.pieces; docs/TRAINING.md).
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}   # keeps a caller's (carried wheels in /tmp/site)
minutes=${1:?usage: gpu_round.sh MINUTES}
python=${PYTHON:-python3}
out=${OUT:-runs/gpu-round}
runs=${RUNS_DIR:-/tmp/gpu-round}
init=${INIT:-models/default}
mkdir -p "$out" "$runs"
# shellcheck disable=SC2086  # $PACKS is a glob, expanded here
packs=$(ls ${PACKS:-/tmp/packs/*.npz})
echo "packs: $packs"
"$python" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
seed=70
models=() pids=()
for run in ${LRS:-2e-4 2e-4:permute}; do
  lr=${run%%:*} name=lr-${run%%:*} extra=()
  if [[ $run == *:permute ]]; then name=$name-permute extra=(--permute-colours); fi
  # shellcheck disable=SC2086
  "$python" -m relight_core.training.fast --pack $packs ${TEST:+--test-pack "$TEST"} --val-pack "$VAL" \
    --device "${DEVICE:-cuda}" --minutes "$minutes" --batch "${BATCH:-128}" --lr "$lr" --seed "$seed" --warmup 100 \
    --ema-decay 0.999 --init "$init" --residual --p-sigma-max 0.9 --albedo-weight 0.5 --mix-lights 0.5 \
    --eval-steps 1 --eval-items 32 --val-items 128 --val-every-minutes 0.5 --export-every-minutes 1000 \
    --checkpoint-every-minutes 1000 --log-every 50 ${COMPILE:+--compile} "${extra[@]}" --out "$runs/$name" \
    > "$out/log-$name.txt" 2>&1 &
  pids+=("$!")
  models+=("$runs/$name/model")
  seed=$((seed + 1))
done
# each run's exit status, so that a run that died says so (failures.txt) rather than only leaving no model
rm -f "$out/failures.txt"
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || echo "the run ${models[$i]%/model} failed (exit status $?): see $out/log-$(basename "${models[$i]%/model}").txt" \
    | tee -a "$out/failures.txt"
done
"$python" -m relight_core.training.pick "${models[@]}" --val "$VAL" --init "$init" --out "$out" \
  --device "${DEVICE:-cuda}"
