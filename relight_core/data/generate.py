"""`render-data`: render a split of synthetic scenes to disk — deterministic, resumable, parallel."""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from relight_core.colour import linear_to_srgb
from relight_core.data.dataset import is_finished, write_frame, write_manifest, write_meta
from relight_core.data.render import SceneRenderer, init_mitsuba, stratified_spp
from relight_core.data.scenes import SPLITS, SceneSpec, camera_to_world, probe_yaw, sample_scene


@dataclass(frozen=True)
class RenderConfig:
    """What to render: `scenes` scenes of `frames` frames at `size`², `spp` samples per pixel."""

    out: Path
    scenes: int = 100
    frames: int = 9
    size: int = 128
    spp: int = 64
    seed: int = 0
    workers: int = 2
    split: str = "train"


def scene_dir(config: RenderConfig, index: int) -> Path:
    """Folder of scene `index` of the configured split."""
    return config.out / config.split / f"scene_{index:06d}"


def frame_seed(spec: SceneSpec, frame: int) -> int:
    """Mitsuba's sampler seed of a frame (both lights use it: their noise is correlated, not different)."""
    return int(np.random.SeedSequence([spec.seed, SPLITS.index(spec.split), spec.index, frame])
               .generate_state(1)[0] & 0x7FFFFFFF)


def render_scene(spec: SceneSpec, size: int, spp: int, out_dir: Path) -> None:
    """Render every frame of a scene under both probes and write it in the dataset format."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with SceneRenderer(spec, size, spp) as renderer:
        for t in range(spec.frames):
            seed = frame_seed(spec, t)
            for light in (0, 1):
                write_frame(out_dir, f"rgb{light}", t, linear_to_srgb(renderer.render(t, light, seed)))
                write_frame(out_dir, f"env{light}", t, renderer.camera_probe(t, light))
            albedo, mask = renderer.render_aovs(t, seed)  # shared by both lights: same geometry
            write_frame(out_dir, "albedo", t, linear_to_srgb(albedo))
            write_frame(out_dir, "mask", t, mask)
    write_meta(out_dir, {
        "kind": "synthetic", "frames": spec.frames, "height": size, "width": size, "lights": 2,
        "motion": list(spec.motion), "probes": [p.source for p in spec.probes],
        "render": {"renderer": "mitsuba3", "spp": stratified_spp(spp), "max_depth": 3},
        "camera_to_world": [camera_to_world(spec, t).round(6).tolist() for t in range(spec.frames)],
        "probe_yaw": [[round(probe_yaw(spec, light, t), 6) for t in range(spec.frames)] for light in (0, 1)],
        "scene": asdict(spec),
    })


def _worker_init() -> None:
    init_mitsuba(threads=1)


def _render_index(job: tuple[RenderConfig, int]) -> tuple[int, float]:
    config, index = job
    start = time.process_time()
    spec = sample_scene(config.seed, config.split, index, config.frames)
    render_scene(spec, config.size, config.spp, scene_dir(config, index))
    return index, time.process_time() - start


def render_dataset(config: RenderConfig, progress: bool = True) -> Path:
    """Render the missing scenes of a split (finished ones are skipped) and rewrite its manifest."""
    split_dir = config.out / config.split
    split_dir.mkdir(parents=True, exist_ok=True)
    todo = [i for i in range(config.scenes) if not is_finished(scene_dir(config, i))]
    bar = tqdm(total=config.scenes, initial=config.scenes - len(todo), unit="scene",
               disable=not progress, desc=f"render-data {config.split}")
    cpu_seconds = 0.0
    start = time.time()
    if config.workers <= 1:
        _worker_init()
        results = map(_render_index, [(config, i) for i in todo])
        for _, seconds in results:
            cpu_seconds += seconds
            bar.update(1)
    else:
        # Spawned (not forked) workers: each selects its Mitsuba variant exactly once.
        with multiprocessing.get_context("spawn").Pool(config.workers, initializer=_worker_init) as pool:
            for _, seconds in pool.imap_unordered(_render_index, [(config, i) for i in todo]):
                cpu_seconds += seconds
                bar.update(1)
    bar.close()
    if todo and progress:
        images = len(todo) * config.frames * 2  # one image per frame and light
        wall = time.time() - start
        print(f"rendered {len(todo)} scenes = {images} images (frame × light) in {wall:.1f} s: "
              f"{images / wall:.2f} images/s, {cpu_seconds / images:.2f} CPU-s per image "
              "incl. albedo, mask and camera-frame probe")
    return write_manifest(split_dir)
