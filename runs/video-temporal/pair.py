"""Pair two probe.py outputs item by item: mean difference (B − A) ± the standard error over scenes.
    python runs/video-temporal/pair.py A.txt B.txt
"""
import json
import sys

import numpy as np


def rows(path):
    return [json.loads(line) for line in open(path) if line.startswith("{")]


a, b = rows(sys.argv[1]), rows(sys.argv[2])
assert [r["name"] for r in a] == [r["name"] for r in b]
scenes = [r["name"].split()[0] for r in a]
for clip in ("relit", "albedo"):
    for key, unit in (("psnr", 1), ("temporal", 255), ("flicker", 255)):
        d = np.array([unit * (y[clip][key] - x[clip][key]) for x, y in zip(a, b)])
        per_scene = np.array([d[[i for i, s in enumerate(scenes) if s == name]].mean() for name in sorted(set(scenes))])
        print(f"{clip} {key}{' (/255)' if unit > 1 else ' (dB)'}: {np.mean([unit * x[clip][key] for x in a]):.3f} → "
              f"{np.mean([unit * y[clip][key] for y in b]):.3f}, paired {d.mean():+.3f} ± "
              f"{per_scene.std(ddof=1) / np.sqrt(len(per_scene)):.3f} ({len(per_scene)} scenes, {len(d)} items; "
              f"{(d > 0).sum()} up, {(d < 0).sum()} down)")
