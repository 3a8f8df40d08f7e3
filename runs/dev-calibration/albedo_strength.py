"""The albedo refiner's strength on the development pack's scenes (test split, seed 2): the mean albedo PSNR at
each strength given, then each one paired per item against the first (give 1, the shipped value, first). The
relit refiner stays as shipped.

    OMP_NUM_THREADS=1 PYTHONPATH=. python runs/dev-calibration/albedo_strength.py DATA ITEMS S1 S2 ...
"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from relight_core.evaluation.harness import RunOptions, load_items, relight, resized
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.pipeline import Relighter


def main():
    data, count, strengths = Path(sys.argv[1]), int(sys.argv[2]), [float(s) for s in sys.argv[3:]]
    relighter = Relighter.load("models/default")
    items = [resized(item, relighter.spec.size, relighter.frame_multiple)
             for item in load_items(data, "test", count, spread=True)]
    config = relighter.refiner.config
    scores = {}
    for strength in strengths:
        relighter.refiner.config = replace(config, strength=strength)
        scores[strength] = np.array([protocol_psnr(relight(relighter, item.input, item.probe, RunOptions(seed=0))[1],
                                                   item.albedo, item.mask) for item in items])
        print(f"albedo strength {strength}: {scores[strength].mean():.3f}", flush=True)
    base = scores[strengths[0]]
    for strength in strengths[1:]:
        diff = scores[strength] - base
        print(f"{strength} - {strengths[0]}: {diff.mean():+.3f} ± {diff.std(ddof=1) / np.sqrt(len(diff)):.3f} "
              f"over {len(diff)} items")


if __name__ == "__main__":
    main()
