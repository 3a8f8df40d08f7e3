"""Loader for a local copy of the MIT multi-illumination dataset (Murmann et al., ICCV 2019).

Layout (as written by the dataset's SDK `multilum.py`; the user downloads it, we cannot):

    <root>/<scene>/dir_{i}_mip{m}.jpg             photo under flash direction i (0..24), sRGB
    <root>/<scene>/dir_{i}_mip{m}.exr             the same in linear HDR (optional)
    <root>/<scene>/probes/dir_{i}_chrome{s}.jpg   chrome-ball crop, s×s (256 in the release)
    <root>/<scene>/probes/dir_{i}_chrome{s}.exr   the same in linear HDR (optional, preferred)
    <root>/<scene>/materials_mip{m}.png           indexed material map (not used here)
    <root>/<scene>/meta.json                      {"chrome"|"gray": {"bounding_box": {x,y,w,h},
                                                   "boundary_points": [{x,y}, ...]}} in mip-0 pixels

Mip m halves the 6000×4000 originals m times (mip 2 = 1500×1000). Protocol of the UniRelight
paper: input = lighting i, target = lighting i + 12. The chrome ball becomes the target's
camera-frame lat-long probe through `lighting.mirror_ball_to_latlong`; `probe_mask` is 0 on the
chrome and grey balls, which the protocol excludes from every metric.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from relight_core import lighting
from relight_core.colour import srgb_to_linear
from relight_core.data.files import read_exr, read_image
from relight_core.errors import InputError

NUM_DIRECTIONS = 25
PROTOCOL_OFFSET = 12
FULL_SIZE = (4000, 6000)  # mip-0 height, width


def list_scenes(root: str | Path, mip: int = 2) -> list[Path]:
    """Scene folders under `root` that hold at least one photo at this mip level, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root} is not a folder; point it at your copy of the MIT multi-illumination data.")
    scenes = sorted(p for p in root.iterdir() if p.is_dir() and any(p.glob(f"dir_*_mip{mip}.*")))
    if not scenes:
        raise InputError(f"No scene folders with dir_<i>_mip{mip}.jpg under {root}; download the dataset "
                         "(https://projects.csail.mit.edu/illumination) or pick the right --mip.")
    return scenes


def directions(scene: Path, mip: int = 2) -> list[int]:
    """Lighting directions present for a scene, sorted."""
    found = {int(p.name.split("_")[1]) for p in scene.glob(f"dir_*_mip{mip}.*")}
    return sorted(found)


def protocol_pairs(available: list[int]) -> list[tuple[int, int]]:
    """(input, target) = (i, i + 12) for every i whose pair is present."""
    present = set(available)
    return [(i, i + PROTOCOL_OFFSET) for i in range(NUM_DIRECTIONS - PROTOCOL_OFFSET)
            if i in present and i + PROTOCOL_OFFSET in present]


def load_photo(scene: Path, direction: int, mip: int = 2) -> np.ndarray:
    """The sRGB photo under one direction, float32 [H,W,3] in [0, 1]."""
    return _read_rgb(scene / f"dir_{direction}_mip{mip}.jpg")


def load_meta(scene: Path) -> dict:
    """The scene's meta.json (probe regions), or {} when absent."""
    path = scene / "meta.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def load_chrome(scene: Path, direction: int, size: int = 256, mip: int = 2) -> np.ndarray:
    """Linear chrome-ball image [s,s,3]: the HDR crop, else the JPEG crop, else cut from the photo."""
    probe_dir = scene / "probes"
    exr = probe_dir / f"dir_{direction}_chrome{size}.exr"
    if exr.is_file():
        return read_exr(exr)
    jpg = probe_dir / f"dir_{direction}_chrome{size}.jpg"
    if jpg.is_file():
        return srgb_to_linear(_read_rgb(jpg)).astype(np.float32)
    box = load_meta(scene).get("chrome", {}).get("bounding_box")
    if box is None:
        raise InputError(f"{scene} has neither probes/dir_{direction}_chrome{size}.jpg nor a chrome bounding "
                         "box in meta.json; download the probes archive for this scene.")
    photo = srgb_to_linear(load_photo(scene, direction, mip))
    sy, sx = photo.shape[0] / FULL_SIZE[0], photo.shape[1] / FULL_SIZE[1]
    x, y, w, h = box["x"] * sx, box["y"] * sy, box["w"] * sx, box["h"] * sy
    crop = photo[int(round(y)):int(round(y + h)), int(round(x)):int(round(x + w))]
    return cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA).astype(np.float32)


