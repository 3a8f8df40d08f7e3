#!/bin/bash
# ./runs/relit-deep/eval-deep.sh MODEL NAME (from the repo root): 80 test items, paired against the shipped model
# (eval/shipped-A40k-80) and against none (eval/A-E1-80: no relit refiner), by probe, and the example image.
C=~/.cache/unirelight-studio
M=$1; N=$2
.venv/bin/python -m relight_core evaluate --data $C/data --split test --model $M --limit 80 --train-items 0 \
  --sigma-items 0 --precision fp32 --size 128 --no-grids --out $C/eval/$N | tail -2
.venv/bin/python runs/default-128-s18r/paired.py $C/eval/shipped-A40k-80 $C/eval/$N --unseen
.venv/bin/python runs/default-128-s18r/paired.py $C/eval/A-E1-80 $C/eval/$N --unseen
(cd $C && python3 "$OLDPWD"/runs/relit-xl/byprobe.py shipped-A40k-80 $N)
PYTHONPATH=. .venv/bin/python runs/relit-gain/example_check.py /tmp/example-$N.png models/default $M
