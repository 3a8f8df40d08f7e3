"""A candidate paired with the shipped model on one or more test sets, each set and all together.

    PYTHONPATH=. python runs/fresh-test/pair.py SHIPPED_SEED0 CAND_SEED0 [SHIPPED_SEED1 CAND_SEED1 ...]

Each argument is an `evaluate` output folder; the folders of a pair score the same items. Prints, per set and for
the sets pooled: the candidate's relit / albedo PSNR and margin, and the paired difference (candidate − shipped)
with its standard error over scenes (the two directions of a scene are not independent), and how many scenes rose.
"""
import json
import sys

import numpy as np


def per_item(folder):
    return json.load(open(f"{folder}/metrics.json"))["test"]["per_item"]


def values(items):
    return {"relit": np.array([i["model"]["relit"]["psnr"] for i in items]),
            "albedo": np.array([i["model"]["albedo"]["psnr"] for i in items]),
            "margin": np.array([i["margin"] for i in items])}


def by_scene(x):
    return x.reshape(-1, 2).mean(1)


def report(name, a, b):
    parts = [f"{name}: {len(a['relit'])} items"]
    for key in ("relit", "albedo", "margin"):
        d = by_scene(b[key] - a[key])
        se = d.std(ddof=1) / np.sqrt(len(d))
        ratio = f"{d.mean() / se:+.1f} SE" if se > 0 else "the same on every scene"
        parts.append(f"{key} {a[key].mean():.3f} → {b[key].mean():.3f} ({d.mean():+.3f} ± {se:.3f}, "
                     f"{int((d > 0).sum())}/{len(d)} scenes up, {ratio})")
    print("\n  ".join(parts))


def main(folders):
    if len(folders) < 2 or len(folders) % 2:
        sys.exit("give pairs of folders: SHIPPED CANDIDATE [SHIPPED CANDIDATE ...]")
    pooled_a, pooled_b = [], []
    for k in range(0, len(folders), 2):
        items_a, items_b = per_item(folders[k]), per_item(folders[k + 1])
        if [i["name"] for i in items_a] != [i["name"] for i in items_b]:
            sys.exit(f"{folders[k]} and {folders[k + 1]} do not score the same items")
        a, b = values(items_a), values(items_b)
        report(f"{folders[k]} vs {folders[k + 1]}", a, b)
        pooled_a.append(a)
        pooled_b.append(b)
    if len(pooled_a) > 1:
        report("pooled", *({key: np.concatenate([v[key] for v in side]) for key in side[0]}
                           for side in (pooled_a, pooled_b)))


if __name__ == "__main__":
    main(sys.argv[1:])
