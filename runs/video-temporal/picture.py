"""Frames 0, 4 and 8 of one test clip item: input | shipped relit without the filter | with it | target, and the
same for the albedo — to look for ghosts of moving things.
    PYTHONPATH=. python runs/video-temporal/picture.py DATA INDEX OUT.png
"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.pipeline import Relighter

data, index, out = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
item = load_items(data, "test")[index]
r = Relighter.load("default", device="cpu", precision="fp32")
steady = relight(r, item.input, item.probe, RunOptions())
r.spec = replace(r.spec, temporal_filter=(0,) + r.spec.temporal_filter[1:])
raw = relight(r, item.input, item.probe, RunOptions())
rows = []
for t in (0, 4, 8):
    rows.append(np.concatenate([item.input[t], raw[0][t], steady[0][t], item.target[t],
                                raw[1][t], steady[1][t], item.albedo[t]], axis=1))
Image.fromarray((np.clip(np.concatenate(rows), 0, 1) * 255).astype(np.uint8)).save(out)
print(item.name)
