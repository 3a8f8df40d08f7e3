# flip test-time averaging of the refiner's correction, on the validation pack
import torch, numpy as np
from pathlib import Path
from relight_core.training import refine as R
from relight_core.training.pack import load_packs
from relight_core.refiner import Refiner, RefinerConfig
from relight_core.checkpoint import load_model
C = Path.home() / ".cache/unirelight-studio"
torch.set_num_threads(1)
spec, _, _ = load_model(Path("models/default"), "cpu")
vp = load_packs([C / "s15/val.npz"])
items = [(i, t) for i in range(len(vp["names"])) for t in (0, 1)]
with np.load(C / "refine/final/outputs-val.npz") as z:
    out = {"relit": z["relit"], "albedo": z["albedo"]}
data = R.item_tensors(vp, items, out, spec, "filtered")
saved = torch.load(C / "refine/final/checkpoint.pt", map_location="cpu", weights_only=True)
m = Refiner(RefinerConfig.from_dict(saved["config"])); m.load_state_dict(saved["ema"]); m.eval()
print("plain", R.validate(m, data, True), flush=True)
al = []
with torch.no_grad():
    for s in range(0, len(items), 32):
        idx = slice(s, s + 32)
        x, r, a, _ = R.model_inputs(data, idx, "filtered")
        with torch.autocast("cpu", dtype=torch.bfloat16):
            d = m(x).float() + m(x.flip(-1)).float().flip(-1)
            d2 = m(x.flip(-2)).float().flip(-2) + m(x.flip(-1).flip(-2)).float().flip(-1).flip(-2)
        al.append((((a + d[:, 3:] / 2).clamp(-1, 1) + 1) / 2, (((a + (d + d2)[:, 3:] / 4).clamp(-1, 1) + 1) / 2)))
for k, name in ((0, "hflip"), (1, "hv4")):
    A = torch.cat([p[k] for p in al]).permute(0, 2, 3, 1).numpy()
    print(name, R.scores(data, A, A)["albedo"])
