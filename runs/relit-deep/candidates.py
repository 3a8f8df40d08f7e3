# Model folders from relit-D2 for the test split: "D2" (its best EMA by validation) and "D2-avg" (that one averaged with
# the relit-G4xxl best it started from, deepened to two blocks a level: the same shape, so the mean is well defined).
# From the repo root: PYTHONPATH=. python runs/relit-deep/candidates.py
import json
from pathlib import Path

from safetensors.torch import load_file, save_file

from relight_core.refiner import Refiner, RefinerConfig
from relight_core.training.refine import deepened_state, write_model

C = Path.home() / ".cache/unirelight-studio"
D = C / "refine/relit-D2"
best = json.loads((D / "best.json").read_text())
trained = load_file(D / "refiner.safetensors")
start = deepened_state(load_file(C / "refine/relit-G4xxl/refiner.safetensors"),
                       Refiner(RefinerConfig.from_dict(best["refiner"])))
for name, weights in (("D2", trained), ("D2-avg", {k: (trained[k].float() + start[k].float()) / 2 for k in trained})):
    run = C / f"refine/tmp-{name}"
    run.mkdir(exist_ok=True)
    save_file({k: v.contiguous() for k, v in weights.items()}, run / "refiner.safetensors")
    write_model(Path("models/default"), run, C / f"cand-{name}", best, "relit_refiner")
    print(name, "done", best["step"], best["val"])
