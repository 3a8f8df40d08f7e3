#!/bin/bash
# Ran from ~/.cache/unirelight-studio/refine (nohup ./chain-xxl.sh > relit-G4xxl-run.log); REPO is the repository root
C=~/.cache/unirelight-studio
cd "${REPO:-/work/main}"
while pgrep -f "outputs.py shard" >/dev/null; do sleep 10; done
PYTHONPATH=. .venv/bin/python runs/relit-xxl/outputs.py merge 2 || exit 1
cp $C/refine/relit-G4xl/checkpoint.pt $C/refine/relit-G4xl/outputs-val.npz $C/refine/relit-G4xl/best.json $C/refine/relit-G4xl/refiner.safetensors $C/refine/relit-G4xxl/
.venv/bin/python -m relight_core.training.refine --model models/default --pack $C/train-s5-20k.npz --scenes 20000 \
  --val-pack $C/s5/val.npz --widths 24 48 96 128 256 --lighting --clips relit --flip-average --permute-colours \
  --slot relit_refiner --same-scenes 500 --threads 2 --val-every-minutes 6 --relit-gain 4 --lr 3e-4 \
  --minutes 115 --out $C/refine/relit-G4xxl --seed 36 --model-dir $C/cand-G4xxl
