"""Image files of the dataset format: 8-bit PNG frames and half-float EXR probes (through the one
HDR file reader and writer, `relight_core.media.hdr`)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from relight_core.media.hdr import read_hdr, save_exr


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
    save_exr(path, np.clip(linear, 0.0, 65504.0), half=True)


def read_exr(path: str | Path) -> np.ndarray:
    """Read an RGB EXR as float32 [H,W,3] (no cleaning, no size limit: dataset files are ours)."""
    return read_hdr(path)


def _atomic_write(path: Path, payload: bytes) -> None:
    """Write to a temporary name then rename, so an interrupted run leaves no half file."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(payload)
    os.replace(tmp, path)
