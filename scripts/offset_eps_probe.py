"""Which regularisation `eps` the offset filter (`upsample.smooth_offset`) should use: a residual
model's relit and albedo on held-out items, their offsets smoothed at each (eps, radius), scored by
`training.calibrate.measure_filters` at the model's own gains (one sampling pass for every eps).

`eps` sets how strong an edge of the input (the guide) must be for the filter to keep a change of the
offset across it: small keeps every texture edge (and the model's blotches along them), large is a
plain box blur. `calibrate` sweeps radii at the project's `GUIDE_EPS`; this says whether that eps is
still the right one for a model.

    python scripts/offset_eps_probe.py --model default --data ~/.cache/unirelight-studio/data
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relight_core.evaluation.harness import load_items, resized  # noqa: E402
from relight_core.pipeline import Relighter  # noqa: E402
from relight_core.training.calibrate import measure_filters  # noqa: E402

EPS = (1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 1.0)
RADII = (2, 4, 8, 12, 16, 24)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="default")
    parser.add_argument("--data", type=Path, required=True, help="render-data output")
    parser.add_argument("--split", default="test")
    parser.add_argument("--items", type=int, default=48)
    parser.add_argument("--skip", type=int, default=16, help="as calibrate's: leave out the first items")
    parser.add_argument("--size", type=int, default=128, help="score at this long side")
    args = parser.parse_args()

    relighter = Relighter.load(args.model)
    gains = relighter.spec.residual_gain
    items = [resized(item, args.size, relighter.frame_multiple)
             for item in load_items(args.data, args.split, args.items, spread=True, skip=args.skip)]
    table = measure_filters(relighter, items, sorted(set(gains)), RADII, EPS)
    print(f"{len(items)} {args.split} items (after the first {args.skip}) at {args.size} px; gains "
          f"{gains}, the model's own radii {relighter.spec.offset_filter}")
    for clip, gain in zip(("relit", "albedo"), gains):
        print(f"{clip} PSNR (dB), eps (rows) by radius (columns, px at the model's size):")
        print("  eps     " + "".join(f"  r={r:<4d}" for r in RADII))
        for eps in EPS:
            print(f"  {eps:6.0e}  " + "".join(f"  {table[gain, r, eps][clip]:6.2f}" for r in RADII))


if __name__ == "__main__":
    main()
