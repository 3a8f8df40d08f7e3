"""The model's relit and albedo outputs for every item of a clip split, cached for choose*.py (1 thread).
    PYTHONPATH=. python runs/video-temporal/cache_outputs.py DATA MODEL OUT.npz
"""
import sys
from pathlib import Path
import numpy as np
import torch
from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.pipeline import Relighter
torch.set_num_threads(1)
data, model, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
items = load_items(data, "test")
r = Relighter.load(model, device="cpu", precision="fp32")
save = {}
for i, it in enumerate(items):
    relit, albedo, _ = relight(r, it.input, it.probe, RunOptions())
    save[f"relit{i}"] = relit; save[f"albedo{i}"] = albedo
np.savez_compressed(out, **save)
print("done", len(items))
