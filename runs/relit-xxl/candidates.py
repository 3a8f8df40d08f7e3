# Model folders from relit-G4xxl for the test split: "last" (the final EMA, step 17,349), "avg" (its mean with the best, step 13,498) and
# "avg3" (those two and the shipped G4xl refiner, equal weights). From the repo root: PYTHONPATH=. python runs/relit-xxl/candidates.py
import json, torch
from pathlib import Path
from safetensors.torch import save_file, load_file
from relight_core.training.refine import write_model
C = Path.home() / ".cache/unirelight-studio"; D = C / "refine/relit-G4xxl"
best = json.loads((D / "best.json").read_text())
ck = torch.load(D / "checkpoint.pt", map_location="cpu", weights_only=True)
last = {k: v.contiguous() for k, v in ck["ema"].items()}
b = load_file(D / "refiner.safetensors")
ship = load_file(C / "cand-G4xl/relit_refiner.safetensors")
for name, w in (("last", last), ("avg", {k: (last[k].float() + b[k].float()) / 2 for k in b}),
                ("avg3", {k: (last[k].float() + b[k].float() + ship[k].float()) / 3 for k in b})):
    run = C / f"refine/tmp-{name}"; run.mkdir(exist_ok=True)
    save_file({k: v.contiguous() for k, v in w.items()}, run / "refiner.safetensors")
    write_model(Path("models/default"), run, C / f"cand-G4xxl-{name}", dict(best, step=json.loads(ck["state"])["step"] if name == "last" else best["step"]), "relit_refiner")
    print(name, "done")
