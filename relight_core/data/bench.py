"""Render cost and noise of the data engine: `python -m relight_core.data.bench` (numbers in docs/DATA.md)."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from relight_core.colour import linear_to_srgb
from relight_core.data.generate import frame_seed
from relight_core.data.render import SceneRenderer, init_mitsuba, render_device
from relight_core.data.scenes import sample_scene
from relight_core.errors import InputError


def seconds_per_frame(size: int, spp: int, scenes: int, seed: int = 0) -> tuple[float, float]:
    """(CPU seconds of this process, wall seconds) per rendered frame, including albedo, mask and camera-frame
    probe: on the CPU variant (one thread) the first is the cost, on the GPU the second."""
    total, wall, frames = 0.0, 0.0, 0
    for index in range(scenes):
        spec = sample_scene(seed, "train", index, frames=2)
        with SceneRenderer(spec, size, spp) as renderer:
            renderer.render(0, 0, seed=0)  # first render compiles kernels: not part of the steady cost
            renderer.render_aovs(0, seed=0)
            start, started = time.process_time(), time.perf_counter()
            for light in (0, 1):
                renderer.render(1, light, frame_seed(spec, 1))
                renderer.camera_probe(1, light)
            renderer.render_aovs(1, frame_seed(spec, 1))  # one albedo + mask pass serves both lights
            total += time.process_time() - start
            wall += time.perf_counter() - started
            frames += 2
    return total / frames, wall / frames


def psnr_against_reference(size: int, spps: list[int], reference_spp: int, scenes: int, seed: int = 0) -> dict:
    """Mean PSNR (dB, sRGB display values) of renders at each spp against a high-spp reference."""
    scores: dict[int, list[float]] = {spp: [] for spp in spps}
    for index in range(scenes):
        spec = sample_scene(seed, "train", index, frames=1)
        with SceneRenderer(spec, size, reference_spp) as renderer:
            reference = linear_to_srgb(np.clip(renderer.render(0, 0, seed=12345), 0, 1))
        for spp in spps:
            with SceneRenderer(spec, size, spp) as renderer:
                image = linear_to_srgb(np.clip(renderer.render(0, 0, seed=index), 0, 1))
            mse = float(np.mean((image - reference) ** 2))
            scores[spp].append(10 * np.log10(1.0 / max(mse, 1e-12)))
    return {spp: float(np.mean(v)) for spp, v in scores.items()}


def main() -> None:
    """Print render cost at --size/--spp and PSNR against a reference at --noise-size."""
    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--noise-size", type=int, default=64, help="0 skips the noise measurement")
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="cuda: Mitsuba's cuda_ad_rgb (read the wall seconds)")
    args = parser.parse_args()
    try:
        device = render_device(args.device)
    except InputError as error:  # --device cuda where Mitsuba cannot render on a GPU
        parser.error(str(error))
    variant = init_mitsuba(threads=1, device=device)
    cost, wall = seconds_per_frame(args.size, args.spp, args.scenes)
    noise = {}
    if args.noise_size:
        noise = psnr_against_reference(args.noise_size, [16, 36, 64, 144], args.reference_spp, args.scenes)
    print(json.dumps({"variant": variant, "size": args.size, "spp": args.spp,
                      "cpu_seconds_per_frame": round(cost, 3), "wall_seconds_per_frame": round(wall, 3),
                      "frames_per_second_2_workers": round(2 / cost, 3),
                      "psnr_db_vs_reference": {str(k): round(v, 2) for k, v in noise.items()},
                      "noise_size": args.noise_size, "reference_spp": args.reference_spp}, indent=1))


if __name__ == "__main__":
    main()
