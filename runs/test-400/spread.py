"""How far the 80 test items' means are from the test distribution's: an evaluate run on 400 items (the test split
rendered to 200 scenes, seed 0, whose first 40 are the usual ones) split into its first 80 and the other 320, each
mean with its standard error over scenes (the two directions of a scene are not independent); with a second run
DIR_B on the same items, the paired difference B − A on the same groups.
    PYTHONPATH=. python runs/test-400/spread.py ~/.cache/unirelight-studio/eval/shipped-400 [DIR_B]
"""
import json
import sys

import numpy as np


def per_item(folder):
    return json.load(open(f"{folder}/metrics.json"))["test"]["per_item"]


def se(x):
    scenes = x.reshape(-1, 2).mean(1)
    return scenes.std(ddof=1) / np.sqrt(len(scenes))


a = per_item(sys.argv[1])
b = per_item(sys.argv[2]) if len(sys.argv) > 2 else None
if b is not None:
    assert [i["name"] for i in a] == [i["name"] for i in b]
for lo, hi in ((0, 80), (80, len(a)), (0, len(a))):
    def get(items, clip, kind="model"):
        return np.array([i[kind][clip]["psnr"] for i in items[lo:hi]])
    r, f, al, fa = get(a, "relit"), get(a, "relit", "floor"), get(a, "albedo"), get(a, "albedo", "floor")
    m = np.array([i["margin"] for i in a[lo:hi]])
    print(f"items {lo}–{hi}: relit {r.mean():.2f} ± {se(r):.2f} (floor {f.mean():.2f}, above it {(r - f).mean():+.2f} ± "
          f"{se(r - f):.2f}), albedo {al.mean():.2f} ± {se(al):.2f} (floor {fa.mean():.2f}), margin {m.mean():+.2f}")
    if b is not None:
        for clip in ("relit", "albedo"):
            d = get(b, clip) - get(a, clip)
            print(f"   B − A {clip}: {d.mean():+.3f} ± {se(d):.3f}")
