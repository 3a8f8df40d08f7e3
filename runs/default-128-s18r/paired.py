"""Paired per-item differences B − A of two evaluate runs (same items): python paired.py DIR_A DIR_B [--unseen]
(--unseen: also the last 32 of 80 test items, the ones no calibration ever saw)"""
import json, sys
import numpy as np
a, b = (json.load(open(f"{d}/metrics.json"))["test"]["per_item"] for d in sys.argv[1:3])
assert [x["name"] for x in a] == [x["name"] for x in b]
groups = {"all": slice(None)}
if "--unseen" in sys.argv[3:] and len(a) == 80:
    groups["unseen32"] = slice(48, 80)
for g, s in groups.items():
    for clip in ("relit", "albedo"):
        x = np.array([i["model"][clip]["psnr"] for i in a])[s]
        y = np.array([i["model"][clip]["psnr"] for i in b])[s]
        d = y - x
        print(f"{g} {clip} n={len(d)} {d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f}  A {x.mean():.2f}  B {y.mean():.2f}")
    x = np.array([i["margin"] for i in a])[s]; y = np.array([i["margin"] for i in b])[s]
    print(f"{g} margin A {x.mean():+.2f} B {y.mean():+.2f}")
