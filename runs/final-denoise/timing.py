"""Seconds a relight takes with the shipped model as it ships (one network call: the schedule ends at 0)
and with the clean-up call at σ_min it ran with before (its gains back to what they were fitted as), in
one process, turn about (an image fastest of N each, the example clip once each); and how far the results are
apart.

    PYTHONPATH=. python runs/final-denoise/timing.py [--repeats 3]
"""
import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from relight_core import media
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    relighter = Relighter.load("default", device="cpu")
    relighter.warm_up()
    shipped = relighter.spec
    before = replace(shipped, final_denoise=True, residual_gain=tuple(g ** 0.5 for g in shipped.residual_gain))
    probe = load_probe(ROOT / "envmaps" / "sunset.exr")
    image = media.resize_frames(media.load_media(ROOT / "examples" / "inputs" / "objects.png").frames,
                                shipped.size, multiple=relighter.frame_multiple)
    clip = media.resize_frames(media.load_media(ROOT / "examples" / "inputs" / "orbit.mp4").frames,
                               shipped.size, multiple=relighter.frame_multiple)
    print(f"torch {torch.__version__}, capability {torch.backends.cpu.get_cpu_capability()}, "
          f"{torch.get_num_threads()} threads, precision {relighter.precision}")
    for name, frames in (("image", image), ("video", clip)):
        times = {"shipped (1 call a frame)": [], "before (2 calls a frame)": []}
        results = {}
        for _ in range(args.repeats if name == "image" else 1):     # a clip once each
            for label, spec in zip(times, (shipped, before)):
                relighter.spec = spec
                started = time.perf_counter()
                result = relighter.relight(RelightRequest(frames, probe=probe))
                times[label].append(time.perf_counter() - started)
                results[label] = result
        relighter.spec = shipped
        a, b = results.values()
        gap = max(float(np.abs(getattr(a, k) - getattr(b, k)).max()) for k in ("relit", "albedo"))
        mean = max(float(np.abs(getattr(a, k) - getattr(b, k)).mean()) for k in ("relit", "albedo"))
        shape = "×".join(map(str, frames.shape[:3]))
        fastest = {label: min(t) for label, t in times.items()}
        parts = ", ".join(f"{label} {s:.2f} s" for label, s in fastest.items())
        ratio = fastest["before (2 calls a frame)"] / fastest["shipped (1 call a frame)"]
        print(f"{name} {shape}: {parts} (×{ratio:.2f}); results apart by at most {gap * 255:.2f}/255, "
              f"mean {mean * 255:.3f}/255")


if __name__ == "__main__":
    main()
