"""Does the shipped model's own frame say when to mix in the input? For each of the 80 test items: the best
single mix weight (input·a + shipped·(1 − a), a on a 0.1 grid) and its gain, beside how close the shipped frame
is to the input (the protocol's PSNR of one against the other) — a rule from that closeness would need the two
to go together.
    PYTHONPATH=. python runs/input-mix/alpha.py /tmp/ens/out2/S23.npz
"""
import sys
from pathlib import Path

import numpy as np

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics

items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", 80)
S = np.load(sys.argv[1])["relit"].astype(np.float64)
X = np.stack([it.input for it in items]).astype(np.float64)


def psnr(P):
    return np.array([protocol_metrics(P[i].astype(np.float32), items[i].target, items[i].mask)["psnr"] for i in range(80)])


grid = np.linspace(0, 1, 11)
table = np.stack([psnr((1 - a) * S + a * X) for a in grid])
best = grid[table.argmax(0)]
close = np.array([protocol_metrics(S[i].astype(np.float32), X[i].astype(np.float32), items[i].mask)["psnr"]
                  for i in range(80)])
for i in np.argsort(close):
    print(f"item {i:2d}  shipped vs input {close[i]:5.1f} dB  floor {table[-1, i]:5.1f}  shipped {table[0, i]:5.1f}  "
          f"best a {best[i]:.1f} ({table.max(0)[i] - table[0, i]:+.2f} dB)")
print(f"correlation of closeness and the best weight: {np.corrcoef(close, best)[0, 1]:+.2f}")
