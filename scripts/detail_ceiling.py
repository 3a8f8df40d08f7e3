"""How much spatial detail of the lighting change a score needs: the *true* relit and albedo taken
through the default model's own output path, scored by the evaluation protocol.

Each test item's ground truth is shrunk to the model's size (as `media.resize_frames` shrinks a user's
frames), its offset from the input smoothed by the calibrated offset filter (`upsample.smooth_offset`)
at a given radius, and brought back to the data's size by guided ratio upsampling — exactly what
`Relighter` does to the model's prediction. A perfect model scores this; the table says which filter
radius (how blurred a lighting change) still reaches a target PSNR, and so how fine the shading and
shadow detail the model has to predict. Also a plain box blur of the true ratio at the data's size.

    python scripts/detail_ceiling.py --pack ~/.cache/unirelight-studio/test.npz --size 64
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relight_core.evaluation.metrics import protocol_psnr
from relight_core.media import resize_frames
from relight_core.training.pack import load_pack
from relight_core.upsample import guided_ratio_upsample, smooth_offset


def box_ratio(inp: np.ndarray, target: np.ndarray, radius: int, eps: float = 1e-2) -> np.ndarray:
    """input × box-blurred (target ÷ input), [H,W,3] in [0, 1]."""
    if radius == 0:
        return target
    x, t = (torch.from_numpy(a).permute(2, 0, 1)[None] for a in (inp, target))
    ratio = F.pad((t + eps) / (x + eps), (radius,) * 4, mode="replicate")
    blurred = F.avg_pool2d(ratio, 2 * radius + 1, 1)
    return ((x + eps) * blurred - eps).clamp(0, 1)[0].permute(1, 2, 0).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pack", type=Path, required=True, help="a test pack (training.pack)")
    parser.add_argument("--size", type=int, default=64, help="the model's working size (px)")
    parser.add_argument("--radii", default="0,2,4,8,16", help="offset filter radii at the model's size")
    parser.add_argument("--box", default="1,2,4,8,16,32", help="box-blur radii at the data's size")
    args = parser.parse_args()
    pack = load_pack(args.pack)
    rgb = pack["rgb"].permute(0, 1, 3, 4, 2).numpy().astype(np.float32) / 255    # (N, 2, H, W, 3)
    albedo = pack["albedo"].permute(0, 2, 3, 1).numpy().astype(np.float32) / 255  # (N, H, W, 3)
    mask = pack["mask"].numpy()
    n = len(rgb)

    def through_model_path(inp, target, radius):
        small_in, small_target = resize_frames(inp[None], args.size, 8), resize_frames(target[None], args.size, 8)
        return guided_ratio_upsample(inp[None], small_in, smooth_offset(small_in, small_target, radius))[0]

    def score(make):
        relit = [protocol_psnr(make(rgb[i, 1 - t], rgb[i, t]), rgb[i, t], mask[i]) for i in range(n) for t in (0, 1)]
        alb = [protocol_psnr(make(rgb[i, 0], albedo[i]), albedo[i], mask[i]) for i in range(n)]
        return float(np.mean(relit)), float(np.mean(alb))

    print(f"{n} items ({2 * n} relit directions), {rgb.shape[2]} px data, model size {args.size} px\n")
    print("| true result through the model's path | relit | albedo |\n|---|---|---|")
    for radius in (int(r) for r in args.radii.split(",")):
        relit, alb = score(lambda inp, target, r=radius: through_model_path(inp, target, r))
        print(f"| offset filter radius {radius} px | {relit:.2f} | {alb:.2f} |", flush=True)
    print("\n| true ratio, box-blurred at the data's size | relit | albedo |\n|---|---|---|")
    for radius in (int(r) for r in args.box.split(",")):
        relit, alb = score(lambda inp, target, r=radius: box_ratio(inp, target, r))
        print(f"| box radius {radius} px | {relit:.2f} | {alb:.2f} |", flush=True)


if __name__ == "__main__":
    main()
