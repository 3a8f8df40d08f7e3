# From the repo root: PYTHONPATH=. python runs/relit-xl/valprobe.py [MODEL] (default models/default; output: valprobe.txt)
# per target-probe gain of a model's relit refiner over the offset filter's frames on the validation pack
import json, collections, sys, torch, numpy as np
from pathlib import Path
from relight_core.checkpoint import load_model, load_refiner
from relight_core.training.pack import load_packs
from relight_core.training.refine import unseen_items, cached_outputs, item_tensors, model_inputs, _hwc
from relight_core.evaluation.metrics import protocol_psnr
torch.set_num_threads(1)
C = Path.home() / ".cache/unirelight-studio"
model = Path(sys.argv[1] if len(sys.argv) > 1 else "models/default")
spec, _, _ = load_model(model, "cpu")
r = load_refiner(spec, model, "cpu", slot="relit_refiner")
vp = load_packs(C / "s5/val.npz"); names = list(vp["names"])
items = unseen_items(vp["names"], [], None, 0)
out = cached_outputs(C / "refine/relit-G4big/outputs-val.npz", model, vp, items)   # the DiT's, the same for every refiner
data = item_tensors(vp, items, out, spec, r.config.base)
rel = []
with torch.no_grad():
    for s in range(0, len(items), 32):
        x, rr, a, get = model_inputs(data, slice(s, s + 32), r.config.base)
        d = r.correction(x, get("env")).float(); rr2, _ = r.corrected(d, rr, a); rel.append((rr2 + 1) / 2)
rel = torch.cat(rel).permute(0, 2, 3, 1).numpy()
base = _hwc(data["f_relit"]); tgt = _hwc(data["target"]); m = data["mask"].numpy(); inp = _hwc(data["input"])
g = collections.defaultdict(list)
for i, (s, t, _) in enumerate(items):
    meta = json.load(open(C / "val5/train" / names[s] / "meta.json"))
    key = meta["probes"][t].split(":")[1]
    g[key].append((protocol_psnr(rel[i], tgt[i], m[i]) - protocol_psnr(base[i], tgt[i], m[i]), protocol_psnr(base[i], tgt[i], m[i]), protocol_psnr(inp[i], tgt[i], m[i])))
for k, v in sorted(g.items(), key=lambda kv: -len(kv[1])):
    v = np.array(v); print(f"{k:24s} n={len(v):3d} gain {v[:,0].mean():+.3f} ± {v[:,0].std()/np.sqrt(len(v)):.3f}  base {v[:,1].mean():.2f} floor {v[:,2].mean():.2f}")
