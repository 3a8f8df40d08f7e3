"""Does taking more of the input's shading out of the albedo help? The shipped albedo keeps ~17 % of the input's
shading (runs/shadow-follow/). The shading left in the input by the albedo, S = input / albedo (luminance, blurred
by σ px), is divided out of the albedo again to the power α: albedo' = albedo · S^(−α). Scored by the protocol on
test items, paired against α = 0 (± SE over items). Outputs are cached in CACHE.npz.
    PYTHONPATH=. python runs/albedo-deshade/probe.py SKIP COUNT MODEL CACHE.npz
"""
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from relight_core.colour import srgb_to_linear, linear_to_srgb
from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter

torch.set_num_threads(int(os.environ.get("T", "2")))
skip, count, model, cache = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], Path(sys.argv[4])
items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", count, skip=skip)
if cache.exists():
    albedos = np.load(cache)["albedo"]
else:
    r = Relighter.load(model, device="cpu", precision="fp32")
    albedos = np.stack([relight(r, it.input, it.probe, RunOptions())[1] for it in items])
    np.savez_compressed(cache, albedo=albedos)
Y = np.array([0.2126, 0.7152, 0.0722])


def deshade(albedo, source, alpha, sigma):
    a, s = srgb_to_linear(np.clip(albedo, 0, 1)), srgb_to_linear(np.clip(source, 0, 1))
    log_s = np.log(s @ Y + 1e-3) - np.log(a @ Y + 1e-3)
    if sigma:
        log_s = np.stack([cv2.GaussianBlur(f.astype(np.float32), (0, 0), sigma) for f in log_s])
    return np.clip(linear_to_srgb(a * np.exp(-alpha * log_s)[..., None]), 0, 1)


base = np.array([protocol_metrics(albedos[i], it.albedo, it.mask)["psnr"] for i, it in enumerate(items)])
print(f"{len(items)} items from {skip}: albedo as shipped {base.mean():.3f}")
for sigma in (0, 2, 6):
    for alpha in (0.1, 0.2, 0.3):
        s = np.array([protocol_metrics(deshade(albedos[i], it.input, alpha, sigma), it.albedo, it.mask)["psnr"]
                      for i, it in enumerate(items)])
        d = s - base
        print(f"σ {sigma} α {alpha}: {s.mean():.3f} paired {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}")
