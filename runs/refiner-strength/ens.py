"""Output ensembles of model folders on the test split (80 items, fp32): each one's mean PSNR and, blended
with the first at weights 0.5 and 0.3, the paired difference; outputs cached in OUT as MODEL.npz.
    PYTHONPATH=. python runs/refiner-strength/ens.py OUT models/default OTHER_MODEL...
"""
import os, sys, numpy as np, torch
from pathlib import Path
from relight_core.evaluation.harness import load_items, relight, RunOptions
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter
root = Path.home() / ".cache/unirelight-studio"
out = Path(sys.argv[1]); models = sys.argv[2:]
torch.set_num_threads(int(os.environ.get('T', '2')))
items = load_items(root / "data", "test", 80)
res = {}
for m in models:
    if m == "input":
        x = np.stack([it.input for it in items]); res[m] = (x, x); continue
    cache = out / (Path(m).name + ".npz")
    if cache.exists():
        z = np.load(cache); res[m] = (z["relit"], z["albedo"]); continue
    r = Relighter.load(m, device="cpu", precision="fp32")
    rel, alb = [], []
    for it in items:
        a, b, _ = relight(r, it.input, it.probe, RunOptions())
        rel.append(a); alb.append(b)
    res[m] = (np.stack(rel), np.stack(alb)); out.mkdir(parents=True, exist_ok=True)
    np.savez(cache, relit=res[m][0], albedo=res[m][1])
def score(rel, alb):
    r = [protocol_metrics(rel[i], it.target, it.mask)["psnr"] for i, it in enumerate(items)]
    a = [protocol_metrics(alb[i], it.albedo, it.mask)["psnr"] for i, it in enumerate(items)]
    return np.array(r), np.array(a)
base = score(*res[models[0]])
print("single", models[0], base[0].mean().round(3), base[1].mean().round(3))
for m in models[1:]:
    s = score(*res[m]); print("single", m, s[0].mean().round(3), s[1].mean().round(3))
    for w in (0.5, 0.3):
        e = score((1-w)*res[models[0]][0] + w*res[m][0], (1-w)*res[models[0]][1] + w*res[m][1])
        d = e[0]-base[0]; da = e[1]-base[1]
        print(f"  mean w={w}", e[0].mean().round(3), e[1].mean().round(3), f"relit paired {d.mean():+.3f} ± {d.std(ddof=1)/np.sqrt(len(d)):.3f}  albedo {da.mean():+.3f} ± {da.std(ddof=1)/np.sqrt(len(da)):.3f}")
