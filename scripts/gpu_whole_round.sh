#!/usr/bin/env bash
# A whole round on a GPU machine in one call: the DiT trained on (scripts/gpu_round.sh, DIT_MINUTES), then the
# model's two refiners fitted again to what the new DiT makes (scripts/gpu_refine.sh, REFIT_MINUTES), from what
# the calls before left in $GPU_DIR (/tmp/gpu; training.calls plans those calls, scripts/prepare_gpu_round.sh
# makes their folders):
#   packs/*.npz             the DiT's training scenes          aux/val.npz    held-out scenes for the DiT's pick
#   aux/test.npz            the test split (scored, not used)  aux/model/     the shipped model folder (the start)
#   refit/*.npz             scenes the DiT never trains on     aux/refit-val.npz  held-out scenes for the refiners
#                                                              (absent: aux/val.npz serves them too)
# Hands back in $OUT (≤ 8 files, ≤ 16 MiB each): the picked DiT as dit-shard-*.safetensors + config.json, the two
# refiners in bf16 (refiner.safetensors, relit_refiner.safetensors) and round.tar.gz (logs, pick.json, best-*.json).
#   OUT=$OUT COMPILE=1 bash scripts/gpu_whole_round.sh 5.5 2
# Here: fast.merge_shards, training.assemble --like models/default --dit … --refiner … --relit-refiner … --bf16,
# then calibrate (--write, --strengths) and evaluate on 400 test items against the shipped model (docs/TRAINING.md).
# Before anything runs, the files the calls brought are checked against the plan's list ($GPU_DIR/round-files.txt,
# which the last call carries): one missing (a machine given back between calls loses /tmp) stops the round at once
# (exit 3, missing.txt in $OUT). LIMIT_S (590): the seconds the command may run (the device's timeout_s, less a
# little); the refit gets at most what the DiT's round leaves of them (less REFIT_OVERHEAD_S, 150, for loading, the
# DiT's outputs and the hand-back), runs under `timeout`, and if stopped still hands back each refiner's best EMA
# so far. round.tar.gz is written once the DiT's round is done and again at the end; failures.txt in it names runs
# that exited with an error.
set -uo pipefail
cd "$(dirname "$0")/.."
dit_minutes=${1:?usage: gpu_whole_round.sh DIT_MINUTES REFIT_MINUTES}
refit_minutes=${2:?usage: gpu_whole_round.sh DIT_MINUTES REFIT_MINUTES}
gpu=${GPU_DIR:-/tmp/gpu}
result=${OUT:?OUT: where the results go}
work=$gpu/work
limit=${LIMIT_S:-590}
started=$(date +%s)
mkdir -p "$result"
if [[ -f $gpu/round-files.txt ]]; then
  missing=()
  while read -r size dest; do
    [[ -f $gpu/$dest && $(stat -c %s "$gpu/$dest") == "$size" ]] || missing+=("$dest")
  done < "$gpu/round-files.txt"
  if (( ${#missing[@]} )); then
    printf '%s\n' "${missing[@]}" > "$result/missing.txt"
    echo "the machine lacks ${#missing[@]} of the round's files (${missing[*]:0:4}…): make the calls that carry them" \
      "again (calls.md), then this one; nothing was run"
    exit 3
  fi
  echo "all $(wc -l < "$gpu/round-files.txt") files of the round are here"
else
  echo "no round-files.txt in $gpu: the files the calls brought are not checked"
fi
rm -rf "$work"
mkdir -p "$work"
hand_logs() {      # the logs so far, in one file of $OUT (written again at the end)
  (cd "$work" && tar czf "$result/round.tar.gz" --ignore-failed-read round/pick.json round/log-*.txt \
    round/failures.txt refit/best-*.json refit/log-*.txt refit/failures.txt 2>/dev/null)
}
OUT=$work/round RUNS_DIR=$work/round-runs PACKS="$gpu/packs/*.npz" VAL=$gpu/aux/val.npz TEST=$gpu/aux/test.npz \
  INIT=$gpu/aux/model bash scripts/gpu_round.sh "$dit_minutes"
echo "the DiT's round took $(( $(date +%s) - started )) s"
hand_logs
status=1
if compgen -G "$work/round/dit-shard-*.safetensors" > /dev/null; then
  cp "$work"/round/dit-shard-*.safetensors "$work/round/config.json" "$result/"
  left=$(( limit - ($(date +%s) - started) - 20 ))       # seconds the refit may take, hand-back included
  refit_val=$gpu/aux/refit-val.npz
  [[ -f $refit_val ]] || refit_val=$gpu/aux/val.npz
  # the minutes asked for, or what the time left allows if less; none if that is under a quarter of a minute
  refit_minutes=$(awk -v asked="$refit_minutes" -v left="$left" -v overhead="${REFIT_OVERHEAD_S:-150}" \
    'BEGIN { m = (left - overhead) / 60; if (asked <= m) m = asked; else if (m < 0.25) m = 0; printf "%.3g", m }')
  refit=(env OUT="$work/refit" RUNS_DIR="$work/refit-runs" DIT="$work/round" LIKE="$gpu/aux/model"
         PACKS="$gpu/refit/*.npz" VAL="$refit_val" bash scripts/gpu_refine.sh)
  mkdir -p "$work/refit"
  if awk -v m="$refit_minutes" 'BEGIN { exit !(m > 0) }'; then
    echo "the refit: $refit_minutes minutes of training, $left s in all"
    timeout --kill-after=5 "$(( left - 30 ))" "${refit[@]}" "$refit_minutes" && status=0
    rc=$?
    if (( rc == 124 || rc == 137 )); then      # stopped by the limit: hand back each refiner's best EMA so far
      echo "the refit ran out of time; handing back what its runs kept"
      echo "the refit was stopped at the time limit (exit status $rc)" >> "$work/refit/failures.txt"
      HAND_BACK=1 timeout 25 "${refit[@]}" 0
    fi
    cp "$work"/refit/*.safetensors "$result/" 2>/dev/null
  else
    echo "the DiT's round left $left s: too little for the refit; the DiT comes back with the refiners it started from"
  fi
else
  echo "the DiT's round wrote no shards: see its logs in round.tar.gz"
fi
hand_logs
echo "all in $(( $(date +%s) - started )) s"
ls -l "$result"
exit $status
