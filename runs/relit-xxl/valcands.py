# Validation (the run's own 384 items, as training.refine scores them) of the candidate model folders' relit
# refiners, bf16 autocast as in training where the CPU has fast bf16. From the repo root:
#   PYTHONPATH=. python runs/relit-xxl/valcands.py MODEL [MODEL ...]
import sys
import torch
from pathlib import Path
from relight_core.checkpoint import load_model, load_refiner
from relight_core.precision import resolve_precision
from relight_core.training.pack import load_packs
from relight_core.training.refine import unseen_items, cached_outputs, item_tensors, validate
torch.set_num_threads(2)
C = Path.home() / ".cache/unirelight-studio"
spec, _, _ = load_model(Path("models/default"), "cpu")
vp = load_packs(C / "s5/val.npz")
items = unseen_items(vp["names"], [], None, len(vp["names"]))
out = cached_outputs(C / "refine/relit-G4xxl/outputs-val.npz", Path("models/default"), vp, items)
autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16
data = None
for model in sys.argv[1:]:
    r = load_refiner(spec, Path(model), "cpu", slot="relit_refiner").float().eval()
    data = data or item_tensors(vp, items, out, spec, r.config.base)
    with torch.no_grad():
        print(model, validate(r, data, autocast), flush=True)
