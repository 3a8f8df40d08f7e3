"""Cache the shipped model's results on the first N test items twice — on the 32-spp inputs the test split has and on
the same scenes rendered at 529 spp (`render-data --spp 529`, same seed: the same scenes, near-clean) — with both
renders' targets, for `analyse.py`.
    PYTHONPATH=. python runs/render-noise/cache.py DATA DATA_HQ N OUT.npz
"""
import os
import sys

import numpy as np
import torch

from relight_core.evaluation.harness import load_items
from relight_core.pipeline import Relighter, RelightRequest

torch.set_num_threads(int(os.environ.get("T", "2")))


def main() -> None:
    data, hq, n, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    items, clean = load_items(data, "test", n), load_items(hq, "test", n)
    r = Relighter.load("default", device="cpu", precision=os.environ.get("P", "fp32"))
    keep: dict[str, list] = {}
    for it, cl in zip(items, clean):
        assert it.name == cl.name, (it.name, cl.name)
        noisy = r.relight(RelightRequest(it.input, mode="relight", camera_probe=it.probe))
        clean_run = r.relight(RelightRequest(cl.input, mode="relight", camera_probe=cl.probe))
        for key, value in (("name", it.name), ("input", it.input[0]), ("clean_input", cl.input[0]),
                           ("target", it.target[0]), ("clean_target", cl.target[0]),
                           ("albedo_target", it.albedo[0]), ("mask", it.mask[0]),
                           ("relit", noisy.relit[0]), ("albedo", noisy.albedo[0]),
                           ("relit_clean_in", clean_run.relit[0]), ("albedo_clean_in", clean_run.albedo[0])):
            keep.setdefault(key, []).append(value)
    np.savez(out, **{k: np.stack(v) for k, v in keep.items()})


if __name__ == "__main__":
    main()
