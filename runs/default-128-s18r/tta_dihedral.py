"""Test-time averaging of the shipped refiner's albedo correction over the square's symmetries (validation):
plain, left-right (shipped), + up-down, all 8 (with transposes)."""
import sys

import torch

from relight_core.training import refine as R
from valdata import bf16, refiner, validation

torch.set_num_threads(2)
data = validation("filtered")
m = refiner(sys.argv[1] if len(sys.argv) > 1 else None)
ops = {  # (forward, inverse) on [..., H, W]
    "id": (lambda t: t, lambda t: t),
    "lr": (lambda t: t.flip(-1), lambda t: t.flip(-1)),
    "ud": (lambda t: t.flip(-2), lambda t: t.flip(-2)),
    "rot180": (lambda t: t.flip(-1, -2), lambda t: t.flip(-1, -2)),
    "T": (lambda t: t.transpose(-1, -2), lambda t: t.transpose(-1, -2)),
    "T-lr": (lambda t: t.transpose(-1, -2).flip(-1), lambda t: t.flip(-1).transpose(-1, -2)),
    "T-ud": (lambda t: t.transpose(-1, -2).flip(-2), lambda t: t.flip(-2).transpose(-1, -2)),
    "T-rot": (lambda t: t.transpose(-1, -2).flip(-1, -2), lambda t: t.flip(-1, -2).transpose(-1, -2)),
}
sets = {"filtered (no refiner)": [], "plain": ["id"], "lr (shipped)": ["id", "lr"], "ud alone": ["ud"],
        "lr+ud (4)": ["id", "lr", "ud", "rot180"], "all 8": list(ops)}
res = {k: [] for k in sets}
with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16()):
    for s in range(0, len(data["input"]), 32):
        x, r, a, _ = R.model_inputs(data, slice(s, s + 32), "filtered")
        outs = {k: inv(m(f(x)).float()[:, 3:]) for k, (f, inv) in ops.items()}
        for name, keys in sets.items():
            d = torch.stack([outs[k] for k in keys]).mean(0) if keys else 0
            res[name].append(((a + d).clamp(-1, 1) + 1) / 2)
for k, v in res.items():
    A = torch.cat(v).permute(0, 2, 3, 1).numpy()
    print(f"{k}: albedo {R.scores(data, A, A)['albedo']}", flush=True)
