"""What the media readers and writers share: the `Media` record, path and size checks, detection of
a file's kind by its bytes, and atomic writes."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import av
import numpy as np
from PIL import Image, UnidentifiedImageError

from relight_core.errors import InputError
from relight_core.paths import check_path, name  # noqa: F401 (re-exported)

MAX_SIDE = 8192  # pixels per side, checked from headers before decoding

EXR_MAGIC = b"\x76\x2f\x31\x01"
RADIANCE_MAGIC = b"#?"
_STILL_DEMUXERS = {"image2", "tty", "gif", "apng"}


@dataclass(frozen=True)
class Media:
    """Decoded frames plus what is needed to write a result back with the same timing and sound."""

    frames: np.ndarray  # [T, H, W, 3] float32 in [0, 1]
    fps: float | None  # None for images
    is_video: bool
    audio_path: str | None = None  # source file to copy the audio stream from
    audio_start: float = 0.0  # seconds into audio_path where frames[0] is shown


def check_side(path: str, width: int, height: int) -> None:
    """InputError unless both sides are within 1…MAX_SIDE pixels."""
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise InputError(
            f"{name(path)} is {width}×{height} pixels; use media at most {MAX_SIDE} pixels on a side."
        )


def is_hdr(path: str) -> bool:
    """Whether the file starts like an OpenEXR or a Radiance HDR file."""
    with open(path, "rb") as f:
        magic = f.read(4)
    return magic == EXR_MAGIC or magic.startswith(RADIANCE_MAGIC)


def kind(path: str) -> str:
    """'linear' (EXR/HDR), 'image' or 'video' (animated GIF, APNG and WebP too), judged from the file's bytes."""
    if is_hdr(path):
        return "linear"
    from relight_core.media.animation import animated  # it imports this module

    try:
        with Image.open(path) as image:
            return "video" if animated(image) else "image"  # an animated GIF, APNG or WebP is a clip
    except Image.DecompressionBombError:
        return "image"  # refused with a clear message by the image reader
    except (UnidentifiedImageError, OSError):
        pass
    try:
        with av.open(path) as container:
            # FFmpeg's still-image and text demuxers pick files by extension; Pillow has already
            # refused this one, so a "video" they report is a damaged or mislabelled file.
            demuxer = container.format.name
            if container.streams.video and demuxer not in _STILL_DEMUXERS and not demuxer.endswith("_pipe"):
                return "video"
            if not container.streams.video:
                raise InputError(f"{name(path)} contains no video stream; pick an image or a video with picture.")
    except av.FFmpegError:
        pass
    raise InputError(
        f"{name(path)} is not a supported image or video; use PNG, JPEG, WebP, GIF, EXR, HDR, MP4, MOV or WebM."
    )


@contextmanager
def atomic(path) -> Iterator[str]:
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds."""
    path = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".partial", dir=folder)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # a normal file (0644), not mkstemp's private 0600
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _umask() -> int:
    """The process umask, read without changing it (Linux); 0o022 where it cannot be read."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022
