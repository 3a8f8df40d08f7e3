"""Latents of a dataset split under a frozen tokenizer, encoded once and cached on disk.

On a 2-core CPU re-encoding nine streams per scene every epoch would cost more than the DiT
step, so each scene is encoded once into `<cache>/<tokenizer hash>/<split>/<scene>.safetensors`
(fp16) and the whole split is then held in memory. Per scene and per stream (`rgb0`, `rgb1`,
`albedo`, `env{light}_{ldr,log,dir}`) the cache holds the full clip ("video", [16,t,h,w]) and a
few frames encoded alone as images ("image", [n,16,1,h,w]) for image–video co-training.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.data.dataset import RelightDataset
from relight_core.dit import LIGHTING_KEYS, pack_lighting
from relight_core.precision import autocast as precision_autocast
from relight_core.precision import resolve_precision

IMAGE_FRAMES = 3   # frames per clip also encoded as single images (first, middle, last)


def tokenizer_fingerprint(tokenizer: torch.nn.Module) -> str:
    """A short hash of the tokenizer's weights: a retrained tokenizer never reuses stale latents."""
    digest = hashlib.sha1()
    for name, value in sorted(tokenizer.state_dict().items()):
        digest.update(name.encode())
        digest.update(value.detach().float().cpu().numpy().tobytes())
    return digest.hexdigest()[:12]


def image_frame_indices(num_frames: int) -> list[int]:
    """Which frames of a clip are also encoded as images: evenly spaced, first and last included."""
    count = min(IMAGE_FRAMES, num_frames)
    return sorted({round(i * (num_frames - 1) / max(count - 1, 1)) for i in range(count)})


