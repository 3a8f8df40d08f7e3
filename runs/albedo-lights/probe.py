"""Does the albedo gain from averaging over target lights? The albedo should not depend on the target probe,
yet the joint DiT predicts it under one; each item's albedo is made again under the same camera-frame probe
turned by 90°, 180° and 270° (rolled along its longitude) and with no probe (mode "albedo"), and averages are
scored against the albedo as shipped (the target probe alone). Paired on the first N test items, fp32.
    PYTHONPATH=. python runs/albedo-lights/probe.py N MODEL [OUT.npz]
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter
from relight_core.requests import RelightRequest

torch.set_num_threads(int(os.environ.get("T", "2")))
n, model = int(sys.argv[1]), sys.argv[2]
items = load_items(Path(os.environ.get("DATA", Path.home() / ".cache/unirelight-studio/data")), "test", n)
r = Relighter.load(model, device="cpu", precision="fp32")
VARIANTS = ["0", "90", "180", "270", "none"]
albedo = {v: [] for v in VARIANTS}
relit0 = []
for it in items:
    width = it.probe.shape[-2]
    for v in VARIANTS:
        if v == "none":
            out = r.relight(RelightRequest(it.input, mode="albedo")).albedo
        else:
            probe = np.roll(it.probe, int(v) * width // 360, axis=-2)
            rel, out, _ = relight(r, it.input, probe, RunOptions())
            if v == "0":
                relit0.append(rel)
        albedo[v].append(out)
albedo = {v: np.stack(a) for v, a in albedo.items()}
if len(sys.argv) > 3:
    np.savez_compressed(sys.argv[3], **albedo, relit0=np.stack(relit0))


def score(alb):
    return np.array([protocol_metrics(alb[i], it.albedo, it.mask)["psnr"] for i, it in enumerate(items)])


base = score(albedo["0"])
print(f"{len(items)} items; as shipped (target probe): albedo {base.mean():.3f}")
for name, chosen in [("no probe", ["none"]), ("0+180", ["0", "180"]), ("0+90+180+270", ["0", "90", "180", "270"]),
                     ("4 turns + no probe", VARIANTS), ("0 + no probe", ["0", "none"])]:
    s = score(np.mean([albedo[v] for v in chosen], 0))
    d = s - base
    print(f"{name:22s} albedo {s.mean():.3f}  paired {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f} "
          f"({(d > 0).sum()} up, {(d < 0).sum()} down)")
