"""Over- or under-fitting at a glance: one-step PSNR of models on 40 test items and 40 train items
(every 75th of the pack), at the packs shrunk to SIZE, raw and after a per-channel least-squares scale
(whole frame) — what the training loss sees vs. roughly what the evaluation protocol forgives.

    .venv/bin/python scripts/raw_vs_fitted.py [--cache DIR] [--size 64] MODEL_DIR [MODEL_DIR ...]
"""
import argparse
from pathlib import Path

import torch
from safetensors.torch import load_file

from relight_core.dit import JointDiT
from relight_core.tokenizer.pixel import PixelTokenizer
from relight_core.training.fast import (FastConfig, dit_config, load_pack, make_batch, psnr, sample_relight,
                                        shrink_pack)


def fitted_psnr(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-item PSNR after a per-channel least-squares scale of pred, on [0,1] values."""
    p, t = (pred + 1) / 2, (truth + 1) / 2
    scale = (p * t).sum((-1, -2, -3), keepdim=True) / (p * p).sum((-1, -2, -3), keepdim=True).clamp_min(1e-8)
    return psnr((scale * p).clamp(0, 1) * 2 - 1, truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "unirelight-studio")
    parser.add_argument("--size", type=int, default=64)
    args = parser.parse_args()
    tok = PixelTokenizer(8)
    test = load_pack(args.cache / "test.npz", torch.device("cpu"))
    train = load_pack(args.cache / "train.npz", torch.device("cpu"))
    count = len(train["rgb"])
    spread = torch.arange(0, count, max(1, count // 40))[:40]
    train = {k: v[spread] if torch.is_tensor(v) and v.shape[:1] == (count,) else v for k, v in train.items()}
    packs = {name: shrink_pack(pack, args.size, 8) for name, pack in (("test", test), ("train", train))}
    for model in args.models:
        dit = JointDiT(dit_config(FastConfig(pack="", out="")))
        dit.load_state_dict({k: v.float() for k, v in load_file(str(Path(model) / "dit.safetensors")).items()})
        dit.eval()
        for split, pack in packs.items():
            idx = torch.arange(min(40, len(pack["rgb"])))
            batch = make_batch(pack, tok, idx, torch.zeros_like(idx), torch.zeros_like(idx, dtype=torch.bool))
            x0 = sample_relight(dit, batch, 1, seed=0, autocast=True, residual=True)
            t = batch["input"].shape[2]
            relit, albedo = tok.decode(x0[:, :, t:2 * t]), tok.decode(x0[:, :, 2 * t:])
            truth_relit, truth_albedo = tok.decode(batch["relit"]), tok.decode(batch["albedo"])
            print(f"{Path(model).name} {split}: raw relit {psnr(relit, truth_relit).mean():.2f} albedo "
                  f"{psnr(albedo, truth_albedo).mean():.2f} | fitted relit {fitted_psnr(relit, truth_relit).mean():.2f} "
                  f"albedo {fitted_psnr(albedo, truth_albedo).mean():.2f}")


if __name__ == "__main__":
    main()
