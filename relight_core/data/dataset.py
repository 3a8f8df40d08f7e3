"""The on-disk dataset format (docs/DATA.md) and the torch `Dataset` that feeds training.

    <root>/<split>/manifest.json            every finished sample, one entry each
    <root>/<split>/<sample>/meta.json       written last: its presence marks a finished sample
    <root>/<split>/<sample>/rgb0/0000.png   frames under illumination 0 (sRGB, 8-bit)
                            rgb1/0000.png   frames under illumination 1 (synthetic only)
                            env0/0000.exr   probe 0 as seen from that frame's camera (half EXR,
                            env1/0000.exr   H×W panorama in the model's convention, linear)
                            albedo/0000.png albedo (sRGB-encoded base colour, 8-bit)
                            mask/0000.png   1 where a camera ray hits geometry, 0 on the probe
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from relight_core import lighting
from relight_core.data.files import read_exr, read_image, write_exr, write_png
from relight_core.errors import InputError

FORMAT = "relight-data/1"
MANIFEST = "manifest.json"
META = "meta.json"


# ---------------------------------------------------------------- writing

def frame_name(t: int) -> str:
    """File stem of frame t."""
    return f"{t:04d}"


def write_frame(sample_dir: Path, folder: str, t: int, image: np.ndarray) -> None:
    """Write frame t of one stream: PNG for [0,1] images and masks, EXR for `env*` probes."""
    (sample_dir / folder).mkdir(parents=True, exist_ok=True)
    if folder.startswith("env"):
        write_exr(sample_dir / folder / f"{frame_name(t)}.exr", image)
    else:
        write_png(sample_dir / folder / f"{frame_name(t)}.png", image)


def write_meta(sample_dir: Path, meta: dict) -> None:
    """Write meta.json atomically; call it last, after every frame of the sample is on disk."""
    tmp = sample_dir / f".{META}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"format": FORMAT, **meta}, indent=1, sort_keys=True))
    os.replace(tmp, sample_dir / META)


def is_finished(sample_dir: Path) -> bool:
    """Whether a sample folder holds a complete sample (its meta.json exists)."""
    return (sample_dir / META).is_file()


def write_manifest(split_dir: Path) -> Path:
    """Index every finished sample of a split folder into manifest.json (sorted, reproducible)."""
    samples = []
    for sample_dir in sorted(p for p in split_dir.iterdir() if p.is_dir() and is_finished(p)):
        meta = json.loads((sample_dir / META).read_text())
        samples.append({"path": sample_dir.name, "kind": meta["kind"], "frames": meta["frames"],
                        "height": meta["height"], "width": meta["width"], "lights": meta["lights"],
                        "motion": meta.get("motion", []), "probes": meta.get("probes", [])})
    path = split_dir / MANIFEST
    tmp = split_dir / f".{MANIFEST}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"format": FORMAT, "split": split_dir.name, "samples": samples},
                              indent=1, sort_keys=True))
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------- reading

@dataclass(frozen=True)
class Item:
    """One training example: a sample folder and which illumination is input and target."""

    sample_dir: Path
    input_light: int | None   # None: no input clip (auto-labelled single-illumination video)
    target_light: int


def read_stream(sample_dir: Path, folder: str, frames: list[int]) -> np.ndarray:
    """Frames of one stream as float32 [T,H,W,3] ([T,H,W] for the mask)."""
    ext = "exr" if folder.startswith("env") else "png"
    reader = read_exr if ext == "exr" else read_image
    return np.stack([reader(sample_dir / folder / f"{frame_name(t)}.{ext}") for t in frames])


class RelightDataset(torch.utils.data.Dataset):
    """Samples of `<root>/<split>` as model-ready tensors; bad samples are reported and skipped.

    Each item is a dict: `input`, `relit`, `albedo` [3,T,H,W] in [−1, 1]; `env_ldr`, `env_log`,
    `env_dir` [3,T,H,W] (lighting.encode_lighting of the target's camera-frame probe); `mask`
    [1,T,H,W] in {0, 1}; `has_input`, `has_lighting`, `has_albedo` (bool tensors; when false the
    matching tensors are zeros, as for auto-labelled videos); `path` (str). `clip_frames` cuts a window of
    that many frames (1 gives images for image–video co-training); the window start is drawn
    from (seed, epoch, index).
    """

    def __init__(self, root: str | Path, split: str = "train", clip_frames: int | None = None, seed: int = 0):
        self.split_dir = Path(root) / split
        manifest = self.split_dir / MANIFEST
        if not manifest.is_file():
            raise InputError(f"No dataset manifest at {manifest}; render one with "
                             f"`python -m relight_core render-data --out {root} --split {split}`.")
        try:
            entries = json.loads(manifest.read_text())["samples"]
        except (ValueError, KeyError) as err:
            raise InputError(f"The dataset manifest {manifest} is unreadable ({err}); delete it and "
                             "re-run render-data to rebuild it.") from None
        self.clip_frames, self.seed, self.epoch = clip_frames, seed, 0
        self.skipped: dict[str, str] = {}
        self.items: list[Item] = []
        for entry in entries:
            sample_dir = self.split_dir / entry["path"]
            if not is_finished(sample_dir):
                self._report(sample_dir, "listed in the manifest but its meta.json is missing")
                continue
            if entry["lights"] >= 2:
                self.items += [Item(sample_dir, 0, 1), Item(sample_dir, 1, 0)]
            else:
                self.items.append(Item(sample_dir, None, 0))

    def set_epoch(self, epoch: int) -> None:
        """Draw new clip windows (call once per epoch)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> dict:
        for offset in range(len(self.items)):
            item = self.items[(index + offset) % len(self.items)]
            if str(item.sample_dir) in self.skipped:
                continue
            try:
                return self._load(item, index)
            except (OSError, ValueError, KeyError) as err:
                self._report(item.sample_dir, str(err))
        raise RuntimeError(f"every sample under {self.split_dir} is unreadable; see the warnings above")

    def _report(self, sample_dir: Path, reason: str) -> None:
        self.skipped[str(sample_dir)] = reason
        warnings.warn(f"skipping dataset sample {sample_dir}: {reason}", RuntimeWarning, stacklevel=3)

    def _load(self, item: Item, index: int) -> dict:
        meta = json.loads((item.sample_dir / META).read_text())
        total = int(meta["frames"])
        length = min(self.clip_frames or total, total)
        start = 0
        if length < total:
            rng = np.random.default_rng([self.seed, self.epoch, index])
            start = int(rng.integers(0, total - length + 1))
        frames = list(range(start, start + length))
        relit = read_stream(item.sample_dir, f"rgb{item.target_light}", frames)  # [T,H,W,3]
        albedo = read_stream(item.sample_dir, "albedo", frames)
        shape = relit.shape
        if shape[1:] != (meta["height"], meta["width"], 3) or albedo.shape != shape:
            raise ValueError(f"frames of shape {relit.shape} / {albedo.shape} do not match meta.json")
        has_input = item.input_light is not None
        source = read_stream(item.sample_dir, f"rgb{item.input_light}", frames) if has_input else np.zeros(shape)
        mask_path = item.sample_dir / "mask"
        mask = read_stream(item.sample_dir, "mask", frames) if mask_path.is_dir() else np.ones(shape[:3])
        has_lighting = meta["kind"] == "synthetic"
        if has_lighting:
            env = read_stream(item.sample_dir, f"env{item.target_light}", frames)
            if env.shape != shape:
                raise ValueError(f"probe frames of shape {env.shape} do not match the frames {shape}")
            encoded = lighting.encode_lighting(torch.from_numpy(env))
        else:
            encoded = {k: torch.zeros(shape) for k in ("env_ldr", "env_log", "env_dir")}

        def pixels(frames_: np.ndarray) -> torch.Tensor:  # [T,H,W,3] in [0,1] → [3,T,H,W] in [−1,1]
            return torch.from_numpy(np.ascontiguousarray(frames_, dtype=np.float32)).permute(3, 0, 1, 2) * 2 - 1

        return {
            "input": pixels(source) if has_input else torch.zeros(3, *shape[:3]),
            "relit": pixels(relit),
            "albedo": pixels(albedo),
            **{k: v.permute(3, 0, 1, 2).contiguous() for k, v in encoded.items()},
            "mask": torch.from_numpy((mask > 0.5).astype(np.float32))[None],
            "has_input": torch.tensor(has_input),
            "has_lighting": torch.tensor(has_lighting),
            "has_albedo": torch.tensor(True),
            "path": str(item.sample_dir),
        }
