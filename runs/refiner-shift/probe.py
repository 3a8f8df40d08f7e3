"""Does averaging the refiners over a half-step shift of their coarsest grid help? The refiners' U-Net halves
the frame four times, so its bottom level sees 16×16-pixel cells; here each refiner's correction is averaged
with the one it makes on the frames padded by S px (reflected) on every side, cropped back — its grid S px off.
Each item runs twice, the same seed (the DiT's frames alike), without and with it; paired on the first N test items, fp32.
    PYTHONPATH=. python runs/refiner-shift/probe.py N MODEL [S]
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter
from relight_core.refiner import Refiner

torch.set_num_threads(int(os.environ.get("T", "2")))
n, model = int(sys.argv[1]), sys.argv[2]
shift = int(sys.argv[3]) if len(sys.argv) > 3 else 8
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", n)
r = Relighter.load(model, device="cpu", precision="fp32")
plain_mirrored = Refiner._mirrored
SHIFTED = {"on": False}


def mirrored(self, x, panoramas):
    out = plain_mirrored(self, x, panoramas)
    if not SHIFTED["on"]:
        return out
    h, w = x.shape[-2:]
    moved = plain_mirrored(self, F.pad(x, (shift,) * 4, mode="reflect"), panoramas)[..., shift:shift + h, shift:shift + w]
    return (out + moved) / 2


Refiner._mirrored = mirrored
scores = {False: ([], []), True: ([], [])}
for it in items:
    for on in (False, True):
        SHIFTED["on"] = on
        relit, albedo, _ = relight(r, it.input, it.probe, RunOptions())
        scores[on][0].append(protocol_metrics(relit, it.target, it.mask)["psnr"])
        scores[on][1].append(protocol_metrics(albedo, it.albedo, it.mask)["psnr"])
for k, name in enumerate(("relit", "albedo")):
    base, new = np.array(scores[False][k]), np.array(scores[True][k])
    d = new - base
    print(f"{name}: plain {base.mean():.3f}  shifted {shift} px {new.mean():.3f}  paired {d.mean():+.3f} ± "
          f"{d.std(ddof=1) / np.sqrt(len(d)):.3f} (over items)  items 80+: {d[80:].mean() if len(d) > 80 else float('nan'):+.3f}")
