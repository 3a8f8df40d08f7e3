"""The shipped DiT's outputs for every seed-5 item but the validation scenes', cached as training.refine caches
them: PYTHONPATH=. python runs/default-128-s18r/outputs.py OUT.npz"""
import sys, torch
from pathlib import Path
from relight_core.training import refine
from relight_core.training.pack import load_packs
torch.set_num_threads(2)
C = Path.home() / ".cache/unirelight-studio"
pack = load_packs([C / "train-s5.npz"])
items = refine.unseen_items(pack["names"], [C / "s5/val.npz"], None)
print(len(items), "items", flush=True)
refine.cached_outputs(Path(sys.argv[1]), Path("models/default"), pack, items, log=lambda m: print(m, flush=True))
