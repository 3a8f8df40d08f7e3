"""Choosing the temporal filter's settings, offline, on the shipped model's cached outputs for the seed-11 clips
(cache_outputs.py): the input-guided filter along time with a weight for the frames' light distance (tau; None =
the light ignored), paired per item against the unfiltered outputs, ± SE over scenes, and the relit gain by motion.
It runs relight_core/temporal.py's filter, the light distance from the dataset's camera probes.
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
from relight_core.temporal import light_descriptor, light_distances, temporal_filter  # noqa: E402

C = Path.home() / ".cache/unirelight-studio"
items = load_items(C / "clips", "test")
outs = np.load(C / "clips-out-default.npz")

def filt(o, x, d, radius, sigma, tau):
    """The library's filter (relight_core/temporal.py); tau None: the light not weighed."""
    return temporal_filter(x, [o], radius, sigma, tau or 1.0, distances=None if tau is None else d)[0]


dists = [light_distances(light_descriptor(torch.as_tensor(it.probe, dtype=torch.float32)), 4) for it in items]
motions = [json.loads((C / "clips/test" / it.name.split()[0] / "meta.json").read_text())["motion"] for it in items]
adj = [d[0, :-1].mean() for d in dists]
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
