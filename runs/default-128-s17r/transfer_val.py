# relit' = filtered relit × (refined albedo / filtered albedo) on the validation pack
import torch, numpy as np
from safetensors.torch import load_file
from relight_core.training import refine as R
from relight_core.refiner import Refiner, RefinerConfig
from valdata import CACHE as C, validation
torch.set_num_threads(1)
data = validation("filtered")
items = range(len(data["input"]))
m = Refiner(RefinerConfig(base="filtered", clips=("albedo",))); m.load_state_dict(load_file(C / "refine/big/refiner-shipped-3472.safetensors")); m.eval()
A2, RR, AA, INP = [], [], [], []
with torch.no_grad():
    for s in range(0, len(items), 32):
        x, r, a, _ = R.model_inputs(data, slice(s, s + 32), "filtered")
        with torch.autocast("cpu", dtype=torch.bfloat16):
            d = m(x).float()
        A2.append(((a + d[:, 3:]).clamp(-1, 1) + 1) / 2); RR.append((r + 1) / 2); AA.append((a + 1) / 2)
A2, RR, AA = (torch.cat(v).permute(0, 2, 3, 1).numpy() for v in (A2, RR, AA))
print("base", R.scores(data, RR, A2))
for eps in (0.02, 0.05, 0.1, 0.2, 0.4):
    print(eps, [(p, R.scores(data, np.clip(RR * ((A2 + eps) / (AA + eps)) ** p, 0, 1), A2)["relit"]) for p in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0)], flush=True)
# additive
for k in (0.3, 0.5, 0.7):
    print("add", k, R.scores(data, np.clip(RR + k * (A2 - AA), 0, 1), A2)["relit"], flush=True)
