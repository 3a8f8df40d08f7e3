# refine/big: 12,000-item outputs cache (final's 6,000 + more-6000 + more-9000) and a checkpoint that starts
# from final's best EMA (step 10,594) with a fresh optimizer
import json, shutil, torch, numpy as np
from pathlib import Path
from safetensors.torch import load_file
from relight_core.training import refine as R
from relight_core.training.pack import load_packs
from relight_core.refiner import Refiner, RefinerConfig
C = Path.home() / ".cache/unirelight-studio"
big = C / "refine/big"; big.mkdir(exist_ok=True)
parts = [np.load(C / "refine/final/outputs-train.npz"), np.load(C / "refine/more-6000.npz"), np.load(C / "refine/more-9000.npz")]
cat = {k: np.concatenate([p[k] for p in parts]) for k in ("names", "targets", "relit", "albedo")}
pack = load_packs([C / "train-s4-e.npz"])
seen = [C / "train-s4.npz", *(C / f"pieces-s14/p{i}.npz" for i in (1, 2, 3)), C / "s15/val.npz"]
items = R.unseen_items(pack["names"], seen, 6000)
assert np.array_equal(cat["names"], np.array([str(pack["names"][s]) for s, _ in items]))
assert np.array_equal(cat["targets"], np.array([t for _, t in items]))
np.savez(big / "outputs-train.npz", **cat)
shutil.copyfile(C / "refine/final/outputs-val.npz", big / "outputs-val.npz")
best = json.loads((C / "refine/final/best.json").read_text())
cfg = RefinerConfig.from_dict(best["refiner"])
m = Refiner(cfg); m.load_state_dict(load_file(C / "refine/final/refiner.safetensors"))
opt = torch.optim.AdamW(m.parameters(), lr=1.5e-3, weight_decay=0.0)
state = {"step": 0, "seconds": 0.0, "best": None, "start": best["start"]}
torch.save({"model": m.state_dict(), "ema": m.state_dict(), "optimizer": opt.state_dict(),
            "generator": torch.Generator().manual_seed(5).get_state(), "config": cfg.to_dict(),
            "state": json.dumps(state)}, big / "checkpoint.pt")
print(len(cat["names"]), "items; checkpoint from step", best["step"])
