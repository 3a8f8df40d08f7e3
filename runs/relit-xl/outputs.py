# The DiT's outputs for the first 15,000 unseen seed-5 scenes (+500 own-light) into refine/relit-G4xl/outputs-train.npz, one thread.
# From the repo root: PYTHONPATH=. OMP_NUM_THREADS=1 python runs/relit-xl/outputs.py (reuses the items a copied outputs-train.npz holds)
import torch
from pathlib import Path
from relight_core.training.pack import load_packs
from relight_core.training.refine import unseen_items, cached_outputs
torch.set_num_threads(1)
C = Path.home() / ".cache/unirelight-studio"
pack = load_packs([C / "train-s5-all.npz"])
items = unseen_items(pack["names"], [C / "s5/val.npz"], 15000, 500)
print(len(items), "items", flush=True)
cached_outputs(C / "refine/relit-G4xl/outputs-train.npz", Path("models/default"), pack, items, lambda m: print(m, flush=True))
print("done", flush=True)
