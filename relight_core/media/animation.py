"""Animated images — GIF, APNG and animated WebP — read as videos: Pillow composes each frame (the format's
disposal and transparency applied), its alpha goes over white as a still's does, and its delays give the clip's
frame rate. A single-frame file of these formats stays an image; a camera's multi-picture JPEG (MPO) or a
multi-page TIFF is read as its first picture, as before (only these three formats animate)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from PIL import Image

from relight_core.errors import InputError
from relight_core.media.base import check_side
from relight_core.media.image import pillow_error, pillow_rgb, to_uint8

ANIMATED_FORMATS = ("GIF", "PNG", "WEBP")
DEFAULT_DELAY_MS = 100.0  # what browsers show a frame whose delay is 0 or 10 ms for
DAMAGE = (Image.DecompressionBombError, OSError, ValueError, EOFError, SyntaxError)  # what Pillow raises


def animated(image: Image.Image) -> bool:
    """Whether an open Pillow image is an animation of more than one frame (GIF, APNG, WebP)."""
    try:
        return image.format in ANIMATED_FORMATS and getattr(image, "n_frames", 1) > 1
    except DAMAGE:  # frames past a damage: the first one is the image
        return False


@dataclass(frozen=True)
class Animation:
    num_frames: int
    fps: float
    width: int
    height: int


def _delay_ms(value) -> float:
    try:
        delay = float(value)
    except (TypeError, ValueError):
        return DEFAULT_DELAY_MS
    return delay if delay > 10 else DEFAULT_DELAY_MS


def probe_animation(path: str) -> Animation:
    """Frame count, frame rate (1000 / the median delay in ms) and size of an animated image."""
    try:
        with Image.open(path) as image:
            check_side(path, *image.size)
            count = image.n_frames
            delays = []
            for index in range(count):
                image.seek(index)
                if "duration" not in image.info:
                    image.load()  # WebP sets a frame's delay when it decodes the frame
                delays.append(_delay_ms(image.info.get("duration")))
            width, height = image.size
    except InputError:  # a ValueError too: the size check's own sentence
        raise
    except DAMAGE as error:
        raise pillow_error(path, error, "animation") from error
    return Animation(count, 1000.0 / float(np.median(delays)), width, height)


def animation_frames(path: str) -> Iterator[tuple[np.ndarray, float]]:
    """Each frame as displayed, [H, W, 3] uint8 (alpha over white), with its start time in seconds."""
    try:
        with Image.open(path) as image:
            check_side(path, *image.size)
            seconds = 0.0
            for index in range(image.n_frames):
                image.seek(index)
                yield to_uint8(pillow_rgb(image)), seconds
                seconds += _delay_ms(image.info.get("duration")) / 1000.0
    except InputError:  # a ValueError too: the size check's own sentence
        raise
    except DAMAGE as error:
        raise pillow_error(path, error, "animation") from error


def is_animation(path: str) -> bool:
    """Whether the file is an animated GIF, APNG or WebP (False for anything Pillow cannot open)."""
    try:
        with Image.open(path) as image:
            return animated(image)
    except DAMAGE:
        return False
