"""The studio's uploads: which are videos (by name and by content, which must agree), and their
frames for a chosen range at the working or the file's own resolution, with errors in one sentence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from relight_core import media
from relight_core.errors import InputError
from relight_core.media.animation import is_animation

VIDEO_SUFFIXES = (".mp4", ".mov", ".webm", ".mkv", ".avi", ".m4v")
ANIMATION_SUFFIXES = (".gif", ".png", ".apng", ".webp")  # a still or, by its content, a clip (media.animation)


def frame_count(path, frame_start, frame_end) -> int:
    """How many frames the chosen range holds (1 for an image)."""
    if not is_clip(path):
        return 1
    return max(1, int(frame_end) - int(frame_start) + 1)


def load_frames(path, frame_start, frame_end, size: int | None, multiple: int = media.SIZE_MULTIPLE) -> media.Media:
    """The frames to relight, at the working resolution `size` (None: the file's own; videos: the
    chosen range only), each side a multiple of `multiple` (the model's `Relighter.frame_multiple`)."""
    start, end = int(frame_start or 0), int(frame_end or 0)
    if is_video(path):
        if end < start:
            raise InputError(f"The last frame ({end}) comes before the first ({start}); "
                             "set the frame range again.")
        count = media.probe_video(path).num_frames
        if end >= count:
            raise InputError(f"The last frame ({end}) is past the end of {Path(path).name}, which has "
                             f"{count} frames (0 to {count - 1}); set the frame range again.")
    return media.load_media(path, start=start, end=end + 1, size=int(size) if size else None, multiple=multiple)


def full_frames(path, frame_start, frame_end) -> np.ndarray | None:
    """The chosen frames at the file's own resolution; None when that is too large to hold."""
    try:
        return load_frames(path, frame_start, frame_end, None).frames
    except InputError:
        return None


def is_video(path) -> bool:
    """Whether the upload is a video (an animated GIF, PNG or WebP too); InputError when its content and its
    name disagree (the page treats a file by its name, the readers by its content)."""
    suffix = Path(path).suffix.lower()
    named_video = suffix in VIDEO_SUFFIXES
    if not named_video and media.media_kind(path) == "video":
        if suffix in ANIMATION_SUFFIXES and is_animation(path):
            return True
        raise InputError(f"{Path(path).name} is a video named like an image; give it its video extension "
                         "(.mp4, .mov, .webm) and upload it again.")
    if named_video:
        media.probe_video(path)  # a file that is no video at all gets the reader's own sentence
        if media.media_kind(path) != "video":
            raise InputError(f"{Path(path).name} is a still image named like a video; give it its image "
                             "extension (.png, .jpg) and upload it again.")
    return named_video


def is_clip(path) -> bool:
    """`is_video` for showing the page's video controls: False for a file that cannot be used."""
    try:
        return bool(path) and is_video(path)
    except (InputError, OSError):
        return False


def whole_number(value, name: str) -> int:
    """A whole-number field of a request (an API client may send anything): one sentence naming the
    field for text, NaN, infinities, fractions and numbers past 2⁶³."""
    if isinstance(value, str) and value.strip().lstrip("+-").isdigit():
        value = int(value)
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2 ** 63:
        return value  # exact: a float would round 2⁶³ − 1, the largest seed, up to 2⁶³
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"The {name} must be a whole number, not '{str(value)[:40]}'.") from None
    if not math.isfinite(number) or abs(number) >= 2.0 ** 63 or number != int(number):
        raise InputError(f"The {name} must be a whole number within range, not {number:.6g}.")
    return int(number)

