"""Where the albedo (and relit) error is: an evaluate run's per-item scores grouped by what the scene holds (glass
objects, metal objects, objects, a textured ground) and by the input's and target's probe.
    PYTHONPATH=. python runs/albedo-glass/breakdown.py ~/.cache/unirelight-studio/eval/shipped-S24-400 [DATA_ROOT]
"""
import collections
import json
import sys
from pathlib import Path

import numpy as np

items = json.load(open(f"{sys.argv[1]}/metrics.json"))["test"]["per_item"]
root = Path(sys.argv[2] if len(sys.argv) > 2 else Path.home() / ".cache/unirelight-studio/data") / "test"
groups = collections.defaultdict(list)
for item in items:
    scene, direction = item["name"].split(" ")
    source, target = map(int, direction.split("→"))
    meta = json.load(open(root / scene / "meta.json"))
    objects = meta["scene"]["objects"]
    glass = sum(o["material"]["transmission"] > 0 for o in objects)
    metal = sum(o["material"]["metallic"] > 0 for o in objects)
    row = (item["model"]["albedo"]["psnr"], item["floor"]["albedo"]["psnr"],
           item["model"]["relit"]["psnr"], item["floor"]["relit"]["psnr"])
    for key in (f"glass objects {min(glass, 2)}{'+' if glass >= 2 else ''}", f"metal objects {min(metal, 2)}{'+' if metal >= 2 else ''}",
                f"objects {len(objects)}", f"textured ground {meta['scene']['ground']['texture'] is not None}",
                f"input probe {meta['probes'][source]}", f"target probe {meta['probes'][target]}"):
        groups[key].append(row)
for key in sorted(groups):
    v = np.array(groups[key])
    print(f"{key:40s} {len(v):4d} items: albedo {v[:, 0].mean():.2f} (floor {v[:, 1].mean():.2f}), "
          f"relit {v[:, 2].mean():.2f} (floor {v[:, 3].mean():.2f})")
