"""Upper bounds on the 80 test items for what a relit refiner could gain by mixing in the input (its own frames
cached by runs/refiner-strength/ens.py: S23.npz = the shipped model, noRR.npz = the same without the relit refiner):
  * one mix weight per item, input·a + shipped·(1 − a): the same a for all, and the best a for each item (oracle);
  * one mix weight per k×k cell, the best for each cell (oracle; least squares on the target, clipped to [0, 1]);
  * one gain per k×k cell and channel on the shipped frames, on the DiT's, on the input (oracle).
    PYTHONPATH=. python runs/input-mix/oracles.py /tmp/ens/out2/S23.npz /tmp/ens/out/noRR.npz
"""
import sys
from pathlib import Path

import numpy as np

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics

items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", 80)
S = np.load(sys.argv[1])["relit"].astype(np.float64)[:, 0]
N = np.load(sys.argv[2])["relit"].astype(np.float64)[:, 0]
X = np.stack([it.input for it in items]).astype(np.float64)[:, 0]
T = np.stack([it.target for it in items]).astype(np.float64)[:, 0]


def psnr(P):
    return np.array([protocol_metrics(P[i][None].astype(np.float32), items[i].target, items[i].mask)["psnr"]
                     for i in range(len(items))])


def cells(A, c):        # [n,h,w,3] -> [n,h/c,w/c,c*c,3]
    n, h, w, k = A.shape
    return A.reshape(n, h // c, c, w // c, c, k).transpose(0, 1, 3, 2, 4, 5).reshape(n, h // c, w // c, c * c, k)


def uncells(A, c):
    n, hh, ww, _, k = A.shape
    return A.reshape(n, hh, ww, c, c, k).transpose(0, 1, 3, 2, 4, 5).reshape(n, hh * c, ww * c, k)


print(f"shipped {psnr(S).mean():.3f}  without the relit refiner {psnr(N).mean():.3f}  floor {psnr(X).mean():.3f}")
grid = np.linspace(0, 1, 11)
table = np.stack([psnr((1 - a) * S + a * X) for a in grid])
print("one weight for all:", " ".join(f"{a:.1f}:{r.mean():.3f}" for a, r in zip(grid, table)))
print(f"the best weight per item (oracle): {table.max(0).mean():.3f}")
for c in (16, 8, 4):
    s, d, t = cells(S, c), cells(X - S, c), cells(T - S, c)
    w = np.clip((d * t).sum((3, 4), keepdims=True) / np.maximum((d * d).sum((3, 4), keepdims=True), 1e-9), 0, 1)
    print(f"the best weight per {c}-px cell (oracle): {psnr(uncells(s + w * d, c)).mean():.3f}")
for c in (16, 8, 4):
    out = []
    for B in (S, N, X):
        b, t = cells(B + 0.02, c), cells(T + 0.02, c)
        r = (b * t).sum(3, keepdims=True) / np.maximum((b * b).sum(3, keepdims=True), 1e-9)
        out.append(psnr(np.clip(uncells(b * r, c) - 0.02, 0, 1)).mean())
    print(f"the best gain per {c}-px cell (oracle) on the shipped frames {out[0]:.3f}, the DiT's {out[1]:.3f}, "
          f"the input {out[2]:.3f}")
