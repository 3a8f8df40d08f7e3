# train-vs-val gap of the refine/final EMA (overfitting check)
import torch, numpy as np
from pathlib import Path
from relight_core.training import refine as R
from relight_core.training.pack import load_packs
from relight_core.refiner import Refiner, RefinerConfig
from relight_core.checkpoint import load_model
C = Path.home() / ".cache/unirelight-studio"
torch.set_num_threads(2)
spec, _, _ = load_model(Path("models/default"), "cpu")
pack = load_packs([C / "train-s4-e.npz"])
items = R.unseen_items(pack["names"], [C / "train-s4.npz", *(C / f"pieces-s14/p{i}.npz" for i in (1, 2, 3)), C / "s15/val.npz"], 3000)
with np.load(C / "refine/final/outputs-train.npz") as z:
    out = {"relit": z["relit"], "albedo": z["albedo"]}
sel = list(range(0, 6000, 6000 // 256))[:256]
items_s = [items[i] for i in sel]
out_s = {k: v[sel] for k, v in out.items()}
data = R.item_tensors(pack, items_s, out_s, spec, "filtered")
saved = torch.load(C / "refine/final/checkpoint.pt", map_location="cpu", weights_only=True)
m = Refiner(RefinerConfig.from_dict(saved["config"])); m.load_state_dict(saved["ema"]); m.eval()
print("train subset start", R.scores(data, R._hwc(data["f_relit"]), R._hwc(data["f_albedo"])))
print("train subset EMA", R.validate(m, data, True))
