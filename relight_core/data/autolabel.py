"""`autolabel`: run the model's albedo mode on real single-illumination videos → (video, albedo) samples.

The samples use the synthetic dataset's format with one illumination and no probe
(`kind = "autolabel"`, `lights = 1`), so `RelightDataset` serves them as the paper's real-data
examples: albedo as condition, the video as the relit target, input and lighting zeroed.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

from relight_core.data.dataset import is_finished, write_frame, write_manifest, write_meta
from relight_core.errors import InputError


def sample_name(path: Path) -> str:
    """Folder name of a source file's sample: its stem made filesystem-safe."""
    return "real_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", path.stem)


def autolabel(videos_dir: Path, out: Path, split: str = "real", model: str = "default", size: int | None = None,
              max_frames: int | None = None, steps: int | None = None, device: str | None = None,
              seed: int = 0) -> Path:
    """Label every video/image in `videos_dir` (finished ones are skipped); returns the manifest path."""
    from tqdm import tqdm

    from relight_core import media
    from relight_core.pipeline import Relighter, RelightRequest

    files = sorted(p for p in Path(videos_dir).iterdir() if p.is_file() and not p.name.startswith("."))
    if not files:
        raise InputError(f"{videos_dir} holds no files; put the videos to label in it.")
    split_dir = Path(out) / split
    split_dir.mkdir(parents=True, exist_ok=True)
    relighter = Relighter.load(model, device=device)
    for path in tqdm(files, unit="video", desc="autolabel"):
        sample_dir = split_dir / sample_name(path)
        if is_finished(sample_dir):
            continue
        try:
            source = media.load_media(path, max_frames=max_frames)
        except InputError as err:  # one unreadable file must not stop a batch of thousands
            warnings.warn(f"skipping {path}: {err}", RuntimeWarning, stacklevel=2)
            continue
        frames = media.resize_frames(source.frames, size or relighter.spec.size, multiple=relighter.frame_multiple)
        result = relighter.relight(RelightRequest(frames, fps=source.fps, mode="albedo", steps=steps, seed=seed))
        for t in range(len(frames)):
            write_frame(sample_dir, "rgb0", t, frames[t])
            write_frame(sample_dir, "albedo", t, result.albedo[t])
        T, H, W, _ = frames.shape
        write_meta(sample_dir, {"kind": "autolabel", "frames": T, "height": H, "width": W, "lights": 1,
                                "source": path.name, "fps": source.fps, "model": relighter.spec.name,
                                "steps": steps, "seed": seed})
    return write_manifest(split_dir)
