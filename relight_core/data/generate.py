"""`render-data`: render a split of synthetic scenes to disk — deterministic, resumable, parallel on Ray.

Each scene is one Ray task declaring one CPU (Mitsuba's llvm_ad_rgb variant on one Dr.Jit thread), on a
local Ray instance of `workers` CPUs, or on the cluster at `address`; `workers == 1` without an address
renders in this process instead (no Ray start-up for a small job). With `device` "cuda" (or "auto" where a
GPU renders) the scenes render with Mitsuba's cuda_ad_rgb variant, each task declaring `gpus_per_worker`
of a GPU. Either way the units go through the engine the batch command uses (relight_core/batch/engine.py,
samples.py): progress, failure isolation, resume; `minutes` stops starting new scenes once that much
time has passed (the next run renders the rest).

Same seed, same scenes. On the CPU the files are the same bytes on every run; a GPU accumulates the film in
whatever order its threads finish, so its images agree with the CPU's to within the render noise, not bit
for bit, and each scene's meta.json names the variant it was rendered with.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from relight_core.batch.engine import (DONE, FAILED, UnitResult, engine, locked, sentence, stop_if_interrupted,
                                      worker_plan)
from relight_core.batch.samples import DataSummary, Sample, run_samples
from relight_core.colour import linear_to_srgb
from relight_core.data.dataset import is_finished, write_frame, write_meta
from relight_core.data.probes import PROBE_LIBRARIES
from relight_core.data.render import (CPU_VARIANT, RENDER_DEVICES, SceneRenderer, init_mitsuba, render_device,
                                     stratified_spp)
from relight_core.data.scenes import SPLITS, SceneSpec, camera_to_world, probe_yaw, sample_scene
from relight_core.errors import InputError


@dataclass(frozen=True)
class RenderConfig:
    """What to render: `scenes` scenes of `frames` frames at `size`², `spp` samples per pixel; where:
    `workers` scenes at once (None: one per CPU of this machine, or of the cluster at `address`)."""

    out: Path
    scenes: int = 100
    frames: int = 9
    size: int = 128
    spp: int = 64
    seed: int = 0
    workers: int | None = None
    split: str = "train"
    address: str | None = None  # a running Ray cluster; None: a local instance (or this process, workers 1)
    device: str = "cpu"         # cpu (llvm_ad_rgb: the same bytes every run), cuda (cuda_ad_rgb) or auto
    gpus_per_worker: float = 0.25  # with cuda: each scene task's share of a GPU (4 scenes at once on one)
    minutes: float | None = None   # start no scene after this many minutes (None: render them all)
    probes: str = "classic"        # probe library (probes.PROBE_LIBRARIES); "extended": more HDRIs for train


def scene_dir(config: RenderConfig, index: int) -> Path:
    """Folder of scene `index` of the configured split."""
    return config.out / config.split / f"scene_{index:06d}"


def frame_seed(spec: SceneSpec, frame: int) -> int:
    """Mitsuba's sampler seed of a frame (both lights use it: their noise is correlated, not different)."""
    return int(np.random.SeedSequence([spec.seed, SPLITS.index(spec.split), spec.index, frame])
               .generate_state(1)[0] & 0x7FFFFFFF)


def render_scene(spec: SceneSpec, size: int, spp: int, out_dir: Path, variant: str = CPU_VARIANT,
                 library: str = "classic") -> None:
    """Render every frame of a scene under both probes and write it in the dataset format; a scene of a probe
    library other than "classic" names it in meta.json's "probe_library" (a classic scene's files are the same
    bytes as before libraries existed)."""
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
    extra = {} if library == "classic" else {"probe_library": library}
    write_meta(out_dir, {
        **extra, "kind": "synthetic", "frames": spec.frames, "height": size, "width": size, "lights": 2,
        "motion": list(spec.motion), "probes": [p.source for p in spec.probes],
        "render": {"renderer": "mitsuba3", "variant": variant, "spp": stratified_spp(spp), "max_depth": 3},
        "camera_to_world": [camera_to_world(spec, t).round(6).tolist() for t in range(spec.frames)],
        "probe_yaw": [[round(probe_yaw(spec, light, t), 6) for t in range(spec.frames)] for light in (0, 1)],
        "scene": asdict(spec),
    })


def render_unit(config: RenderConfig, index: int) -> UnitResult:
    """Render scene `index` into its folder (a Ray task, or a call in this process); a failure is the
    scene's result, with one sentence."""
    name = scene_dir(config, index).name
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        # once per process: the variant (config.device is settled by render_dataset); one CPU thread keeps the
        # bits reproducible
        try:
            variant = init_mitsuba(threads=1, device=config.device)
        except (ImportError, RuntimeError) as exc:  # a cluster node whose GPU Mitsuba cannot use
            raise InputError(f"Mitsuba could not select {config.device}'s variant on this worker "
                             f"({' '.join(str(exc).split())[:160]}); render with --device cpu.") from None
        spec = sample_scene(config.seed, config.split, index, config.frames, config.probes)
        render_scene(spec, config.size, config.spp, scene_dir(config, index), variant, config.probes)
        status, error = DONE, ""
    except Exception as exc:  # a full disk, a bug in one scene: this scene's result
        stop_if_interrupted(exc)  # but a SIGTERM inside Mitsuba's render stops the run
        status, error = FAILED, sentence(exc, "scene")
    return UnitResult(name, status, time.perf_counter() - wall, error, time.process_time() - cpu)


