"""How much the one-step result depends on the noise draw: seeds 0..K−1 of the same model on the first N test
items, fp32; each seed's mean PSNR, the spread between two seeds, and the mean of the K results paired with seed 0.
    PYTHONPATH=. python runs/shift-average/seeds.py N K MODEL
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter

torch.set_num_threads(int(os.environ.get("T", "2")))
n, k, model = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", n)
r = Relighter.load(model, device="cpu", precision="fp32")
outs = [[relight(r, it.input, it.probe, RunOptions(seed=s))[:2] for it in items] for s in range(k)]


def score(rel, alb):
    return (np.array([protocol_metrics(rel[i], it.target, it.mask)["psnr"] for i, it in enumerate(items)]),
            np.array([protocol_metrics(alb[i], it.albedo, it.mask)["psnr"] for i, it in enumerate(items)]))


scores = [score([o[0] for o in out], [o[1] for o in out]) for out in outs]
for s, (a, b) in enumerate(scores):
    print(f"seed {s}: relit {a.mean():.3f} albedo {b.mean():.3f}")
diff = np.abs(np.stack([o[0] for o in outs[0]]) - np.stack([o[0] for o in outs[1]]))
print(f"mean |seed 0 − seed 1| relit {diff.mean() * 255:.2f}/255")
mean = score(np.mean([[o[0] for o in out] for out in outs], 0), np.mean([[o[1] for o in out] for out in outs], 0))
for j, name in enumerate(("relit", "albedo")):
    d = mean[j] - scores[0][j]
    print(f"mean of {k} seeds {name}: {mean[j].mean():.3f} paired {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}")
