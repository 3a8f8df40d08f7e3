#!/bin/bash
# Ran from ~/.cache/unirelight-studio/refine (./eval-xxl.sh [MODEL NAME] > eval-NAME.log); REPO is the repository root
C=~/.cache/unirelight-studio; cd "${REPO:-/work/main}"
while pgrep -f "relight_core.training.refine" >/dev/null; do sleep 5; done
M=${1:-$C/cand-G4xxl}; N=${2:-G4xxl-80}
.venv/bin/python -m relight_core evaluate --data $C/data --split test --model $M --limit 80 --train-items 0 \
  --sigma-items 0 --precision fp32 --size 128 --no-grids --out $C/eval/$N
.venv/bin/python runs/default-128-s18r/paired.py $C/eval/G4xl-80 $C/eval/$N --unseen
.venv/bin/python runs/default-128-s18r/paired.py $C/eval/A-E1-80 $C/eval/$N --unseen
(cd $C && python3 "${REPO:-/work/main}"/runs/relit-xl/byprobe.py A-E1-80 $N; python3 "${REPO:-/work/main}"/runs/relit-xl/byprobe.py G4xl-80 $N)
PYTHONPATH=. .venv/bin/python runs/relit-gain/example_check.py /tmp/example-$N.png models/default $M
