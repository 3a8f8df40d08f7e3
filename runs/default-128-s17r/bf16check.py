# validation albedo of a refiner with its weights as trained (fp32) and rounded to bf16 (as it would ship)
import sys, torch
from pathlib import Path
from safetensors.torch import load_file, save_file
from relight_core.training import refine as R
from relight_core.refiner import Refiner, RefinerConfig
from valdata import validation
torch.set_num_threads(2)
src = Path(sys.argv[1])
data = validation("filtered")
state = load_file(src)
cfg = RefinerConfig(widths=(24, 48, 96, 128, 256), blocks=1, base="filtered", clips=("albedo",))
for name, st in (("fp32", state), ("bf16", {k: v.to(torch.bfloat16).float() for k, v in state.items()})):
    m = Refiner(cfg); m.load_state_dict(st); m.eval()
    print(name, "autocast", R.validate(m, data, True)["albedo"], "fp32", R.validate(m, data, False)["albedo"], flush=True)
if len(sys.argv) > 2:
    save_file({k: v.to(torch.bfloat16).contiguous() for k, v in state.items()}, sys.argv[2])
    print("wrote", sys.argv[2])
