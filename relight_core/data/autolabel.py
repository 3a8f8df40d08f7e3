"""`autolabel`: run the model's albedo mode on real single-illumination videos → (video, albedo) samples.

The samples use the synthetic dataset's format with one illumination and no probe
(`kind = "autolabel"`, `lights = 1`), so `RelightDataset` serves them as the paper's real-data
examples: albedo as condition, the video as the relit target, input and lighting zeroed.

Each file of the folder is one unit of work for the engine the batch command uses
(relight_core/batch/engine.py, samples.py): Ray actors that each load the model once (a GPU each
when the cluster has GPUs, else a CPU budget) label videos one at a time, on a local Ray instance
or the cluster at `address`; `workers == 1` without an address labels in this process instead. A
file that cannot be read or labelled fails alone with its sentence; finished samples are skipped.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

from relight_core.batch.engine import (DONE, FAILED, ModelWorker, UnitResult, engine, locked, sentence,
                                      stop_if_interrupted, worker_plan)
from relight_core.batch.samples import DataSummary, Sample, run_samples
from relight_core.data.dataset import is_finished, write_frame, write_meta
from relight_core.errors import InputError


def sample_name(path: Path) -> str:
    """Folder name of a source file's sample: its stem made filesystem-safe."""
    return "real_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", path.stem)


@dataclass(frozen=True)
class LabelSettings:
    """How each video is labelled (the same for every worker)."""

    size: int | None = None        # working resolution; None: the model's
    max_frames: int | None = None  # cut each video to this many frames
    steps: int | None = None       # sampling steps; None: the model's
    seed: int = 0


class LabelWorker(ModelWorker):
    """A Ray actor (or the in-process worker): one model, loaded once, labelling files one at a time."""

    def __init__(self, model: str, device: str | None, precision: str | None, threads: int | None,
                 settings: LabelSettings):
        super().__init__(model, device, precision, threads)
        self.settings = settings

    def run(self, source: str, sample_dir: str) -> UnitResult:
        """Label one video or image into `sample_dir`; every failure is this file's result, with one sentence."""
        self.check()
        path, started = Path(source), time.perf_counter()
        try:
            label(self.relighter, path, Path(sample_dir), self.settings)
            return UnitResult(path.name, DONE, time.perf_counter() - started)
        except Exception as exc:  # an unreadable file, a full disk, a bug: this file's result
            stop_if_interrupted(exc)
            return UnitResult(path.name, FAILED, time.perf_counter() - started, sentence(exc, "video"))


def label(relighter, path: Path, sample_dir: Path, settings: LabelSettings) -> None:
    """Write one (video, albedo) sample: the resized frames as `rgb0/`, the model's albedo as `albedo/`,
    meta.json last."""
    from relight_core import media
    from relight_core.pipeline import RelightRequest

    source = media.load_media(path, max_frames=settings.max_frames)
    frames = media.resize_frames(source.frames, settings.size or relighter.spec.size,
                                 multiple=relighter.frame_multiple)
    result = relighter.relight(RelightRequest(frames, fps=source.fps, mode="albedo", steps=settings.steps,
                                              seed=settings.seed))
    for t in range(len(frames)):
        write_frame(sample_dir, "rgb0", t, frames[t])
        write_frame(sample_dir, "albedo", t, result.albedo[t])
    T, H, W, _ = frames.shape
    write_meta(sample_dir, {"kind": "autolabel", "frames": T, "height": H, "width": W, "lights": 1,
                            "source": path.name, "fps": source.fps, "model": relighter.spec.name,
                            "steps": settings.steps, "seed": settings.seed})


def autolabel(videos_dir: Path, out: Path, split: str = "real", model: str = "default", size: int | None = None,
              max_frames: int | None = None, steps: int | None = None, device: str | None = None,
              seed: int = 0, *, address: str | None = None, workers: int | None = None,
              cpus_per_worker: int = 1, gpus_per_worker: float = 1.0, precision: str | None = None,
              progress: bool = True) -> DataSummary:
    """Label every file in `videos_dir` (finished ones are skipped) on `workers` workers (None: as many
    as the Ray instance or cluster has room for); `summary.manifest` is the split's manifest path."""
    from relight_core.checkpoint import resolve_model

    files = sorted(p.resolve() for p in Path(videos_dir).iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise InputError(f"{videos_dir} holds no files; put the videos to label in it.")
    spec, weights = resolve_model(model)  # an unknown model is one sentence before Ray starts
    if weights is not None and str(model) != "default":  # a model folder, named the same in every worker
        model = str(weights.resolve())
    split_dir = Path(out).expanduser().resolve() / split
    split_dir.mkdir(parents=True, exist_ok=True)
    settings = LabelSettings(size, max_frames, steps, seed)
    with locked(split_dir, ".autolabel.lock", "autolabel run", "--out or --split"):
        todo, first_of = [], {}
        for path in files:
            folder = split_dir / sample_name(path)
            if folder.name in first_of:  # clip.mp4 and clip.png would write one sample
                todo.append(Sample(folder, path.name, (), f"{path.name} would be labelled as {folder.name}, like "
                                   f"{first_of[folder.name]}; rename one of them."))
                continue
            first_of[folder.name] = path.name
            if not is_finished(folder):
                todo.append(Sample(folder, path.name, (str(path), str(folder))))
        notes = [] if spec.trained else [f"note: model '{spec.name}' has random weights; labels will be noise."]
        desc = f"autolabel {split}"
        runnable = sum(not s.error for s in todo)
        if not runnable:  # nothing to label: no Ray, no model
            return run_samples(split_dir, len(files), todo, None, 1, None, None, "video", desc, progress)
        with engine(address, workers) as ray:
            if ray is None:
                count = 1
                start = lambda: LabelWorker(model, device, precision, None, settings)  # noqa: E731
                call = lambda worker, sample: worker.run(*sample.args)  # noqa: E731
            else:
                plan = worker_plan(ray, runnable, workers, device, cpus_per_worker, gpus_per_worker)
                actor = ray.remote(LabelWorker).options(**plan.demand)
                count = plan.count
                start = lambda: actor.remote(model, plan.device, precision, plan.threads, settings)  # noqa: E731
                call = lambda worker, sample: worker.run.remote(*sample.args)  # noqa: E731
            return run_samples(split_dir, len(files), todo, ray, count, start, call, "video", desc, progress, notes)
