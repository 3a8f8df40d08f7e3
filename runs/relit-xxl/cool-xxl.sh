#!/bin/bash
# Ran from ~/.cache/unirelight-studio/refine (nohup ./cool-xxl.sh > relit-G4xxl-cool.log); REPO is the repository root
# at the first validation past 98 min: stop the lr-3e-4 run once its checkpoint is written, resume at lr 1e-4 to 115 min
C=~/.cache/unirelight-studio; D=$C/refine/relit-G4xxl
cd "${REPO:-/work/main}"
while true; do
  m=$(tail -n 1 $D/log.jsonl | python3 -c 'import json,sys; print(json.loads(sys.stdin.read())["minutes"])')
  if python3 -c "import sys; sys.exit(0 if $m >= 98 else 1)" && [ $D/checkpoint.pt -nt $D/log.jsonl ]; then break; fi
  sleep 5
done
sleep 3
pkill -f "relit-G4xxl --seed 36"; sleep 5
echo "cooldown from $m min" 
.venv/bin/python -m relight_core.training.refine --model models/default --pack $C/train-s5-20k.npz --scenes 20000 \
  --val-pack $C/s5/val.npz --widths 24 48 96 128 256 --lighting --clips relit --flip-average --permute-colours \
  --slot relit_refiner --same-scenes 500 --threads 2 --val-every-minutes 4 --relit-gain 4 --lr 1e-4 \
  --minutes 115 --out $D --seed 36 --model-dir $C/cand-G4xxl
