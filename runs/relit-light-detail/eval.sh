#!/usr/bin/env bash
# Score a candidate model folder (a relit refiner trained by `training.refine --model-dir`, strength 1) against
# the shipped model: fit the relit refiner's strength on the 48 held-out calibration items (written into the
# candidate's config.json), then evaluate the 80 test items in fp32 and pair them with the shipped model's run.
#   bash runs/relit-light-detail/eval.sh NAME      (candidate in ~/.cache/unirelight-studio/cand-NAME)
set -euo pipefail
cd "$(dirname "$0")/../.."
C=~/.cache/unirelight-studio
name=${1:?usage: eval.sh NAME}
here=runs/relit-light-detail
.venv/bin/python -m relight_core.training.calibrate --model "$C/cand-$name" --data "$C/data" --split test --skip 16 \
  --items 48 --strengths --size 128 --write > "$here/$name-calibrate-strengths.txt" 2>&1
.venv/bin/python -m relight_core evaluate --data "$C/data" --split test --model "$C/cand-$name" --limit 80 \
  --train-items 0 --sigma-items 0 --precision fp32 --size 128 --no-grids --out "$C/eval/$name-80" > /dev/null 2>&1
{ echo "== $name against the shipped model (80 test items, fp32)"; grep -o '"strength": [0-9.]*' "$C/cand-$name/config.json";
  .venv/bin/python runs/default-128-s18r/paired.py "$C/eval/shipped-S23-80" "$C/eval/$name-80" --unseen; } | tee "$here/$name-paired.txt"
