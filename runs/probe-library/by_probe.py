"""Paired relit differences (B − A) on the fresh test items by the target probe, ± SE over items.

    PYTHONPATH=. python runs/probe-library/by_probe.py DATA_ROOT EVAL_A EVAL_B
"""
import json
import sys

import numpy as np

samples = {s["path"]: s["probes"] for s in json.load(open(f"{sys.argv[1]}/test/manifest.json"))["samples"]}
a, b = (json.load(open(f"{d}/metrics.json"))["test"]["per_item"] for d in sys.argv[2:4])
rows = {}
for x, y in zip(a, b):
    assert x["name"] == y["name"]
    scene, direction = x["name"].split()[0], x["name"].split()[1]  # "scene_000003 0→1"
    target = samples[scene][int(direction[-1])]
    rows.setdefault(target, []).append(y["model"]["relit"]["psnr"] - x["model"]["relit"]["psnr"])
for target, d in sorted(rows.items()):
    d = np.array(d)
    print(f"target {target:28s} {len(d):3d} items: relit {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}")
