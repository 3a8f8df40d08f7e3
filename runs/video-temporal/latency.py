"""The temporal filter's cost: the example orbit video (17 frames at the model's size, sunset probe) relit with
and without it, 2 threads, `auto` precision, median of 3 each, one after the other; and the filter alone on 100
random 128-px frames (median of 3).
    PYTHONPATH=. python runs/video-temporal/latency.py
"""
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from relight_core import media
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.temporal import temporal_filter

torch.set_num_threads(2)
root = Path(__file__).resolve().parents[2]
r = Relighter.load("default", device="cpu")
frames = media.resize_frames(media.load_media(root / "examples/inputs/orbit.mp4").frames, r.spec.size)
request = RelightRequest(frames, probe=load_probe(root / "envmaps/sunset.exr"))
r.relight(request)  # warm-up
on = r.spec
for name, spec in (("with the filter", on), ("without", replace(on, temporal_filter=(0,) + on.temporal_filter[1:]))):
    r.spec = spec
    times = []
    for _ in range(3):
        started = time.perf_counter()
        r.relight(request)
        times.append(time.perf_counter() - started)
    print(f"{name}: {np.median(times):.3f} s for {len(frames)} frames of {frames.shape[2]}×{frames.shape[1]}")
rng = np.random.default_rng(0)
guide = rng.random((100, 128, 128, 3), dtype=np.float32)
outs = [rng.random((100, 128, 128, 3), dtype=np.float32) for _ in range(2)]
times = []
for _ in range(3):
    started = time.perf_counter()
    temporal_filter(guide, outs, *on.temporal_filter, distances=np.zeros((100, 100)))
    times.append(time.perf_counter() - started)
print(f"the filter alone, relit + albedo of 100 frames of 128×128: {np.median(times):.3f} s")
