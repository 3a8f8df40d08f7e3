# A 128-px relight under the sunset probe for each model folder given (default: the shipped one); median of 10
# after a warm-up, 2 threads, auto precision.
#   PYTHONPATH=. python runs/colour-average/latency.py MODEL [MODEL ...]
import sys
import time

import numpy as np
import torch

from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest

torch.set_num_threads(2)
frames = np.random.default_rng(0).random((1, 128, 128, 3)).astype(np.float32)
probe = load_probe("envmaps/sunset.exr")
for model in sys.argv[1:] or ["models/default"]:
    r = Relighter.load(model, device="cpu", precision="auto")
    r.relight(RelightRequest(frames, probe=probe))
    t = []
    for _ in range(10):
        s = time.perf_counter()
        r.relight(RelightRequest(frames, probe=probe))
        t.append(time.perf_counter() - s)
    print(model, f"median {np.median(t):.3f} s")
