#!/usr/bin/env bash
# Score a candidate model folder (a relit refiner trained by `training.refine --model-dir`, strength 1) against
# the shipped model on the 400 test items: fit the relit refiner's strength on the 48 held-out calibration items
# (test items 16–63, written into the candidate's config.json), evaluate all 400 in fp32, and pair them per item
# with the shipped model's run (eval/shipped-S24-400, or eval/$BASE), ± the standard error over scenes; the
# reports go to runs/relit-transport (or $HERE).
#   [BASE=SA2-400 HERE=runs/refiner-copies] bash runs/relit-transport/eval.sh NAME   (candidate in ~/.cache/unirelight-studio/cand-NAME)
set -euo pipefail
cd "$(dirname "$0")/../.."
C=~/.cache/unirelight-studio
name=${1:?usage: eval.sh NAME}
here=${HERE:-runs/relit-transport}
base=${BASE:-shipped-S24-400}
.venv/bin/python -m relight_core.training.calibrate --model "$C/cand-$name" --data "$C/data" --split test --skip 16 \
  --items 48 --strengths --size 128 --write > "$here/$name-calibrate-strengths.txt" 2>&1
.venv/bin/python -m relight_core evaluate --data "$C/data" --split test --model "$C/cand-$name" --limit 400 \
  --train-items 0 --sigma-items 0 --precision fp32 --size 128 --no-grids --out "$C/eval/$name-400" > /dev/null 2>&1
{ echo "== $name against the shipped model (400 test items, fp32)"; grep -o '"strength": [0-9.]*' "$C/cand-$name/config.json";
  PYTHONPATH=. .venv/bin/python runs/test-400/spread.py "$C/eval/$base" "$C/eval/$name-400"; } | tee "$here/$name-400-paired.txt"
