"""How much of the additive relit refiner M's validation gain is coarse (runs/relit-lighting/, not shipped):
its correction turned into a log gain, (refined + ε) / (base + ε), or kept as an addition, blurred by a
Gaussian of σ px, then scored on the validation pack (256 items relit to another light, 128 to their own):
    PYTHONPATH=. python runs/relit-gain/smooth_probe.py        (output: smooth-probe.txt)"""
import torch
from pathlib import Path
from torch.nn import functional as F
from relight_core.checkpoint import load_model, load_refiner
from relight_core.training.refine import unseen_items, cached_outputs, item_tensors, model_inputs, scores, _hwc
from relight_core.training.pack import load_packs
torch.set_num_threads(2)
C = Path.home() / ".cache/unirelight-studio"
model = C / "cand-M"
spec, _, d = load_model(model, "cpu")
ref = load_refiner(spec, model, "cpu", "relit_refiner")
vp = load_packs([C / "s5/val.npz"])
items = unseen_items(vp["names"], [], None, len(vp["names"]))
outs = cached_outputs(C / "refine/relit-M/outputs-val.npz", model, vp, items)
data = item_tensors(vp, items, outs, spec, "filtered")
rel = []
with torch.no_grad():
    for s in range(0, len(items), 32):
        x, r, a, get = model_inputs(data, slice(s, s + 32), "filtered")
        with torch.autocast("cpu", dtype=torch.bfloat16):
            delta = ref.correction(x, get("env")).float()
        rr, _ = ref.corrected(delta, r, a)
        rel.append(((rr + 1) / 2))
rel = torch.cat(rel)
base = torch.from_numpy(_hwc(data["f_relit"])).permute(0, 3, 1, 2)
alb = _hwc(data["f_albedo"])
print("base", scores(data, base.permute(0, 2, 3, 1).numpy(), alb))
print("M", scores(data, rel.permute(0, 2, 3, 1).numpy(), alb))
eps = 0.02
logr = torch.log(rel + eps) - torch.log(base + eps)
def blur(t, s):
    k = int(3 * s) * 2 + 1
    x = torch.arange(k) - k // 2
    w = torch.exp(-x.float() ** 2 / (2 * s * s)); w = w / w.sum()
    t = F.pad(t, (k // 2,) * 4, mode="replicate")
    t = F.conv2d(t, w.view(1, 1, 1, k).expand(3, 1, 1, k), groups=3)
    return F.conv2d(t, w.view(1, 1, k, 1).expand(3, 1, k, 1), groups=3)
for s in (1, 2, 4, 8, 16):
    g = blur(logr, s)
    out = ((base + eps) * torch.exp(g) - eps).clamp(0, 1)
    add = (base + blur(rel - base, s)).clamp(0, 1)
    print(s, "gain", scores(data, out.permute(0, 2, 3, 1).numpy(), alb), "add", scores(data, add.permute(0, 2, 3, 1).numpy(), alb))
