"""The first look, offline on the shipped model's cached outputs for the seed-11 clips (cache_outputs.py): a
per-frame level smoothing (the mean log gain over the input, or absolute, averaged over ±r frames) against the
input-guided filter along time on the outputs ("plain") or on their log ratio to the input ("ratio"), the light
not weighed. Paired per item against the unfiltered outputs (± SE over items).
    PYTHONPATH=. python runs/video-temporal/choose_plain.py ~/.cache/unirelight-studio/clips-out-default.npz
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from probe import score  # noqa: E402
from relight_core.evaluation.harness import load_items  # noqa: E402
from relight_core.temporal import temporal_filter  # noqa: E402

C = Path.home() / ".cache/unirelight-studio"
items = load_items(C / "clips", "test")
outs = np.load(sys.argv[1])
EPS = 1e-2


def level_smooth(o, x, radius=1, relative=True):
    lo = np.log(o.mean(axis=(1, 2)) + EPS)
    lx = np.log(x.mean(axis=(1, 2)) + EPS) if relative else 0 * lo
    g = lo - lx
    T = len(g)
    gs = np.stack([g[max(0, t - radius):t + radius + 1].mean(0) for t in range(T)])
    return np.clip(o * np.exp(gs - g)[:, None, None, :], 0, 1)


def bilateral(o, x, radius=1, sigma=0.05, ratio=True):
    """The library's filter (relight_core/temporal.py, the light not weighed) on the outputs, or on their log
    ratio to the input."""
    lr = np.log(o + EPS) - np.log(x + EPS) if ratio else o
    v = temporal_filter(x, [lr], radius, sigma, 1.0)[0]
    return np.clip(np.exp(v) * (x + EPS) - EPS if ratio else v, 0, 1)


variants = {
    "raw": lambda o, x: o,
    "level r1 rel": lambda o, x: level_smooth(o, x, 1, True),
    "level r2 rel": lambda o, x: level_smooth(o, x, 2, True),
    "level r1 abs": lambda o, x: level_smooth(o, x, 1, False),
    "bil r1 s.05 ratio": lambda o, x: bilateral(o, x, 1, 0.05, True),
    "bil r1 s.1 ratio": lambda o, x: bilateral(o, x, 1, 0.1, True),
    "bil r2 s.05 ratio": lambda o, x: bilateral(o, x, 2, 0.05, True),
    "bil r2 s.03 ratio": lambda o, x: bilateral(o, x, 2, 0.03, True),
    "bil r1 s.03 plain": lambda o, x: bilateral(o, x, 1, 0.03, False),
    "bil r1 s.05 plain": lambda o, x: bilateral(o, x, 1, 0.05, False),
    "bil r1 s.08 plain": lambda o, x: bilateral(o, x, 1, 0.08, False),
    "bil r2 s.03 plain": lambda o, x: bilateral(o, x, 2, 0.03, False),
    "bil r2 s.05 plain": lambda o, x: bilateral(o, x, 2, 0.05, False),
    "bil r4 s.03 plain": lambda o, x: bilateral(o, x, 4, 0.03, False),
}
res = {k: {"relit": [], "albedo": []} for k in variants}
for i, it in enumerate(items):
    for kind, truth in (("relit", it.target), ("albedo", it.albedo)):
        o = outs[f"{kind}{i}"]
        for name, f in variants.items():
            res[name][kind].append(score(f(o, it.input), truth, it.mask))
print("| variant | relit PSNR | temporal | flicker | albedo PSNR | temporal | flicker |")
base = {kind: np.array([s["psnr"] for s in res["raw"][kind]]) for kind in ("relit", "albedo")}
for name in variants:
    row = []
    for kind in ("relit", "albedo"):
        p = np.array([s["psnr"] for s in res[name][kind]])
        d = p - base[kind]
        row.append(f"{p.mean():.3f} ({d.mean():+.3f}±{d.std(ddof=1)/np.sqrt(len(d)):.3f}) | "
                   f"{255*np.mean([s['temporal'] for s in res[name][kind]]):.2f} | "
                   f"{255*np.mean([s['flicker'] for s in res[name][kind]]):.2f}")
    print(f"| {name} | " + " | ".join(row) + " |")
