"""HDR files: the one reader of OpenEXR and Radiance (.hdr) images, and the OpenEXR writer.

Light probes (`lighting.load_probe`), EXR/HDR pictures (`media.load_image`) and the dataset's probe
frames (`data.files`) are all read here; each caller keeps its own size limits and cleaning.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import
# OpenCV prints its own "[ERROR:0@0.4] global loadsave.cpp ..." lines for damaged files; our
# errors already say what went wrong in one sentence. OPENCV_LOG_LEVEL set by the user still wins.
_OPENCV_QUIET = "OPENCV_LOG_LEVEL" not in os.environ

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402

from relight_core.errors import InputError  # noqa: E402
from relight_core.media.base import EXR_MAGIC, RADIANCE_MAGIC, atomic, name  # noqa: E402
from relight_core.stderr import quiet_about  # noqa: E402

if _OPENCV_QUIET:
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

_RADIANCE_SIZE = re.compile(rb"[-+]([XY])\s+(\d+)\s+[-+]([XY])\s+(\d+)")


def read_hdr(path, subject: str | None = None, check_size: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Linear float32 [H, W, 3] of an OpenEXR or Radiance file (judged by its bytes), uncleaned.

    `check_size(width, height)` sees the header's size before any pixel is decoded (it raises to
    refuse); `subject` starts each error sentence (default: the file's name).
    """
    path = os.fspath(path)
    subject = subject or name(path)
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:4] == EXR_MAGIC:
        with quiet_about(path):  # OpenEXR prints its own line about a damaged file; ours says it
            pixels = _read_exr(path, subject, check_size)
    elif head.startswith(RADIANCE_MAGIC):
        pixels = _read_radiance(path, head, subject, check_size)
    else:
        raise InputError(f"{subject} is not an OpenEXR or Radiance HDR file; use .exr or .hdr.")
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return np.repeat(pixels, 3, axis=-1) if pixels.shape[-1] == 1 else np.ascontiguousarray(pixels[..., :3])


def _read_exr(path: str, subject: str, check_size) -> np.ndarray:
    try:
        with OpenEXR.File(path, header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
        if check_size is not None:
            check_size(int(x1 - x0 + 1), int(y1 - y0 + 1))
        # One plane per channel: R, G and B may differ in pixel type (half, float), which the grouped
        # "RGB" view refuses. Pixel arrays are only valid inside the block.
        with OpenEXR.File(path, separate_channels=True) as f:
            channels = f.channels()
            names = "RGB" if all(c in channels for c in "RGB") else "Y" if "Y" in channels else None
            if names is None:
                raise InputError(f"{subject} has no RGB or Y channels (found {', '.join(sorted(channels))}); "
                                 "export it as a plain RGB OpenEXR.")
            return np.stack([np.asarray(channels[c].pixels, np.float32) for c in names], axis=-1)
    except InputError:
        raise
    except Exception as error:  # OpenEXR raises RuntimeError/ValueError/... on damaged files
        raise InputError(f"{subject} could not be read as OpenEXR ({error}); re-export or re-download it.") from error


def _read_radiance(path: str, head: bytes, subject: str, check_size) -> np.ndarray:
    match = _RADIANCE_SIZE.search(head)
    if match is None:
        raise InputError(f"{subject} has no Radiance resolution line; re-export it as .hdr or .exr.")
    sides = {match.group(1): int(match.group(2)), match.group(3): int(match.group(4))}
    if check_size is not None:
        check_size(sides[b"X"], sides[b"Y"])
    bgr = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.ndim != 3:
        raise InputError(f"{subject} could not be decoded as Radiance HDR; re-export or re-download it.")
    return bgr[..., 2::-1].astype(np.float32)  # OpenCV gives BGR


def save_exr(path, linear: np.ndarray, half: bool = False) -> None:
    """Write a linear [H, W, 3] image as OpenEXR (float32, or half when `half`), ZIP-compressed."""
    data = np.ascontiguousarray(linear, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic(path) as tmp:
        OpenEXR.File(header, {"RGB": data}).write(tmp)
