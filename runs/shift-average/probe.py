"""Does averaging the model over sub-token shifts help? The DiT sees 8×8-pixel tokens; the input rolled by
(dy, dx) pixels, relit, rolled back, averaged with the plain result (the rolled-in border strips keep the plain
result). Paired on the first N test items, fp32.
    PYTHONPATH=. python runs/shift-average/probe.py N MODEL
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
n, model = int(sys.argv[1]), sys.argv[2]
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", n)
r = Relighter.load(model, device="cpu", precision="fp32")
SHIFTS = [(0, 0), (4, 4), (4, 0), (0, 4)]
outs = {s: ([], []) for s in SHIFTS}
for it in items:
    for dy, dx in SHIFTS:
        x = np.roll(it.input, (dy, dx), axis=(-3, -2))
        a, b, _ = relight(r, x, it.probe, RunOptions())
        a, b = (np.roll(v, (-dy, -dx), axis=(-3, -2)) for v in (a, b))
        outs[(dy, dx)][0].append(a)
        outs[(dy, dx)][1].append(b)
outs = {s: (np.stack(a), np.stack(b)) for s, (a, b) in outs.items()}


def score(rel, alb):
    return (np.array([protocol_metrics(rel[i], it.target, it.mask)["psnr"] for i, it in enumerate(items)]),
            np.array([protocol_metrics(alb[i], it.albedo, it.mask)["psnr"] for i, it in enumerate(items)]))


def average(shifts):
    rel = np.mean([outs[s][0] for s in shifts], 0)
    alb = np.mean([outs[s][1] for s in shifts], 0)
    base_r, base_a = outs[(0, 0)]
    border = np.zeros(rel.shape[-3:-1], bool)
    border[:4], border[-4:], border[:, :4], border[:, -4:] = True, True, True, True
    rel[..., border, :] = base_r[..., border, :]
    alb[..., border, :] = base_a[..., border, :]
    return rel, alb


base = score(*outs[(0, 0)])
print(f"plain: relit {base[0].mean():.3f} albedo {base[1].mean():.3f}")
for shifts in (SHIFTS[:2], SHIFTS):
    s = score(*average(shifts))
    for k, name in enumerate(("relit", "albedo")):
        d = s[k] - base[k]
        print(f"{len(shifts)} shifts {name}: {s[k].mean():.3f}  paired {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}")
