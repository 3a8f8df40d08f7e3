"""The shift average at the DiT (before the refiners, as `Relighter`'s ensemble averages): `_members` and
`_decode` patched so that member m sees the frames rolled by SHIFTS[m] pixels (no mirror) and its result is
rolled back, the rolled-in border strips weighted zero. Paired against ensemble 1 on the first N test items.
    PYTHONPATH=. python runs/shift-average/dit_level.py N K MODEL
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.evaluation.metrics import protocol_metrics
from relight_core.pipeline import Relighter

SHIFTS = [(0, 0), (4, 4), (4, 0), (0, 4), (-4, -4), (-4, 4), (4, -4), (-4, 0)]


def members(self, request, frames, albedo, probe, rotations, overlap, count):
    variants = [self._conditions(request, np.roll(frames, s, axis=(1, 2)), albedo, probe, rotations, overlap)
                for s in SHIFTS[:count]]
    return torch.cat([v[0] for v in variants]), variants[0][1], torch.cat([v[2] for v in variants])


def decode(self, x0, t, length):
    count = x0.shape[0]
    clips = x0[:, :, t:].float()
    both = torch.cat([clips[:, :, :t], clips[:, :, t:]], dim=0)
    with torch.no_grad(), self._autocast():
        video = self.tokenizer.decode(both).float()
    frames = ((video.clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 4, 1).cpu().numpy()[:, :length]
    h, w = frames.shape[2:4]
    out = []
    for clip in (frames[:count], frames[count:]):
        total, weight = 0, 0
        for m in range(count):
            dy, dx = SHIFTS[m]
            valid = np.ones((h, w), np.float32)
            if dy > 0: valid[:dy] = 0
            if dy < 0: valid[dy:] = 0
            if dx > 0: valid[:, :dx] = 0
            if dx < 0: valid[:, dx:] = 0
            total = total + np.roll(clip[m] * valid[None, :, :, None], (-dy, -dx), axis=(1, 2))
            weight = weight + np.roll(valid, (-dy, -dx), axis=(0, 1))
        out.append((total / weight[None, :, :, None]).astype(np.float32))
    return out[0], out[1]


def score(items, outs):
    return (np.array([protocol_metrics(o[0], it.target, it.mask)["psnr"] for o, it in zip(outs, items)]),
            np.array([protocol_metrics(o[1], it.albedo, it.mask)["psnr"] for o, it in zip(outs, items)]))


def main():
    torch.set_num_threads(int(os.environ.get("T", "2")))
    n, k, model = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    items = load_items(Path.home() / ".cache/unirelight-studio/data", "test", n)
    r = Relighter.load(model, device="cpu", precision="fp32")
    plain = [relight(r, it.input, it.probe, RunOptions())[:2] for it in items]
    Relighter._members, Relighter._decode = members, decode
    shifted = [relight(r, it.input, it.probe, RunOptions(ensemble=k))[:2] for it in items]
    a, b = score(items, plain), score(items, shifted)
    for j, name in enumerate(("relit", "albedo")):
        d = (b[j] - a[j]).reshape(-1, 2).mean(1)
        print(f"{k} shifts at the DiT, {name}: {a[j].mean():.3f} → {b[j].mean():.3f}  paired {d.mean():+.3f} ± "
              f"{d.std(ddof=1) / np.sqrt(len(d)):.3f} (SE over scenes)")


if __name__ == "__main__":
    main()
