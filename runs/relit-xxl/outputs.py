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
from relight_core.training.refine import unseen_items, dit_outputs, item_keys, held_rows, held_frames

C = Path.home() / ".cache/unirelight-studio"
OLD, NEW = C / "refine/relit-G4xl/outputs-train.npz", C / "refine/relit-G4xxl"
pack = load_packs([C / "train-s5-20k.npz"])
items = unseen_items(pack["names"], [C / "s5/val.npz"], 20000, 500)
names, targets, same = item_keys(pack, items)
rows = held_rows(OLD, names, targets, same)
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
    out = held_frames(OLD, rows)
    for k in range(int(sys.argv[2])):
        with np.load(NEW / f"shard-{k}.npz") as s:
            for key, frames in out.items():
                frames[s["index"]] = s[key]
    np.savez(NEW / "outputs-train.npz", names=names, targets=targets, same=same, **out)
    print("merged", len(items), flush=True)
