"""Validation albedo of refiners' weights averaged (a "soup" of runs that start from the same weights):
python soup.py OUT.safetensors A.safetensors B.safetensors [...] — scores each one and their mean, writes the mean."""
import sys

import torch
from safetensors.torch import load_file, save_file

from relight_core.training import refine as R
from valdata import bf16, refiner, validation

torch.set_num_threads(2)
data = validation("filtered")


def score(model) -> float:
    return R.validate(model, data, autocast=bf16())["albedo"]


states = [{k: v.float() for k, v in load_file(p).items()} for p in sys.argv[2:]]
for path in sys.argv[2:]:
    print(f"{path}: albedo {score(refiner(path))}", flush=True)
mean = {k: sum(s[k] for s in states) / len(states) for k in states[0]}
save_file(mean, sys.argv[1])
print(f"mean of {len(states)}: albedo {score(refiner(sys.argv[1]))}", flush=True)
