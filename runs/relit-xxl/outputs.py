# The DiT's outputs for all 20,000 seed-5 scenes' unseen items (19,872 scenes both ways + 500 own-light = 40,244)
# into refine/relit-G4xxl/outputs-train.npz, reusing the 30,492 that refine/relit-G4xl/outputs-train.npz holds.
# From the repo root, the missing items in two one-thread shards side by side, then merged:
#   PYTHONPATH=. OMP_NUM_THREADS=1 python runs/relit-xxl/outputs.py shard 0 2 &
#   PYTHONPATH=. OMP_NUM_THREADS=1 python runs/relit-xxl/outputs.py shard 1 2; wait
#   PYTHONPATH=. python runs/relit-xxl/outputs.py merge 2
import sys
import numpy as np
import torch
from pathlib import Path
from relight_core.training.pack import load_packs
from relight_core.training.refine import unseen_items, dit_outputs

C = Path.home() / ".cache/unirelight-studio"
OLD, NEW = C / "refine/relit-G4xl/outputs-train.npz", C / "refine/relit-G4xxl"
pack = load_packs([C / "train-s5-20k.npz"])
items = unseen_items(pack["names"], [C / "s5/val.npz"], 20000, 500)
keys = [(str(pack["names"][s]), t, k) for s, t, k in items]
with np.load(OLD, allow_pickle=False) as z:
    where = {(str(n), int(t), int(k)): i for i, (n, t, k) in enumerate(zip(z["names"], z["targets"], z["same"]))}
rows = [where.get(key) for key in keys]
missing = [i for i, r in enumerate(rows) if r is None]
print(len(items), "items,", len(missing), "to compute", flush=True)
NEW.mkdir(parents=True, exist_ok=True)
if sys.argv[1] == "shard":
    torch.set_num_threads(1)
    k, n = int(sys.argv[2]), int(sys.argv[3])
    mine = missing[k::n]
    out = dit_outputs(Path("models/default"), pack, [items[i] for i in mine], log=lambda m: print(m, flush=True))
    np.savez(NEW / f"shard-{k}.npz", index=np.array(mine), **out)
else:
    n = int(sys.argv[2])
    with np.load(OLD, allow_pickle=False) as z:
        out = {key: np.empty((len(items), *z[key].shape[1:]), np.uint8) for key in ("relit", "albedo")}
        hits = [i for i, r in enumerate(rows) if r is not None]
        for key, frames in out.items():
            frames[hits] = z[key][[rows[i] for i in hits]]
    for k in range(n):
        with np.load(NEW / f"shard-{k}.npz") as s:
            for key, frames in out.items():
                frames[s["index"]] = s[key]
    np.savez(NEW / "outputs-train.npz", names=np.array([a for a, _, _ in keys]), targets=np.array([t for _, t, _ in keys]),
             same=np.array([k for _, _, k in keys], dtype=np.int64), **out)
    print("merged", len(items), flush=True)
