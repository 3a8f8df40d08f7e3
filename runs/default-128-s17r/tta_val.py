# test-time averaging of the grown refiner's correction over colour orders and left-right flips (validation)
import itertools, sys, torch
from safetensors.torch import load_file
from relight_core.training import refine as R
from relight_core.refiner import Refiner, RefinerConfig
from valdata import validation
torch.set_num_threads(2)
data = validation("filtered")
items = range(len(data["input"]))
m = Refiner(RefinerConfig(widths=(24, 48, 96, 128, 256), blocks=1, base="filtered", clips=("albedo",)))
m.load_state_dict(load_file(sys.argv[1])); m.eval()
perms = [torch.tensor(p) for p in itertools.permutations(range(3))]
inverse = [torch.argsort(p) for p in perms]
res = {k: [] for k in ("plain", "flip", "perm6", "perm6flip")}
with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
    for s in range(0, len(items), 32):
        x, r, a, _ = R.model_inputs(data, slice(s, s + 32), "filtered")
        b = len(x)
        outs = {}
        for flip in (False, True):
            for j, p in enumerate(perms):
                xx = R.permute_colours(x.flip(-1) if flip else x, p.expand(b, 3))
                d = m(xx).float()[:, 3:]
                d = R.permute_colours(d, inverse[j].expand(b, 3))
                outs[(flip, j)] = d.flip(-1) if flip else d
        def fin(ds): return ((a + torch.stack(ds).mean(0)).clamp(-1, 1) + 1) / 2
        res["plain"].append(fin([outs[(False, 0)]]))
        res["flip"].append(fin([outs[(False, 0)], outs[(True, 0)]]))
        res["perm6"].append(fin([outs[(False, j)] for j in range(6)]))
        res["perm6flip"].append(fin(list(outs.values())))
for k, v in res.items():
    A = torch.cat(v).permute(0, 2, 3, 1).numpy()
    print(k, R.scores(data, A, A)["albedo"], flush=True)
