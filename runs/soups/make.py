"""A model folder whose refiner in SLOT is the weighted mean of refiner weight files that start from one
refiner (a "soup"): a tensor one file lacks (a layer its config does not have) counts as zeros, and a smaller one
(the FiLM of a refiner without light_detail / film_encoder) is zero-padded at the end of each axis, which is how
`training.refine.initial_weights` grows such a refiner. The rest of the folder is copied from BASE.
    PYTHONPATH=. python runs/soups/make.py BASE OUT SLOT W1:FILE1 W2:FILE2 ...
"""
import shutil
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.refiner import REFINER_SLOTS

base, out, slot = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
parts = [(float(w), load_file(f)) for w, f in (a.split(":", 1) for a in sys.argv[4:])]
reference = load_file(base / REFINER_SLOTS[slot])
soup = {}
for key, value in reference.items():
    total = torch.zeros(value.shape, dtype=torch.float64)
    for weight, state in parts:
        if key in state:
            part = state[key].double()
            if any(a > b for a, b in zip(part.shape, value.shape)) or part.dim() != value.dim():
                raise SystemExit(f"{key}: {tuple(part.shape)} does not fit in {tuple(value.shape)}")
            total[tuple(slice(0, n) for n in part.shape)] += weight * part
    soup[key] = (total / sum(w for w, _ in parts)).to(value.dtype)
out.mkdir(parents=True, exist_ok=True)
for f in base.iterdir():
    if f.is_file() and f.name != REFINER_SLOTS[slot]:
        shutil.copy2(f, out / f.name)
save_file(soup, str(out / REFINER_SLOTS[slot]))
missing = {k for _, s in parts for k in reference if k not in s}
print(f"{out}: {slot} = mean of {len(parts)}; zero-filled in some: {sorted(missing)[:6]}{'…' if len(missing) > 6 else ''}")
