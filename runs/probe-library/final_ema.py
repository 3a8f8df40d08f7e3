"""The EMA a `training.refine` run ended with (its checkpoint's), as a refiner.safetensors — the run's
`refiner.safetensors` is its best by validation, which on the training engine's held-out scenes is the start or
near it; the question here is what the minutes of training did.

    PYTHONPATH=. python runs/probe-library/final_ema.py RUN_DIR OUT.safetensors
"""
import json
import sys

import torch
from safetensors.torch import save_file

saved = torch.load(f"{sys.argv[1]}/checkpoint.pt", map_location="cpu", weights_only=True)
save_file({k: v.detach().contiguous() for k, v in saved["ema"].items()}, sys.argv[2])
print(f"{sys.argv[1]}: the EMA at step {json.loads(saved['state']).get('step')} → {sys.argv[2]}")
