"""How steady are the shipped model's video results? The model is an image model run frame by frame (one
shared noise draw a clip), so what it gets wrong can change from frame to frame — flicker a still image never
shows. On 9-frame test clips (`render-data --split test --frames 9 --seed 11`: held-out probes, meshes and
textures, each clip with one or two of camera orbit, camera sway, light rotation and object motion) this scores
each item's relit and albedo clips by the protocol (one per-channel scale fitted over the whole clip) and their
**temporal error**: the RMS, over the mask of both frames, of (out[t+1] − out[t]) − (truth[t+1] − truth[t]) after
that scale fit — what changes between frames that should not, or does not change that should. A clip's result
that flickers scores worse here than the input clip itself does (the floor); the albedo's truth changes only by
the motion.
    PYTHONPATH=. python runs/video-temporal/probe.py DATA MODEL [N]   (writes nothing; prints a table)
"""
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics

torch.set_num_threads(int(os.environ.get("T", "2")))


def score(pred, truth, mask) -> dict:
    """PSNR by the protocol and the clip's steadiness (`metrics.steadiness`: "temporal", "flicker")."""
    metrics = protocol_metrics(pred, truth, mask)
    return {key: metrics[key] for key in ("psnr", "temporal", "flicker")}


def main() -> None:
    from relight_core.pipeline import Relighter

    data, model = Path(sys.argv[1]), sys.argv[2]
    n = int(sys.argv[3]) if len(sys.argv) > 3 else None
    items = load_items(data, "test", n)
    r = Relighter.load(model, device="cpu", precision="fp32")
    rows = []
    for it in items:
        motion = json.loads((data / "test" / it.name.split()[0] / "meta.json").read_text())["motion"]
        relit, albedo, _ = relight(r, it.input, it.probe, RunOptions())
        rows.append({"name": it.name, "motion": motion,
                     "relit": score(relit, it.target, it.mask), "albedo": score(albedo, it.albedo, it.mask),
                     "floor_relit": score(it.input, it.target, it.mask),
                     "floor_albedo": score(it.input, it.albedo, it.mask)})
        print(json.dumps(rows[-1]), flush=True)
    print(f"\n{len(rows)} clip items of {len(items[0].input)} frames, model {model}")
    print("| | PSNR | temporal error (/255) | flicker (/255) |\n|---|---|---|---|")
    for key in ("relit", "floor_relit", "albedo", "floor_albedo"):
        m = {k: np.mean([row[key][k] for row in rows]) for k in ("psnr", "temporal", "flicker")}
        print(f"| {key} | {m['psnr']:.2f} | {255 * m['temporal']:.2f} | {255 * m['flicker']:.2f} |")
    for kind in sorted({k for row in rows for k in row["motion"]}):
        sub = [row for row in rows if kind in row["motion"]]
        print(f"{kind} ({len(sub)} items): relit temporal {255 * np.mean([r['relit']['temporal'] for r in sub]):.2f}"
              f" (floor {255 * np.mean([r['floor_relit']['temporal'] for r in sub]):.2f}), albedo temporal "
              f"{255 * np.mean([r['albedo']['temporal'] for r in sub]):.2f}, relit flicker "
              f"{255 * np.mean([r['relit']['flicker'] for r in sub]):.2f}")


if __name__ == "__main__":
    main()
