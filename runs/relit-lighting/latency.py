"""Seconds a 128-px relight takes (median of 7 after a warm-up) for model folders, precision auto and fp32:
    PYTHONPATH=. python runs/relit-lighting/latency.py models/default [OTHER_MODEL ...]"""
import statistics
import sys
import time

import numpy as np
import torch

from relight_core.pipeline import Relighter, RelightRequest

torch.set_num_threads(2)
frames = np.random.default_rng(0).random((1, 128, 128, 3)).astype(np.float32)
probe = np.ones((64, 128, 3), np.float32)
probe[10:16, 30:40] = 50.0
for precision in ("auto", "fp32"):
    for model in sys.argv[1:]:
        relighter = Relighter.load(model, device="cpu", precision=precision)
        request = RelightRequest(frames=frames, probe=probe)
        relighter.relight(request)
        times = []
        for _ in range(7):
            started = time.perf_counter()
            relighter.relight(request)
            times.append(time.perf_counter() - started)
        print(f"{precision} {relighter.precision} {model}: {statistics.median(times):.3f} s", flush=True)
