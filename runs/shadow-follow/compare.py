"""Paired comparison of probe.py runs on the same scenes: each model's means and its per-scene difference from
the first run (± SE over scenes).
    python runs/shadow-follow/compare.py FIRST/summary.json OTHER/summary.json ...
"""
import json
import sys

import numpy as np

KEYS = ("follow", "follow_detail", "reach", "shadow_agreement", "albedo_shading")
runs = [json.load(open(path)) for path in sys.argv[1:]]
first = runs[0]
print(f"{len(first['scenes'])} scenes, probe {first['summary']['probe']}, yaws {first['summary']['yaws']}; "
      f"ceilings (the truth against itself rendered with other noise): follow "
      f"{first['summary']['follow_ceiling']:.3f}, follow_detail {first['summary']['follow_detail_ceiling']:.3f}")
for run in runs:
    cells = []
    for key in KEYS:
        pairs = [(a[key], b[key]) for a, b in zip(run["scenes"], first["scenes"]) if a[key] is not None and b[key] is not None]
        d = np.array([a - b for a, b in pairs])
        mean = np.mean([a for a, _ in pairs])
        cells.append(f"{key} {mean:.3f}" + ("" if run is first else f" ({d.mean():+.3f} ± {d.std(ddof=1) / np.sqrt(len(d)):.3f})"))
    print(run["summary"]["model"].split("/")[-1] + ": " + "; ".join(cells))
