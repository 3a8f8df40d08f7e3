# DiT outputs for the unseen items [lo, hi) of unseen_items(..., 6000) -> more-{lo}.npz (one thread)
import sys, torch, numpy as np
from pathlib import Path
from relight_core.training import refine as R
from relight_core.training.pack import load_packs
C = Path.home() / ".cache/unirelight-studio"
torch.set_num_threads(1)
lo, hi = int(sys.argv[1]), int(sys.argv[2])
pack = load_packs([C / "train-s4-e.npz"])
seen = [C / "train-s4.npz", *(C / f"pieces-s14/p{i}.npz" for i in (1, 2, 3)), C / "s15/val.npz"]
items = R.unseen_items(pack["names"], seen, 6000)[lo:hi]
out = R.dit_outputs(Path("models/default"), pack, items, log=lambda m: print(m, flush=True))
np.savez(C / f"refine/more-{lo}.npz", names=np.array([str(pack["names"][s]) for s, _ in items]),
         targets=np.array([t for _, t in items]), **out)
print("done", flush=True)
