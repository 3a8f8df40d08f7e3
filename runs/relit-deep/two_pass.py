"""Two-pass proxy on the 128 validation scenes (light 1 -> 0): pass 1 default mode -> the shipped model's refined
albedo; pass 2 the DiT in 'both' mode (input and albedo given) with that albedo -> relit; the relit refiner on each;
and pass 2 with the true albedo (the oracle). PSNR after a per-channel scale fit on the foreground mask, per item.
Ran from the repo root: .venv/bin/python runs/relit-deep/two_pass.py THREADS [ITEMS]  (output: two-pass-128.txt)"""
import sys, torch
from functools import partial
from pathlib import Path
REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from relight_core.training.fast import make_batch, network
from relight_core.training.pack import load_pack
from relight_core.pipeline import Relighter
from relight_core.diffusion import ConditionedDenoiser, EDMPrecond, get_sigmas_karras, sample_res2ab
torch.set_num_threads(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
R = Relighter.load(str(REPO / 'models/default'), device='cpu', precision='fp32')
dit, tok = R.dit, R.tokenizer
pack = load_pack(Path.home() / '.cache/unirelight-studio/s5/val.npz')
GAIN_A = R.spec.residual_gain[1]
print('gains', R.spec.residual_gain)
n = int(sys.argv[2]) if len(sys.argv) > 2 else len(pack['rgb'])

def sample(batch, albedo=None):
    inp = batch['input']; b, _, t = inp.shape[:3]
    z = torch.zeros_like(inp)
    condition = torch.cat([inp, z, z if albedo is None else albedo], dim=2)
    mask = torch.zeros(b, 1, 3 * t, 1, 1); mask[:, :, :t] = 1
    if albedo is not None: mask[:, :, 2 * t:] = 1
    den = ConditionedDenoiser(EDMPrecond(partial(network, dit)), condition, mask, seed=0, residual=True)
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(condition.shape, generator=g)
    s = get_sigmas_karras(1)
    with torch.no_grad():
        x0 = sample_res2ab(lambda x, sg, **kw: den(x, sg, lighting=batch['lighting']), noise * s[0], s).float()
    src = inp
    return (src + 1.0 * (x0[:, :, t:2 * t] - src)), (src + GAIN_A * (x0[:, :, 2 * t:] - src))

def img(z):  # latent -> [B,H,W,3] numpy in [0,1]
    d = tok.decode(z)
    d = d[:, :, 0] if d.dim() == 5 else d
    return ((d.float().clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).contiguous().numpy()

MASK = None
def fitted(a, b):  # scale-fitted PSNR per item on the mask, images [B,H,W,3] in [0,1]
    m = MASK[..., None].double()
    a, b = torch.from_numpy(a).double(), torch.from_numpy(b).double()
    s = (m * a * b).sum((1, 2)) / (m * a * a).sum((1, 2)).clamp_min(1e-9)
    mse = (m * (a * s[:, None, None] - b) ** 2).sum((1, 2, 3)) / (3 * m.sum((1, 2, 3)))
    return 10 * torch.log10(1 / mse)

res = {}
def add(k, v): res.setdefault(k, []).append(v)
for start in range(0, n, 16):
    idx = torch.arange(start, min(n, start + 16))
    batch = make_batch(pack, tok, idx, torch.zeros_like(idx), torch.zeros_like(idx, dtype=torch.bool))
    MASK = pack['mask'][idx]
    tgt, alb, inp = img(batch['relit']), img(batch['albedo']), img(batch['input'])
    light = pack['env'][idx, 0].float()
    r, a = sample(batch)
    r1, a1 = img(r), img(a)
    rr, ar = R._refined('relight', inp, r1, a1, light)
    add('relit DiT', fitted(r1, tgt)); add('relit shipped', fitted(rr, tgt))
    add('albedo DiT', fitted(a1, alb)); add('albedo shipped', fitted(ar, alb))
    # pass 2 with the refined albedo
    a_in = torch.from_numpy(ar).permute(0, 3, 1, 2).float() * 2 - 1
    a_lat = tok.encode(a_in.unsqueeze(2))
    r2, _ = sample(batch, a_lat)
    r2i = img(r2)
    rr2, _ = R._refined('relight', inp, r2i, a1, light)
    rr2b, _ = R._refined('relight', inp, r2i, ar, light)
    add('relit 2pass DiT', fitted(r2i, tgt)); add('relit 2pass +relit refiner', fitted(rr2, tgt))
    add('relit 2pass +relit refiner (refined albedo in)', fitted(rr2b, tgt))
    g2, _ = sample(batch, batch['albedo'])
    add('relit GT-albedo DiT', fitted(img(g2), tgt))
    print(start + len(idx), {k: round(float(torch.cat(v).mean()), 3) for k, v in res.items()}, flush=True)