@torch.no_grad()
def encode_streams(tokenizer, streams: dict[str, torch.Tensor], autocast: bool = True,
                   dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
    """{name: [3,T,H,W] in [-1,1]} → {name/video: [16,t,h,w], name/image: [n,16,1,h,w]} (fp16).

    Encoded in `dtype` (default: this CPU's `auto` precision, precision.py); fp32 when `autocast` is off."""
    dtype = (dtype or resolve_precision("auto", "cpu")) if autocast else torch.float32
    names = list(streams)
    videos = torch.stack([streams[n] for n in names])                               # (S, 3, T, H, W)
    frames = image_frame_indices(videos.shape[2])
    images = videos[:, :, frames].permute(0, 2, 1, 3, 4).flatten(0, 1)[:, :, None]  # (S·n, 3, 1, H, W)
    with precision_autocast(dtype):
        z_video = tokenizer.encode(videos).float()                                   # (S, 16, t, h, w)
        z_image = tokenizer.encode(images).float()                                   # (S·n, 16, 1, h, w)
    z_image = z_image.unflatten(0, (len(names), len(frames)))                        # (S, n, 16, 1, h, w)
    out = {}
    for i, name in enumerate(names):
        out[f"{name}/video"] = z_video[i].half().contiguous()
        out[f"{name}/image"] = z_image[i].half().contiguous()
    return out


@dataclass(frozen=True)
class LatentItem:
    """One training example: which cached scene, which illumination is input and which target."""

    scene: int
    input_light: int | None
    target_light: int
    has_lighting: bool


class LatentSet:
    """A dataset split's cached latents in memory, and the batches drawn from them."""

    def __init__(self, scenes: list[dict[str, torch.Tensor]], items: list[LatentItem]):
        self.scenes = scenes
        self.items = items

    def __len__(self) -> int:
        return len(self.items)

    def batch(self, indices: list[int], image_frames: list[int] | None = None) -> dict[str, torch.Tensor]:
        """Latents of items: input, relit, albedo [B,16,t,h,w], lighting [B,51,t,h,w], has_* [B] bool.

        `image_frames` (one per item, an index into the cached image frames) selects 1-frame
        image latents instead of the full clips.
        """
        out = {k: [] for k in ("input", "relit", "albedo", "lighting", "has_input", "has_lighting")}
        for j, index in enumerate(indices):
            item = self.items[index]
            scene = self.scenes[item.scene]

            def get(name: str) -> torch.Tensor:
                if image_frames is None:
                    return scene[f"{name}/video"].float()                              # (16, t, h, w)
                return scene[f"{name}/image"][image_frames[j]].float()                 # (16, 1, h, w)

            relit = get(f"rgb{item.target_light}")
            out["relit"].append(relit)
            out["albedo"].append(get("albedo"))
            has_input = item.input_light is not None
            out["input"].append(get(f"rgb{item.input_light}") if has_input else torch.zeros_like(relit))
            if item.has_lighting:
                env = [get(f"env{item.target_light}_{key.removeprefix('env_')}")[None] for key in LIGHTING_KEYS]
                out["lighting"].append(pack_lighting(*env)[0])                        # (51, t, h, w)
            else:
                out["lighting"].append(relit.new_zeros(3 * (relit.shape[0] + 1), *relit.shape[1:]))
            out["has_input"].append(has_input)
            out["has_lighting"].append(item.has_lighting)
        batch = {k: torch.stack(v) for k, v in out.items() if k not in ("has_input", "has_lighting")}
        batch["has_input"] = torch.tensor(out["has_input"])
        batch["has_lighting"] = torch.tensor(out["has_lighting"])
        return batch

    @property
    def num_image_frames(self) -> int:
        return self.scenes[0]["albedo/image"].shape[0]


def build_latent_set(dataset: RelightDataset, tokenizer, cache_dir: Path, progress: bool = True,
                     dtype: torch.dtype | None = None, shard: tuple[int, int] = (0, 1)) -> LatentSet:
    """Encode (or load from `cache_dir`) every scene of `dataset` and index its items (in `dtype`).

    `shard=(rank, world)` takes only the scenes k with k % world == rank: the share of the cache
    that one rank of a data-parallel run fills (training.distributed).
    """
    rank, world = shard
    cache = Path(cache_dir) / tokenizer_fingerprint(tokenizer) / dataset.split_dir.name
    cache.mkdir(parents=True, exist_ok=True)
    by_scene: dict[Path, list[int]] = {}
    for index, item in enumerate(dataset.items):
        by_scene.setdefault(item.sample_dir, []).append(index)
    scenes, items = [], []
    for number, (sample_dir, indices) in enumerate(by_scene.items()):
        if number % world != rank:
            continue
        path = cache / f"{sample_dir.name}.safetensors"
        samples = [dataset.items[i] for i in indices]
        if path.is_file():
            scene = load_file(str(path))
            has_lighting = {int(k): bool(v) for k, v in zip(scene.pop("_lights"), scene.pop("_has_lighting"))}
        else:
            streams, has_lighting = {}, {}
            for index, item in zip(indices, samples):
                sample = dataset[index]
                if sample["path"] != str(sample_dir):      # the dataset skipped a broken sample
                    break
                streams[f"rgb{item.target_light}"] = sample["relit"]
                streams["albedo"] = sample["albedo"]
                if item.input_light is not None:
                    streams[f"rgb{item.input_light}"] = sample["input"]
                has_lighting[item.target_light] = bool(sample["has_lighting"])
                if has_lighting[item.target_light]:
                    for key in LIGHTING_KEYS:
                        streams[f"env{item.target_light}_{key.removeprefix('env_')}"] = sample[key]
            else:
                scene = encode_streams(tokenizer, streams, dtype=dtype)
                lights = sorted(has_lighting)
                save_file({**scene, "_lights": torch.tensor(lights),
                           "_has_lighting": torch.tensor([has_lighting[k] for k in lights])}, str(path))
            if not has_lighting or len(has_lighting) < len(samples):
                continue
        if progress and (number + 1) % 25 == 0:
            print(f"latents: {number + 1}/{len(by_scene)} scenes of {dataset.split_dir}", flush=True)
        for item in samples:
            items.append(LatentItem(len(scenes), item.input_light, item.target_light, has_lighting[item.target_light]))
        scenes.append(scene)
    return LatentSet(scenes, items)
