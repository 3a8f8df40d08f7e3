"""Could a small convolutional refiner add the detail the default model lacks? A measurement, not a
product feature (docs/QUALITY.md, "A detail refiner on the results").

The shipped model's results at 128 px (its whole path: 64 px, gains, offset filter, guided ratio back
to 128 — `evaluation.harness.relight`, as `evaluate --size 128` runs it) go with the 128-px input into
a U-Net (~0.8M parameters) that predicts a correction of the relit and albedo results, its last layer
zero so that it starts as the identity. Trained on the train pack's items (both directions of each
scene; left↔right flips, exact for a network that never sees the probe), scored by the evaluation
protocol on the test split's first 80 items.

    # 1. the model's results on the test items and on pack items (chunks; two processes side by side)
    .venv/bin/python scripts/refiner_probe.py results --data ~/.cache/unirelight-studio/data --out R/test80.npz
    .venv/bin/python scripts/refiner_probe.py results --pack ~/.cache/unirelight-studio/train-s3-all-3.npz \\
        --start 0 --count 400 --out R/train-0.npz
    # 2. train and score
    .venv/bin/python scripts/refiner_probe.py train --test R/test80.npz --out R/run --minutes 40 R/train-*.npz
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relight_core.evaluation.harness import RunOptions, brought_back, load_items, model_size, relight  # noqa: E402
from relight_core.evaluation.metrics import protocol_psnr  # noqa: E402
from relight_core.media.image import to_uint8  # noqa: E402
from relight_core.pipeline import Relighter  # noqa: E402
from relight_core.precision import resolve_precision  # noqa: E402
from relight_core.requests import RelightRequest  # noqa: E402


def results(args) -> None:
    """input, target, albedo, mask and the model's relit0 / albedo0 at the items' size, uint8."""
    relighter = Relighter.load(args.model, precision="fp32")
    rec: dict[str, list] = {k: [] for k in ("input", "target", "albedo", "mask", "relit0", "albedo0")}
    if args.pack:
        from relight_core.training.pack import load_pack
        pack = load_pack(args.pack)
        for i in range(args.start, min(args.start + args.count, len(pack["rgb"]))):
            for t in (0, 1):  # relight the scene under its other probe to probe t
                frames = pack["rgb"][i, 1 - t].permute(1, 2, 0).numpy()[None].astype(np.float32) / 255
                small = model_size(relighter, frames)
                result = relighter.relight(RelightRequest(small, mode="relight", seed=0,
                                                          camera_probe=pack["env"][i, t].numpy()[None]))
                rec["input"].append(to_uint8(frames[0]))
                rec["target"].append(pack["rgb"][i, t].permute(1, 2, 0).numpy())
                rec["albedo"].append(pack["albedo"][i].permute(1, 2, 0).numpy())
                rec["mask"].append(pack["mask"][i].numpy())
                rec["relit0"].append(to_uint8(brought_back(frames, small, result.relit)[0]))
                rec["albedo0"].append(to_uint8(brought_back(frames, small, result.albedo)[0]))
    else:
        for item in load_items(args.data, "test", args.count):
            relit, albedo, _ = relight(relighter, item.input, item.probe, RunOptions(seed=0))
            for key, value in (("input", item.input), ("target", item.target), ("albedo", item.albedo),
                               ("relit0", relit), ("albedo0", albedo)):
                rec[key].append(to_uint8(value[0]))
            rec["mask"].append(item.mask[0] > 0.5)
    np.savez(args.out, **{k: np.stack(v) for k, v in rec.items()})
    print(f"wrote {len(rec['input'])} items to {args.out}")


class Block(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.a, self.b = nn.Conv2d(c, c, 3, padding=1), nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x):
        return x + self.b(F.silu(self.a(F.silu(x))))


class Refiner(nn.Module):
    """U-Net over (input, relit0, albedo0) in [-1, 1] → relit0, albedo0 plus a correction."""

    def __init__(self, w: int = 24):
        super().__init__()
        self.stem, self.e1 = nn.Conv2d(9, w, 3, padding=1), Block(w)
        self.d1, self.e2 = nn.Conv2d(w, 2 * w, 4, 2, 1), Block(2 * w)
        self.d2, self.mid = nn.Conv2d(2 * w, 4 * w, 4, 2, 1), nn.Sequential(*[Block(4 * w) for _ in range(3)])
        self.u2, self.f2 = nn.Conv2d(6 * w, 2 * w, 3, padding=1), Block(2 * w)
        self.u1, self.f1 = nn.Conv2d(3 * w, w, 3, padding=1), Block(w)
        self.head = nn.Conv2d(w, 6, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x):
        h1 = self.e1(self.stem(x))
        h2 = self.e2(self.d1(h1))
        h3 = self.mid(self.d2(h2))
        g2 = self.f2(self.u2(torch.cat([F.interpolate(h3, scale_factor=2, mode="bilinear"), h2], 1)))
        g1 = self.f1(self.u1(torch.cat([F.interpolate(g2, scale_factor=2, mode="bilinear"), h1], 1)))
        return x[:, 3:9] + self.head(F.silu(g1))


def load(paths) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    parts = [np.load(p) for p in paths]

    def cat(key):
        return np.concatenate([z[key] for z in parts])
    x = np.concatenate([cat("input"), cat("relit0"), cat("albedo0")], -1)
    y = np.concatenate([cat("target"), cat("albedo")], -1)
    return (torch.from_numpy(x).permute(0, 3, 1, 2).contiguous(), torch.from_numpy(y).permute(0, 3, 1, 2).contiguous(),
            torch.from_numpy(cat("mask")))


def signed(u8: torch.Tensor, device: torch.device | str = "cpu") -> torch.Tensor:
    return u8.to(device).float() / 127.5 - 1


def score(net, x, y, m) -> tuple[float, float]:
    """Mean protocol PSNR (relit, albedo) of the refined results."""
    device = next(net.parameters()).device
    net.eval()
    relit, albedo = [], []
    with torch.no_grad():
        for i in range(0, len(x), 16):
            pred = ((net(signed(x[i:i + 16], device)).float().clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).cpu().numpy()
            truth = (y[i:i + 16].float() / 255).permute(0, 2, 3, 1).numpy()
            mask = m[i:i + 16].float().numpy()
            for k in range(len(pred)):
                relit.append(protocol_psnr(pred[k, None, ..., :3], truth[k, None, ..., :3], mask[k, None]))
                albedo.append(protocol_psnr(pred[k, None, ..., 3:], truth[k, None, ..., 3:], mask[k, None]))
    net.train()
    return float(np.mean(relit)), float(np.mean(albedo))


def train(args) -> None:
    torch.manual_seed(0)
    tx, ty, tm = load([args.test])
    x, y, m = load(args.train)
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    net = Refiner(args.width).to(device, memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    fast = resolve_precision("auto", device) == torch.bfloat16  # bf16 only where this device runs it fast
    log = Path(f"{args.out}.jsonl").open("a")

    def write(**record):
        log.write(json.dumps(record) + "\n")
        log.flush()
        print(json.dumps(record), flush=True)
    write(event="start", items=len(x), params=sum(p.numel() for p in net.parameters()),
          test=score(net, tx, ty, tm))
    generator = torch.Generator().manual_seed(0)
    started, step = time.time(), 0
    while time.time() - started < args.minutes * 60:
        progress = (time.time() - started) / (args.minutes * 60)
        for group in opt.param_groups:
            group["lr"] = args.lr * min(1, (step + 1) / 100) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))
        index = torch.randint(0, len(x), (args.batch,), generator=generator)
        flip = (torch.rand(args.batch, generator=generator) < 0.5).view(-1, 1, 1, 1)
        flip = flip.to(device)
        xb, yb, mb = (torch.where(flip, v.flip(-1), v).contiguous(memory_format=torch.channels_last)
                      for v in (signed(x[index], device), signed(y[index], device),
                                m[index].to(device).float()[:, None]))
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=fast):
            pred = net(xb)
        weight = 0.1 + mb  # the foreground counts, the background a little
        loss = ((pred.float() - yb) ** 2 * weight).sum() / (weight.sum() * 6)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 50 == 0:
            write(step=step, loss=round(float(loss.detach()), 5), seconds=round(time.time() - started))
        if step % args.eval_every == 0:
            write(step=step, test=score(net, tx, ty, tm))
    write(step=step, final=True, test=score(net, tx, ty, tm))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("results")
    r.add_argument("--model", default="default")
    r.add_argument("--data", type=Path, help="render-data output: its test split's first --count items")
    r.add_argument("--pack", type=Path, help="a train pack: scenes --start … --start + --count")
    r.add_argument("--start", type=int, default=0)
    r.add_argument("--count", type=int, default=80)
    r.add_argument("--out", type=Path, required=True)
    t = sub.add_parser("train")
    t.add_argument("train", nargs="+", type=Path)
    t.add_argument("--test", type=Path, required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--minutes", type=float, default=40)
    t.add_argument("--width", type=int, default=24)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--eval-every", type=int, default=400)
    t.add_argument("--device", default=None, help="cpu or cuda (default: cuda when there is one)")
    args = parser.parse_args()
    if args.command == "results" and (args.data is None) == (args.pack is None):
        parser.error("results takes --data (test items) or --pack (train items)")
    (results if args.command == "results" else train)(args)


if __name__ == "__main__":
    main()
