"""Image files of the dataset format: 8-bit PNG frames and half-float EXR probes."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import OpenEXR


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear → sRGB transfer (IEC 61966-2-1), input clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB → linear transfer, the inverse of `srgb_encode` on [0, 1]."""
    x = np.clip(encoded, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write [H,W,3] or [H,W] values in [0, 1] as an 8-bit PNG, atomically."""
    data = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    if data.ndim == 3:
        data = data[..., ::-1]  # OpenCV stores BGR
    ok, buf = cv2.imencode(".png", data)
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    _atomic_write(Path(path), buf.tobytes())


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8-bit PNG or JPEG as float32 in [0, 1]: [H,W,3] for colour, [H,W] for grey."""
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise OSError(f"cannot read image {path}")
    if data.ndim == 3:
        data = data[..., 2::-1]  # BGR(A) → RGB
    return data.astype(np.float32) / 255.0


def write_exr(path: str | Path, linear: np.ndarray) -> None:
    """Write linear [H,W,3] radiance as a half-float, ZIP-compressed EXR, atomically."""
    data = np.ascontiguousarray(np.clip(linear, 0.0, 65504.0).astype(np.float16))
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.exr")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": data}).write(str(tmp))
    os.replace(tmp, path)


def read_exr(path: str | Path) -> np.ndarray:
    """Read an RGB EXR as float32 [H,W,3] (no cleaning: dataset files are ours)."""
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGB" in channels:
            pixels = channels["RGB"].pixels
        else:
            pixels = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
        return np.asarray(pixels, dtype=np.float32)


def _atomic_write(path: Path, payload: bytes) -> None:
    """Write to a temporary name then rename, so an interrupted run leaves no half file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(payload)
    os.replace(tmp, path)
