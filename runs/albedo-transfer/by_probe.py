"""The 80 test items' relit PSNR (shipped model, cached by runs/refiner-strength/ens.py), by target probe and by
input probe, against the floor (the input returned unchanged).
    PYTHONPATH=. python runs/albedo-transfer/by_probe.py /tmp/ens/out2
"""
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics

root = Path.home() / ".cache/unirelight-studio/data/test"
items = load_items(root.parent, "test", 80)
S = np.load(Path(sys.argv[1]) / "S23.npz")["relit"]
rows = []
for i, it in enumerate(items):
    sample, pair = it.name.split(" ", 1)
    a, b = (int(x) for x in pair.replace("→", " ").split())
    probes = json.loads((root / sample / "meta.json").read_text())["probes"]
    rows.append((probes[a].split(":")[-1], probes[b].split(":")[-1],
                 protocol_metrics(S[i], it.target, it.mask)["psnr"],
                 protocol_metrics(it.input, it.target, it.mask)["psnr"]))
for label, key in (("target probe", 1), ("input probe", 0)):
    groups = defaultdict(list)
    for r in rows:
        groups[r[key]].append(r)
    print(f"by {label}:")
    for name, g in sorted(groups.items()):
        m, f = np.mean([r[2] for r in g]), np.mean([r[3] for r in g])
        print(f"  {name:22s} n={len(g):2d}  relit {m:.2f}  floor {f:.2f}  above {m - f:+.2f}")