def chrome_to_panorama(ball: np.ndarray, height: int, width: int) -> np.ndarray:
    """Chrome ball (seen by the camera) → the camera-frame panorama the model is given, [H,W,3].

    The ball shows light in the camera frame, so the recovered lat-long is already camera-frame
    (rotation 0, identity pose); `probe_in_camera` then re-grids it like every synthetic probe.
    """
    latlong = lighting.mirror_ball_to_latlong(torch.from_numpy(ball), height, 2 * height, rotation=0.0)
    return lighting.probe_in_camera(latlong, height, width, rotation=0.0).numpy()


def probe_mask(scene: Path, height: int, width: int) -> np.ndarray:
    """[H,W] float32: 1 on scene content, 0 on the chrome and grey balls (meta.json regions)."""
    region = np.zeros((height, width), np.uint8)
    sy, sx = height / FULL_SIZE[0], width / FULL_SIZE[1]
    for key in ("chrome", "gray"):
        entry = load_meta(scene).get(key) or {}
        points = entry.get("boundary_points") or []
        if len(points) >= 3:
            polygon = np.array([[p["x"] * sx, p["y"] * sy] for p in points], np.float32)
            cv2.fillPoly(region, [np.round(polygon).astype(np.int32)], 1)
        elif entry.get("bounding_box"):
            b = entry["bounding_box"]
            x0, y0 = int(np.floor(b["x"] * sx)), int(np.floor(b["y"] * sy))
            x1, y1 = int(np.ceil((b["x"] + b["w"]) * sx)), int(np.ceil((b["y"] + b["h"]) * sy))
            region[max(y0, 0):y1, max(x0, 0):x1] = 1
    return (1 - region).astype(np.float32)


class MITMultiIllumination(torch.utils.data.Dataset):
    """(input i, target i + 12) pairs as the same dict `RelightDataset` yields, with T = 1.

    Albedo is unknown (`has_albedo` false, zeros); `mask` is the probe mask; `size` resizes
    photos so the long side is `size` (both sides multiples of 16), keeping the aspect ratio.
    """

    def __init__(self, root: str | Path, mip: int = 2, size: int | None = None, probe_size: int = 256):
        self.mip, self.size, self.probe_size = mip, size, probe_size
        self.pairs = [(scene, i, j) for scene in list_scenes(root, mip)
                      for i, j in protocol_pairs(directions(scene, mip))]

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict:
        scene, i, j = self.pairs[index]
        source, target = load_photo(scene, i, self.mip), load_photo(scene, j, self.mip)
        if self.size is not None:
            source, target = _resize(source, self.size), _resize(target, self.size)
        h, w = target.shape[:2]
        env = chrome_to_panorama(load_chrome(scene, j, self.probe_size, self.mip), h, w)
        encoded = lighting.encode_lighting(torch.from_numpy(env)[None])

        def pixels(frame: np.ndarray) -> torch.Tensor:  # [H,W,3] in [0,1] → [3,1,H,W] in [−1,1]
            return torch.from_numpy(np.ascontiguousarray(frame, np.float32)).permute(2, 0, 1)[:, None] * 2 - 1

        return {
            "input": pixels(source), "relit": pixels(target), "albedo": torch.zeros(3, 1, h, w),
            **{k: v.permute(3, 0, 1, 2).contiguous() for k, v in encoded.items()},
            "mask": torch.from_numpy(probe_mask(scene, h, w))[None, None],
            "has_input": torch.tensor(True), "has_lighting": torch.tensor(True),
            "has_albedo": torch.tensor(False), "path": f"{scene}:dir_{i}->dir_{j}",
        }


def _read_rgb(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(f"{path} is missing; re-download that scene of the MIT multi-illumination data.")
    return read_image(path)


def _resize(frame: np.ndarray, size: int) -> np.ndarray:
    h, w = frame.shape[:2]
    scale = size / max(h, w)
    new_h, new_w = max(16, round(h * scale / 16) * 16), max(16, round(w * scale / 16) * 16)
    return cv2.resize(frame, (new_w, new_h), interpolation=cv2.INTER_AREA)
