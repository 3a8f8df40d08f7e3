"""Does the albedo refiner's correction carry over to the relit frames? On the 80 test items (fp32, outputs
cached by runs/refiner-strength/ens.py): relit × ((refined albedo + e) / (DiT albedo + e))^β, in sRGB and in
linear light, from the shipped relit frames (S23) and from the DiT's (noref), optionally the ratio blurred.
    PYTHONPATH=. python runs/albedo-transfer/transfer.py /tmp/ens/out2
"""
import sys
from pathlib import Path

import numpy as np
import cv2

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics

out = Path(sys.argv[1])
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", 80)
S = np.load(out / "S23.npz")
D = np.load(out / "noref.npz")
alb_ref, alb_dit = S["albedo"].astype(np.float64), D["albedo"].astype(np.float64)


def lin(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb(x):
    x = np.clip(x, 0, None)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055)


def psnr(P):
    return np.array([protocol_metrics(np.clip(P[i], 0, 1).astype(np.float32), it.target, it.mask)["psnr"]
                     for i, it in enumerate(items)])


base = {name: z["relit"].astype(np.float64) for name, z in (("S23", S), ("noref", D))}
ref = psnr(base["S23"])
print("shipped relit", ref.mean().round(3), " DiT relit", psnr(base["noref"]).mean().round(3))
for name, relit in base.items():
    for space in ("srgb", "linear"):
        for e in (0.02, 0.05):
            for blur in (0, 2):
                a, b = (alb_ref, alb_dit) if space == "srgb" else (lin(alb_ref), lin(alb_dit))
                ratio = (a + e) / (b + e)
                if blur:
                    ratio = np.stack([cv2.GaussianBlur(f, (0, 0), blur) for f in ratio.reshape(-1, *ratio.shape[2:])]).reshape(ratio.shape)
                for beta in (0.25, 0.5, 1.0):
                    r = ratio ** beta
                    p = relit * r if space == "srgb" else srgb(lin(relit) * r)
                    s = psnr(p)
                    d = s - ref
                    print(f"{name} {space} e={e} blur={blur} β={beta}: {s.mean():.3f}  paired vs shipped "
                          f"{d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}", flush=True)