def scene_library(folder: Path) -> str:
    """The probe library a finished scene was drawn from (meta.json's "probe_library"; absent: classic)."""
    return json.loads((folder / "meta.json").read_text()).get("probe_library", "classic")


def check_library(config: RenderConfig, split_dir: Path) -> None:
    """One probe library a split folder: resuming a folder with another library would mix two datasets."""
    if config.probes not in PROBE_LIBRARIES:
        raise InputError(f"--probes {config.probes} is not one of {', '.join(PROBE_LIBRARIES)}.")
    finished = next((d for d in sorted(split_dir.glob("scene_*")) if is_finished(d)), None)
    held = scene_library(finished) if finished is not None else config.probes
    if held != config.probes:
        raise InputError(f"{split_dir} holds scenes of the {held} probe library and this run asks for "
                         f"{config.probes}; render it into another --out folder, or with --probes {held}.")


def render_dataset(config: RenderConfig, progress: bool = True) -> DataSummary:
    """Render the missing scenes of a split (finished ones are skipped) and rewrite its manifest;
    `summary.manifest` is the manifest's path, `summary.failures` the scenes that failed."""
    if config.minutes is not None and not config.minutes > 0:
        raise InputError(f"--minutes {config.minutes} is not a positive number of minutes.")
    if config.device not in RENDER_DEVICES:
        raise InputError(f"--device {config.device} is not one of {', '.join(RENDER_DEVICES)}.")
    deadline = None if config.minutes is None else time.monotonic() + 60 * config.minutes  # from the start
    # The device, settled once so that every scene renders on it: on this machine by rendering two pixels with
    # the CUDA variant (render_device); on a cluster by its GPUs ("cuda" without GPUs is refused by worker_plan).
    why_not: list[str] = []
    device = config.device if config.address else render_device(config.device, why_not)
    config = dataclasses.replace(config, out=Path(config.out).expanduser().resolve(),  # workers' paths
                                 workers=config.workers or (
                                     None if config.address or device != "cpu" else os.cpu_count() or 1))
    split_dir = config.out / config.split
    split_dir.mkdir(parents=True, exist_ok=True)
    with locked(split_dir, ".render-data.lock", "render-data run", "--out or --split"):
        check_library(config, split_dir)
        todo = [Sample(scene_dir(config, i), scene_dir(config, i).name, (i,))
                for i in range(config.scenes) if not is_finished(scene_dir(config, i))]
        desc = f"render-data {config.split}"
        if not todo:  # nothing to render: no Ray
            return run_samples(split_dir, config.scenes, [], None, 1, None, None, "scene", desc, progress)
        num_cpus = config.workers if device == "cpu" else None
        with engine(config.address, config.workers, num_cpus=num_cpus) as ray:
            if device == "auto":  # a cluster: its GPUs, if it has any
                device = "cuda" if ray.cluster_resources().get("GPU", 0) > 0 else "cpu"
            if config.device == "auto" and progress:
                print(f"render-data: --device auto renders on the "
                      f"{'GPU (cuda_ad_rgb)' if device == 'cuda' else 'CPU'}"
                      f"{f': no CUDA GPU Mitsuba can use here ({why_not[0]})' if why_not else ''}.", file=sys.stderr)
            config = dataclasses.replace(config, device=device)
            if ray is None:
                count, call = 1, lambda _, sample: render_unit(config, *sample.args)
            else:
                plan = worker_plan(ray, len(todo), config.workers, device=device, gpu_capable=device == "cuda",
                                   gpus_per_worker=config.gpus_per_worker)
                # No retries: a scene whose process dies fails alone, with its sentence.
                task = ray.remote(render_unit).options(**plan.demand, max_retries=0)
                count, call = plan.count, lambda _, sample: task.remote(config, *sample.args)
            summary = run_samples(split_dir, config.scenes, todo, ray, count, None, call, "scene", desc, progress,
                                  deadline=deadline)
    rendered = summary.ran - len(summary.failures)
    left = summary.total - summary.done - len(summary.failures)
    if deadline is not None and left:
        print(f"{config.minutes:g} minutes are up: {left} scene{'s' * (left != 1)} not started; the same command "
              "renders them.", file=sys.stderr)
    if rendered and progress:
        images = rendered * config.frames * 2  # one image per frame and light
        print(f"rendered {rendered} scenes = {images} images (frame × light) in {summary.seconds:.1f} s on "
              f"{count} worker{'s' * (count != 1)}: {images / summary.seconds:.2f} images/s, "
              f"{summary.cpu_seconds / images:.2f} CPU-s per image incl. albedo, mask and camera-frame probe",
              file=sys.stderr)
    return summary
