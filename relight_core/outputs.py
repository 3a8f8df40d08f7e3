"""Results as files: the one writer of a relight's outputs, for the command line and the batch runner
(`jobs.py`), the studio (`ui/studio.py`) and the studio's cached examples (`scripts/make_examples.py`).

What each mode makes is `MODE_OUTPUTS`. A clip is written as MP4 when the source is a video (with
the source's audio over the same span) and as PNG when it is an image; a video's middle frame can
go beside it as a still, and an image's result as linear-light EXR. Every write is atomic (the
`media` writers rename a finished file into place), so a stopped job leaves no half-written file.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relight_core import media
from relight_core.upsample import guided_ratio_upsample

STREAM_BLOCK = 16  # frames of a video brought to full resolution and written at a time


@dataclass(frozen=True)
class FullVideo:
    """A video's frames [start, end) at its own size, read back from its file a block at a time when its
    results are written (`write_outputs`), so they need never be held together."""

    path: str
    start: int = 0
    end: int | None = None

    def blocks(self) -> Iterator[np.ndarray]:
        return media.iter_video(self.path, self.start, self.end, STREAM_BLOCK)

    def frame(self, index: int) -> np.ndarray:
        """Frame `index` of the range, [H,W,3]."""
        return next(media.iter_video(self.path, self.start + index, self.start + index + 1, 1))[0]


def full_resolution_blocks(full: FullVideo, working: np.ndarray, clip: np.ndarray) -> Iterator[np.ndarray]:
    """`clip` (a result for the working-size frames `working`) at the video's own size, `STREAM_BLOCK` frames at
    a time: each block of `full` decoded, its results brought onto it by guided ratio upsampling — exactly the
    frames of `result_clips(..., full frames)`, in a block's memory."""
    at = 0
    for block in full.blocks():
        n = min(block.shape[0], len(clip) - at)
        if n <= 0:
            break
        yield guided_ratio_upsample(block[:n], working[at:at + n], clip[at:at + n])
        at += n


# The clips each mode writes, in order. `render` takes the albedo as its input, so it writes only
# the rendering; random illuminations write each seed's relit result and the albedo found with it.
MODE_OUTPUTS: dict[str, tuple[str, ...]] = {
    "relight": ("relit", "albedo"),
    "albedo": ("albedo",),
    "render": ("relit",),
    "random": ("relit", "albedo"),
}


def result_clips(result, mode: str, working: np.ndarray, full: np.ndarray | None = None
                 ) -> dict[str, np.ndarray]:
    """The clips `mode` makes from a `RelightResult`, by name; with `full` (the input's frames at their
    own resolution), brought from the working size `working` to it by guided ratio upsampling."""
    clips = {name: getattr(result, name) for name in MODE_OUTPUTS[mode]}
    if full is None:
        return clips
    return {name: guided_ratio_upsample(full, working, clip) for name, clip in clips.items()}


def save_still(stem: Path, frame: np.ndarray) -> Path:
    """`<stem>.png`: one [H,W,3] frame in [0, 1]."""
    path = Path(f"{stem}.png")
    media.save_image(path, frame)
    return path


def save_clip(stem: Path, frames, video: bool, fps: float | None = None,
              audio_path: str | None = None, audio_start: float = 0.0, num_frames: int | None = None) -> Path:
    """`<stem>.mp4` for a video (with `audio_path`'s sound from `audio_start` on), else `<stem>.png`
    (the first frame). A video's `frames` may be blocks of frames, `num_frames` in all (`media.save_video`)."""
    if not video:
        return save_still(stem, frames[0])
    path = Path(f"{stem}.mp4")
    media.save_video(path, frames, fps, audio_from=audio_path, audio_start=audio_start, num_frames=num_frames)
    return path


def write_outputs(clips: dict[str, np.ndarray], folder: Path, video: bool, fps: float | None = None,
                  audio_path: str | None = None, audio_start: float = 0.0, prefix: str = "", suffix: str = "",
                  stills: bool = False, linear: tuple[str, ...] = (), full: FullVideo | None = None,
                  working: np.ndarray | None = None) -> dict[str, Path]:
    """Write each clip as `<prefix><name><suffix>` (`save_clip`) into `folder`; returns the files by key:

    * `name`: the clip (`.mp4` for a video, `.png` for an image);
    * `name_still` (with `stills`): its middle frame as PNG (for an image, the clip's own file);
    * `name_linear` (for the names in `linear`, images only): `<...>-linear.exr`, in linear light.

    With `full` (a video; `clips` made for the working-size frames `working`), each clip is written at the
    video's own size a block at a time (`full_resolution_blocks`), its still the middle frame brought there.
    """
    files: dict[str, Path] = {}
    for name, frames in clips.items():
        stem = Path(folder) / f"{prefix}{name}{suffix}"
        middle = frames.shape[0] // 2
        if full is not None and video:
            kept = []   # the middle frame, caught on its way to the clip (not decoded again for the still)

            def blocks(frames=frames, middle=middle, kept=kept):
                at = 0
                for block in full_resolution_blocks(full, working, frames):
                    if at <= middle < at + len(block):
                        kept.append(block[middle - at])
                    at += len(block)
                    yield block

            files[name] = save_clip(stem, blocks(), True, fps, audio_path, audio_start, num_frames=len(frames))
            if stills:
                files[f"{name}_still"] = save_still(stem, kept[0])
            continue
        files[name] = save_clip(stem, frames, video, fps, audio_path, audio_start)
        if stills:
            files[f"{name}_still"] = save_still(stem, frames[middle]) if video else files[name]
        if name in linear and not video:
            files[f"{name}_linear"] = Path(f"{stem}-linear.exr")
            media.save_exr(files[f"{name}_linear"], media.srgb_to_linear(frames[0]))
    return files
