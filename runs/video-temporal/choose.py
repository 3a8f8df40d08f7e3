"""Choosing the temporal filter's settings, offline, on the shipped model's cached outputs for the seed-11 clips
(cache_outputs.py): the input-guided filter along time with a weight for the frames' light distance (tau; None =
the light ignored), paired per item against the unfiltered outputs, ± SE over scenes, and the relit gain by motion.
This is the prototype of relight_core/temporal.py (the light distance here from the dataset's camera probes).
    PYTHONPATH=. python runs/video-temporal/choose.py      (choose-seed11.txt)
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from probe import score  # noqa: E402
from relight_core.evaluation.harness import load_items  # noqa: E402
from relight_core.lighting.panorama import downsample_panorama  # noqa: E402

C = Path.home() / ".cache/unirelight-studio"
items = load_items(C / "clips", "test")
outs = np.load(C / "clips-out-default.npz")

def light_dist(probe):
    p = downsample_panorama(torch.as_tensor(probe, dtype=torch.float32), 16).numpy()
    m = p.mean(axis=(1, 2, 3))
    T = len(p)
    d = np.zeros((T, T))
    for t in range(T):
        for s in range(T):
            d[t, s] = np.abs(p[t] - p[s]).mean() / (0.5 * (m[t] + m[s]))
    return d

def filt(o, x, d, radius, sigma, tau):
    T = len(o); out = np.empty_like(o)
    for t in range(T):
        num = np.zeros_like(o[t]); den = np.zeros(o.shape[1:3] + (1,), np.float32)
        for s in range(max(0, t - radius), min(T, t + radius + 1)):
            wl = 1.0 if tau is None else np.exp(-(d[t, s] / tau) ** 2)
            w = wl * np.exp(-((x[t] - x[s]) ** 2).sum(-1, keepdims=True) / (2 * sigma ** 2))
            num += w * o[s]; den += w
        out[t] = num / den
    return out

dists = [light_dist(it.probe) for it in items]
motions = [json.loads((C / "clips/test" / it.name.split()[0] / "meta.json").read_text())["motion"] for it in items]
adj = [np.diag(d, 1).mean() for d in dists]
for kind in sorted({k for m in motions for k in m}):
    print(kind, "adjacent light distance", np.round(np.mean([a for a, m in zip(adj, motions) if kind in m]), 3))
variants = [("raw", None), ("r2 s.05 tau inf", (2, .05, None)), ("r2 s.05 tau .5", (2, .05, .5)),
            ("r2 s.05 tau .3", (2, .05, .3)), ("r2 s.05 tau .1", (2, .05, .1)), ("r2 s.05 tau .03", (2, .05, .03)),
            ("r3 s.05 tau .3", (3, .05, .3)), ("r4 s.05 tau .3", (4, .05, .3)), ("r3 s.08 tau .3", (3, .08, .3))]
res = {}
for name, v in variants:
    rows = []
    for i, it in enumerate(items):
        row = {}
        for kind, truth in (("relit", it.target), ("albedo", it.albedo)):
            o = outs[f"{kind}{i}"]
            f = o if v is None else filt(o, it.input, dists[i], *v)
            row[kind] = score(f, truth, it.mask)
        rows.append(row)
    res[name] = rows
for name, _ in variants:
    line = name
    for kind in ("relit", "albedo"):
        d = np.array([r[kind]["psnr"] for r in res[name]]) - np.array([r[kind]["psnr"] for r in res["raw"]])
        # SE over scenes (2 items a scene)
        ds = d.reshape(-1, 2).mean(1)
        line += f" | {kind} {d.mean():+.3f}±{ds.std(ddof=1)/np.sqrt(len(ds)):.3f} temporal {255*np.mean([r[kind]['temporal'] for r in res[name]]):.2f} flicker {255*np.mean([r[kind]['flicker'] for r in res[name]]):.2f}"
    for kind in ("light", "orbit", "oscillate", "objects"):
        sel = [k for k, m in enumerate(motions) if kind in m]
        d = np.array([res[name][k]["relit"]["psnr"] - res["raw"][k]["relit"]["psnr"] for k in sel])
        line += f" | {kind} {d.mean():+.3f}"
    print(line)
