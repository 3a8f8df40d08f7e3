"""Over- or under-fitting at a glance: one-step PSNR of models on 40 test items and 40 train items
(spread evenly over the train pack), at the packs shrunk to SIZE, raw and after the evaluation's
per-channel least-squares scale (`evaluation.metrics.scale_fit`, whole frame) — what the training loss
sees vs. roughly what the evaluation protocol forgives.

    .venv/bin/python scripts/raw_vs_fitted.py [--cache DIR] [--train-pack NAME] [--size 64] MODEL_DIR [...]
"""
import argparse
from pathlib import Path

import numpy as np
import torch

from relight_core.checkpoint import load_model
from relight_core.evaluation.metrics import psnr, scale_fit
from relight_core.training.fast import load_pack, make_batch, sample_relight, shrink_pack

ITEMS = 40


def mean_psnr(pred: torch.Tensor, truth: torch.Tensor, fitted: bool) -> float:
    """Mean PSNR over items of decoded [-1,1] clips [B,3,T,H,W], raw or after the protocol's scale fit."""
    values = []
    pred01, truth01 = ((x.float().permute(0, 2, 3, 4, 1).numpy() + 1) / 2 for x in (pred, truth))
    for p, t in zip(pred01, truth01, strict=True):
        values.append(psnr(scale_fit(p, t)[0] if fitted else np.clip(p, 0, 1), t))
    return float(np.mean(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "unirelight-studio")
    parser.add_argument("--train-pack", default="train.npz", help="the train pack's file name in the cache")
    parser.add_argument("--size", type=int, default=64)
    args = parser.parse_args()
    test = load_pack(args.cache / "test.npz", torch.device("cpu"))
    train = load_pack(args.cache / args.train_pack, torch.device("cpu"))
    count = len(train["rgb"])
    spread = torch.arange(0, count, max(1, count // ITEMS))[:ITEMS]
    train = {k: v[spread] if torch.is_tensor(v) and v.shape[:1] == (count,) else v for k, v in train.items()}
    for model in args.models:
        spec, dit, tok = load_model(model)
        for split, pack in (("test", test), ("train", train)):
            pack = shrink_pack(pack, args.size, tok.spatial_factor)
            idx = torch.arange(min(ITEMS, len(pack["rgb"])))
            batch = make_batch(pack, tok, idx, torch.zeros_like(idx), torch.zeros_like(idx, dtype=torch.bool))
            x0 = sample_relight(dit, batch, 1, seed=0, autocast=True, residual=spec.residual)
            t = batch["input"].shape[2]
            relit, albedo = tok.decode(x0[:, :, t:2 * t]), tok.decode(x0[:, :, 2 * t:])
            truth_relit, truth_albedo = tok.decode(batch["relit"]), tok.decode(batch["albedo"])
            print(f"{Path(model).name} {split}: raw relit {mean_psnr(relit, truth_relit, False):.2f} albedo "
                  f"{mean_psnr(albedo, truth_albedo, False):.2f} | fitted relit "
                  f"{mean_psnr(relit, truth_relit, True):.2f} albedo {mean_psnr(albedo, truth_albedo, True):.2f}")


if __name__ == "__main__":
    main()
