"""Media I/O: images and videos in, frames `float32 [T, H, W, 3]` in [0, 1] out; mp4/png/exr back.

Formats are detected by content, never by extension: OpenEXR / Radiance magic bytes, then
anything Pillow can open (PNG, JPEG, WebP, ...; an animated GIF, PNG or WebP is a video, its
frames composed by Pillow: `animation`), then anything PyAV can demux with a video stream.
EXR/HDR images are shown with the plain display transform `srgb(clamp(x, 0, 1))` (exposure 0,
linear 1.0 = display white). Alpha is composited over white, as the released inference does
(`bg_color = (1, 1, 1)`). Every writer writes a temporary file next to the target and renames it
at the end, so a failure leaves nothing half-written.

One module per kind of file: `image` (Pillow/OpenCV pictures, resizing), `video` (PyAV; animated
images through `animation`, Pillow), `hdr` (the one OpenEXR/Radiance reader, also used for light
probes and the dataset's probe frames); `base` holds what they share. Every public name is
importable from `relight_core.media`.
"""

from relight_core.colour import linear_to_srgb, srgb_to_linear
from relight_core.media.base import MAX_SIDE, Media, check_path, kind
from relight_core.media.hdr import read_hdr, save_exr
from relight_core.media.image import SIZE_MULTIPLE, load_image, resize_frames, save_image, target_size
from relight_core.media.video import (
    AAC_SAMPLE_RATES,
    MAX_DECODED_PIXELS,
    VideoInfo,
    check_range,
    iter_video,
    load_video,
    probe_video,
    save_video,
)

__all__ = [
    "AAC_SAMPLE_RATES",
    "MAX_DECODED_PIXELS",
    "MAX_SIDE",
    "SIZE_MULTIPLE",
    "Media",
    "VideoInfo",
    "check_range",
    "iter_video",
    "linear_to_srgb",
    "load_image",
    "load_media",
    "load_video",
    "media_kind",
    "probe_video",
    "read_hdr",
    "resize_frames",
    "save_exr",
    "save_image",
    "save_video",
    "srgb_to_linear",
    "target_size",
]


def media_kind(path) -> str:
    """'image' (PNG, JPEG, EXR, HDR, ...) or 'video', judged from the file's bytes, not its name."""
    return "video" if kind(check_path(path)) == "video" else "image"


def load_media(
    path, *, max_frames: int | None = None, start: int = 0, end: int | None = None, size: int | None = None,
    multiple: int = SIZE_MULTIPLE,
) -> Media:
    """Image or video, detected by content -> Media (images: T = 1, fps None; start/end ignored); with `size`,
    the long side scaled to it and each side rounded to a multiple of `multiple` (a model's
    `Relighter.frame_multiple`)."""
    path = check_path(path)
    if kind(path) == "video":
        return load_video(path, start=start, end=end, max_frames=max_frames, size=size, multiple=multiple)
    frames = load_image(path)
    if size is not None:
        frames = resize_frames(frames, size, multiple)
    return Media(frames=frames, fps=None, is_video=False)
