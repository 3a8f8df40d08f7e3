"""The input mix's weight m a refiner gives on some test items (the mean over the frame): the items where the
input helps most (44–47, 74–75, 50, 63: the largest gains in runs/input-mix/alpha.txt) and others.
    PYTHONPATH=. python runs/input-mix/mixdiag.py MODEL_FOLDER [CHECKPOINT.pt [ema|model]]
"""
import sys
from pathlib import Path

import torch
from torch.nn import functional as F

from relight_core import refiner as R
from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.pipeline import Relighter

torch.set_num_threads(1)
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", 80)
r = Relighter.load(sys.argv[1], device="cpu", precision="fp32")
if len(sys.argv) > 2:           # a training checkpoint's EMA (or raw) weights instead of the folder's
    which = sys.argv[3] if len(sys.argv) > 3 else "ema"
    r.relit_refiner.load_state_dict(torch.load(sys.argv[2], map_location="cpu", weights_only=True)[which])
mixes = []
correction = r.relit_refiner.correction


def watched(x, panoramas=None):
    delta = correction(x, panoramas)
    z = F.avg_pool2d(delta[:, 9:10] * r.relit_refiner.config.strength, r.relit_refiner.config.relit_gain)
    mixes.append(torch.sigmoid(R.MIX_SCALE * z - R.MIX_OFFSET).mean().item())
    return delta


r.relit_refiner.correction = watched
index = [44, 45, 46, 47, 74, 75, 50, 63, 0, 1, 2, 10, 20, 30]
for i in index:
    relight(r, items[i].input, items[i].probe, RunOptions())
print({i: round(m, 3) for i, m in zip(index, mixes)})
