#!/usr/bin/env bash
# A whole round on a GPU machine in one call: the DiT trained on (scripts/gpu_round.sh, DIT_MINUTES), then the
# model's two refiners fitted again to what the new DiT makes (scripts/gpu_refine.sh, REFIT_MINUTES), from what
# the calls before left in $GPU_DIR (/tmp/gpu; training.calls plans those calls, scripts/prepare_gpu_round.sh
# makes their folders):
#   packs/*.npz             the DiT's training scenes          aux/val.npz    held-out scenes for the DiT's pick
#   aux/test.npz            the test split (scored, not used)  aux/model/     the shipped model folder (the start)
#   refit/*.npz             scenes the DiT never trains on     aux/refit-val.npz  held-out scenes for the refiners
# Hands back in $OUT (≤ 8 files, ≤ 16 MiB each): the picked DiT as dit-shard-*.safetensors + config.json, the two
# refiners in bf16 (refiner.safetensors, relit_refiner.safetensors) and round.tar.gz (logs, pick.json, best-*.json).
#   OUT=$OUT COMPILE=1 bash scripts/gpu_whole_round.sh 5.5 2
# Here: fast.merge_shards, training.assemble --like models/default --dit … --refiner … --relit-refiner … --bf16,
# then calibrate (--write, --strengths) and evaluate on 400 test items against the shipped model (docs/TRAINING.md).
set -uo pipefail
cd "$(dirname "$0")/.."
dit_minutes=${1:?usage: gpu_whole_round.sh DIT_MINUTES REFIT_MINUTES}
refit_minutes=${2:?usage: gpu_whole_round.sh DIT_MINUTES REFIT_MINUTES}
gpu=${GPU_DIR:-/tmp/gpu}
result=${OUT:?OUT: where the results go}
work=$gpu/work
rm -rf "$work"
mkdir -p "$work" "$result"
started=$(date +%s)
OUT=$work/round RUNS_DIR=$work/round-runs PACKS="$gpu/packs/*.npz" VAL=$gpu/aux/val.npz TEST=$gpu/aux/test.npz \
  INIT=$gpu/aux/model bash scripts/gpu_round.sh "$dit_minutes"
echo "the DiT's round took $(( $(date +%s) - started )) s"
status=1
if compgen -G "$work/round/dit-shard-*.safetensors" > /dev/null; then
  cp "$work"/round/dit-shard-*.safetensors "$work/round/config.json" "$result/"
  OUT=$work/refit RUNS_DIR=$work/refit-runs DIT=$work/round LIKE=$gpu/aux/model PACKS="$gpu/refit/*.npz" \
    VAL=$gpu/aux/refit-val.npz bash scripts/gpu_refine.sh "$refit_minutes" && status=0
  cp "$work"/refit/*.safetensors "$result/" 2>/dev/null
else
  echo "the DiT's round wrote no shards: see its logs in round.tar.gz"
fi
(cd "$work" && tar czf "$result/round.tar.gz" --ignore-failed-read round/pick.json round/log-*.txt refit/best-*.json \
  refit/log-*.txt 2>/dev/null)
echo "all in $(( $(date +%s) - started )) s"
ls -l "$result"
exit $status
