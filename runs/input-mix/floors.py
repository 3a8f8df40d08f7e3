"""How often a pair's two probes light the scene alike: the share of items whose input is within k dB of the
target (the protocol's PSNR, `refine.input_floors`), in the relit refiners' training packs and on the 80 test items.
    PYTHONPATH=. python runs/input-mix/floors.py
"""
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.training.pack import load_packs
from relight_core.training.refine import input_floors

C = Path.home() / ".cache/unirelight-studio"
pack = load_packs([C / "train-s5x.npz", C / "train-s7.npz"])
both = {"input": torch.cat([pack["rgb"][:, 0], pack["rgb"][:, 1]]), "target": torch.cat([pack["rgb"][:, 1], pack["rgb"][:, 0]]),
        "mask": torch.cat([pack["mask"], pack["mask"]])}             # each scene in both directions
train = input_floors(both).numpy()
test = np.array([protocol_psnr(it.input, it.target, it.mask) for it in load_items(C / "data", "test", 80)])
for name, x in (("training items", train), ("test items", test)):
    print(f"{name}: {len(x)}, mean floor {x.mean():.2f} dB; " + ", ".join(f"≥ {k} dB {np.mean(x >= k) * 100:.1f} %"
                                                                          for k in (22, 24, 26, 28, 30)))
