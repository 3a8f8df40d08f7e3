# From ~/.cache/unirelight-studio: python3 $REPO/runs/relit-xl/byprobe.py A B — paired relit gain B − A of two evaluate dirs (eval/A, eval/B), by the target probe
import json, sys, collections, numpy as np
a, b = [json.load(open(f"eval/{x}/metrics.json"))["test"]["per_item"] for x in sys.argv[1:3]]
g = collections.defaultdict(list)
for x, y in zip(a, b):
    scene, d = x["name"].split(" ")
    src, dst = (0, 1) if d == "0→1" else (1, 0)
    probes = json.load(open(f"data/test/{scene}/meta.json"))["probes"]
    key = probes[dst].split(":")[1]
    g[key].append((y["model"]["relit"]["psnr"] - x["model"]["relit"]["psnr"], x["model"]["relit"]["psnr"], x["floor"]["relit"]["psnr"]))
for k, v in sorted(g.items()):
    v = np.array(v); print(f"{k:22s} n={len(v):2d} gain {v[:,0].mean():+.3f} ± {v[:,0].std()/np.sqrt(len(v)):.3f}  base {v[:,1].mean():.2f} floor {v[:,2].mean():.2f}")
