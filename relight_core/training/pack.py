"""Image packs: a dataset split's still frames in one small file, for training anywhere.

A pack holds, per scene, frame 0 under both illuminations and its albedo (JPEG quality 92, 4:4:4: ~38 dB; or with
`--lossless` PNG, the rendered pixels exactly, ~2.5× the size), the
foreground mask (bit-packed) and both camera-frame probes already seen through the model's
lighting grid (`lighting.downsample_panorama` to `lighting_size`², fp16). ~30 KB a 128² scene, so
a few thousand scenes travel to a GPU machine in one file, and `load_pack` rebuilds the tensors
the trainer needs without the data engine (no Mitsuba, no EXR reader).

    python -m relight_core.training.pack --data cache/data --split train --out cache/train.npz
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

STREAMS = ("rgb0", "rgb1", "albedo")
JPEG_QUALITY = 92


def _encode_frame(rgb: np.ndarray, lossless: bool = False) -> bytes:
    """uint8 [H,W,3] RGB → JPEG bytes (quality 92, no chroma subsampling), or PNG bytes with `lossless`
    (`_decode_frame` reads either). JPEG's error is not nothing to the model: the shipped one relit the first 80
    test items 0.155 dB worse from their JPEG than from their PNG inputs (runs/dit-top/jpeg-inputs-40.txt)."""
    if lossless:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    else:
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                  cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise RuntimeError("image encoding failed")
    return buf.tobytes()


def _uint8(image01: np.ndarray) -> np.ndarray:
    return np.round(np.clip(image01, 0, 1) * 255).astype(np.uint8)


def _decode_frame(data: np.ndarray) -> np.ndarray:
    image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("a pack holds a corrupt JPEG; rebuild the pack")
    return image[..., ::-1]


def write_pack(data: Path, split: str, out: Path, lighting_size: int = 32, limit: int | None = None,
               frame: int = 0, lossless: bool = False, names_prefix: str = "") -> int:
    """Pack frame `frame` of every finished synthetic scene of `data/split` (as PNG with `lossless`), each named
    `names_prefix` + its folder's name (a prefix keeps scenes of another split or seed apart from a training pack's
    alike-named ones: `training.refine` leaves out of training every scene its validation pack names); returns
    the scene count."""
    from relight_core import lighting
    from relight_core.data.dataset import write_manifest
    from relight_core.data.files import read_exr, read_image

    split_dir = Path(data) / split
    # Re-index first: a render still running has finished scenes its manifest does not list yet.
    manifest = json.loads(write_manifest(split_dir).read_text())
    samples = [s for s in manifest["samples"] if s.get("lights", 1) == 2][:limit]
    blobs, masks, envs, names = [], [], [], []
    for sample in samples:
        root = split_dir / sample["path"]
        name = f"{frame:04d}"
        for stream in STREAMS:
            blobs.append(_encode_frame(_uint8(read_image(root / stream / f"{name}.png")), lossless))
        mask = read_image(root / "mask" / f"{name}.png")
        masks.append(np.packbits(mask.reshape(mask.shape[0], mask.shape[1], -1)[..., 0].ravel() > 0.5))
        pans = torch.stack([torch.from_numpy(read_exr(root / f"env{light}" / f"{name}.exr")) for light in (0, 1)])
        envs.append(lighting.downsample_panorama(pans, lighting_size).numpy().astype(np.float16))
        names.append(names_prefix + sample["path"])
    height, width = read_image(split_dir / samples[0]["path"] / "rgb0" / f"{frame:04d}.png").shape[:2]
    out.parent.mkdir(parents=True, exist_ok=True)
    save_pack(out, blobs, np.stack(masks), np.stack(envs), (height, width), lighting_size, names)
    return len(samples)


def save_pack(out: Path, blobs: list, mask: np.ndarray, env: np.ndarray, size, lighting_size: int,
              names) -> None:
    """Write a pack: `blobs` the JPEGs of every scene's STREAMS in order (bytes or uint8 arrays), `mask`
    bit-packed [N, ⌈H·W/8⌉], `env` [N,2,s,s,3] fp16, `size` (H, W), `names` one per scene."""
    sizes = np.array([len(b) for b in blobs], np.int64)
    jpeg = np.concatenate([np.frombuffer(b, np.uint8) for b in blobs]) if blobs else np.zeros(0, np.uint8)
    np.savez_compressed(out, jpeg=jpeg, offsets=np.concatenate([[0], np.cumsum(sizes)]), mask=mask, env=env,
                        size=np.array(size), lighting_size=np.array(lighting_size), names=np.array(names))


def load_pack(path: Path, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
    """A pack as tensors: rgb [N,2,3,H,W] uint8, albedo [N,3,H,W] uint8, mask [N,H,W] bool,
    env [N,2,s,s,3] float32 (linear camera-frame probes on the lighting grid)."""
    with np.load(path, allow_pickle=False) as z:
        jpeg, offsets = z["jpeg"], z["offsets"]
        height, width = (int(v) for v in z["size"])
        images = np.stack([_decode_frame(jpeg[offsets[i]:offsets[i + 1]]) for i in range(len(offsets) - 1)])
        images = images.reshape(-1, len(STREAMS), height, width, 3)
        mask = np.unpackbits(z["mask"], axis=1)[:, :height * width].reshape(-1, height, width)
        out = {"env": torch.from_numpy(z["env"].astype(np.float32)), "names": list(z["names"]),
               "lighting_size": int(z["lighting_size"])}
    images = torch.from_numpy(images).permute(0, 1, 4, 2, 3)                # (N, 3 streams, 3, H, W)
    out.update(rgb=images[:, :2].contiguous(), albedo=images[:, 2].contiguous(), mask=torch.from_numpy(mask > 0))
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in out.items()}


class PackMismatch(ValueError):
    """Packs that cannot be trained together (different image size or lighting grid)."""


def load_packs(paths: Path | list[Path] | tuple[Path, ...], device: str | torch.device = "cpu") -> dict:
    """Several packs (e.g. scenes rendered with different dataset seeds) as one: their items in order.
    They must share image size and lighting grid."""
    paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    if not paths:
        raise ValueError("no pack given")
    packs = [load_pack(p, device) for p in paths]
    first = packs[0]
    for path, pack in zip(paths[1:], packs[1:]):
        if pack["rgb"].shape[-2:] != first["rgb"].shape[-2:] or pack["lighting_size"] != first["lighting_size"]:
            raise PackMismatch(f"{path} holds {tuple(pack['rgb'].shape[-2:])} px images on a {pack['lighting_size']}² "
                             f"lighting grid, {paths[0]} {tuple(first['rgb'].shape[-2:])} px on "
                             f"{first['lighting_size']}²; packs trained together must match: pack them alike")
    if len(packs) == 1:
        return first
    out = {k: torch.cat([p[k] for p in packs]) for k in ("rgb", "albedo", "mask", "env")}
    out.update(names=[n for p in packs for n in p["names"]], lighting_size=first["lighting_size"])
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--lighting-size", type=int, default=32)
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--lossless", action="store_true", help="PNG instead of JPEG 92: the rendered pixels exactly")
    parser.add_argument("--names-prefix", default="",
                        help="put before every scene's name (e.g. test-s2/ for a development pack of the test split)")
    args = parser.parse_args(argv)
    count = write_pack(args.data, args.split, args.out, args.lighting_size, args.limit, lossless=args.lossless,
                       names_prefix=args.names_prefix)
    print(f"packed {count} scenes into {args.out} ({args.out.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
