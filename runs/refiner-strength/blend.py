"""Linear blends of cached test-split outputs (ens.py) with the shipped model's relit frames: paired PSNR on all 80
items, the 48 `calibrate --skip 16 --items 48` chooses on, and the 32 it never sees.
    PYTHONPATH=. python runs/refiner-strength/blend.py /tmp/ens/out
"""
import sys, numpy as np
from pathlib import Path
from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics
root = Path.home() / ".cache/unirelight-studio"
items = load_items(root / "data", "test", 80)
cal = sorted({16 + round(k * 63 / 47) for k in range(48)}); uns = [i for i in range(80) if i not in cal]
O = {p.stem: np.load(p) for p in Path(sys.argv[1]).glob("*.npz")}   # ens.py's output folder
O["input"] = {"relit": np.stack([it.input for it in items]), "albedo": np.stack([it.input for it in items])}
def psnr(pred, key="relit"):
    t = [it.target if key == "relit" else it.albedo for it in items]
    return np.array([protocol_metrics(pred[i], t[i], items[i].mask)["psnr"] for i in range(80)])
def combo(weights, key="relit"):
    base = O["default"][key].astype(np.float64) * (1 - sum(weights.values()))
    for k, w in weights.items(): base = base + w * O[k][key]
    return base.astype(np.float32)
ref = psnr(O["default"]["relit"])
def show(label, w, key="relit"):
    p = psnr(combo(w, key), key); r = ref if key == "relit" else psnr(O["default"][key], key)
    d = p - r
    f = lambda ix: f"{d[ix].mean():+.3f}±{d[ix].std(ddof=1)/np.sqrt(len(ix)):.3f}"
    print(f"{label:40s} all {p.mean():.3f} paired {f(list(range(80)))} cal {f(cal)} unseen {f(uns)}", flush=True)
print(len(cal), len(uns), sorted(O))
for s in (0.1, 0.2, 0.3, 0.4): show(f"noRR {s}", {"noRR": s})
for k in ("f974422", "b7fa1e5", "2c6a647", "oldDiT-newR", "35f58f6"):
    for s in (0.2, 0.3, 0.4): show(f"{k} {s}", {k: s})
show("noRR .2 + b7 .2", {"noRR": .2, "b7fa1e5": .2})
show("noRR .15 + b7 .15 + f97 .15", {"noRR": .15, "b7fa1e5": .15, "f974422": .15})
show("b7 .15 + f97 .15", {"b7fa1e5": .15, "f974422": .15})
show("b7 .1 f97 .1 2c .1", {"b7fa1e5": .1, "f974422": .1, "2c6a647": .1})
show("b7 .15 f97 .15 2c .15", {"b7fa1e5": .15, "f974422": .15, "2c6a647": .15})
