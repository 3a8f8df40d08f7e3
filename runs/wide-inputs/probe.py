"""Does the default model relight a 16:9 frame as well as a square one? It was trained on square 128-px frames only;
16:9 inputs run at 128×72 since 2026-12-06 (before, they failed on the command line). On test items (128², held-out
probes, meshes and textures) this takes the middle 72 rows — a 16:9 frame — and scores, on those rows, by the
protocol (per-channel scale fit on the mask):
  crop      the 128×72 frame relit as it is (what a user's 16:9 input gets);
  pad       the 128×72 frame reflected to 128×128, relit, cropped back (an alternative: square frames, 1.8× tokens);
  context   the whole 128² item relit, cropped to the rows (a reference a real 16:9 input cannot have: more scene).
Paired per item, ± the standard error over scenes.
    PYTHONPATH=. python runs/wide-inputs/probe.py DATA [N]
"""
import os
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter, RelightRequest

torch.set_num_threads(int(os.environ.get("T", "2")))
TOP, ROWS = 28, 72


def run(r, frames, probe):
    result = r.relight(RelightRequest(frames, mode="relight", camera_probe=probe))
    return result.relit, result.albedo


def main() -> None:
    data = Path(sys.argv[1])
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 80
    items = load_items(data, "test", n)
    r = Relighter.load("default", device="cpu", precision=os.environ.get("P", "auto"))
    rows = slice(TOP, TOP + ROWS)
    scores = defaultdict(list)
    for it in items:
        crop = it.input[:, rows]
        pad = np.pad(crop, ((0, 0), (TOP, 128 - TOP - ROWS), (0, 0), (0, 0)), mode="reflect")
        outs = {"crop": run(r, crop, it.probe),
                "pad": tuple(x[:, rows] for x in run(r, pad, it.probe)),
                "context": tuple(x[:, rows] for x in run(r, it.input, it.probe))}
        mask, target, albedo = it.mask[:, rows], it.target[:, rows], it.albedo[:, rows]
        for way, (relit, alb) in outs.items():
            scores[way, "relit"].append(protocol_metrics(relit, target, mask)["psnr"])
            scores[way, "albedo"].append(protocol_metrics(alb, albedo, mask)["psnr"])
        scores["floor", "relit"].append(protocol_metrics(crop, target, mask)["psnr"])
        scores["scene", None].append(it.name.split()[0])
    scenes = np.array(scores["scene", None])

    def paired(a, b):
        d = np.array(a) - np.array(b)
        per_scene = np.array([d[scenes == s].mean() for s in np.unique(scenes)])
        return f"{d.mean():+.3f} ± {per_scene.std(ddof=1) / np.sqrt(len(per_scene)):.3f} ({(d > 0).sum()} of {len(d)} up)"

    print(f"{len(items)} test items, middle {ROWS} of 128 rows, default model, precision {r.precision}")
    print("| way | relit PSNR | albedo PSNR | relit vs crop | albedo vs crop |\n|---|---|---|---|---|")
    for way in ("crop", "pad", "context"):
        print(f"| {way} | {np.mean(scores[way, 'relit']):.2f} | {np.mean(scores[way, 'albedo']):.2f} | "
              f"{paired(scores[way, 'relit'], scores['crop', 'relit'])} | "
              f"{paired(scores[way, 'albedo'], scores['crop', 'albedo'])} |")
    print(f"| floor (the crop unchanged) | {np.mean(scores['floor', 'relit']):.2f} | | | |")


if __name__ == "__main__":
    main()
