"""Videos: metadata without decoding, frames decoded (resized while decoding) with their timing
and audio, and H.264/AAC mp4 written back. An animated GIF, APNG or WebP is read as a video without
sound (`animation`: Pillow composes its frames)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from fractions import Fraction

import av
import numpy as np

from relight_core.errors import InputError
from relight_core.media.animation import animation_frames, is_animation, probe_animation
from relight_core.media.base import Media, atomic, check_path, check_side, name
from relight_core.media.image import SIZE_MULTIPLE, resize, target_size, to_uint8

MAX_DECODED_PIXELS = 2**28  # T·H·W after decoding (≈ 3.2 GB as float32 RGB)
AAC_SAMPLE_RATES = (8000, 11025, 12000, 16000, 22050, 24000, 32000, 44100, 48000, 64000, 88200, 96000)


@dataclass(frozen=True)
class VideoInfo:
    """Video metadata read without decoding the clip."""

    num_frames: int  # from the container, or estimated from duration × fps
    fps: float
    width: int  # as displayed (after the rotation metadata)
    height: int
    has_audio: bool


def _check_budget(path: str, num_frames: int, height: int, width: int) -> None:
    if num_frames * height * width > MAX_DECODED_PIXELS:
        raise InputError(
            f"{name(path)} would decode to {num_frames} frames of {width}×{height}, more than this tool "
            "holds in memory; pass a smaller size, max_frames or a shorter start/end range."
        )


def _reason(error: av.FFmpegError) -> str:
    """FFmpeg's reason in words ("invalid data found when processing input"), without its error number
    and the server-side path that str(error) carries."""
    words = getattr(error, "strerror", None) or str(error)
    return words[:1].lower() + words[1:]


def _open_video(path: str) -> av.container.InputContainer:
    try:
        container = av.open(path)
    except av.FFmpegError as error:
        raise InputError(f"{name(path)} could not be opened as a video ({_reason(error)}); "
                         "re-export it as MP4.") from error
    if not container.streams.video:
        container.close()
        raise InputError(f"{name(path)} contains no video stream; pick a video with picture.")
    return container


def _fps(stream) -> float:
    rate = stream.average_rate or stream.guessed_rate or stream.base_rate
    return float(rate) if rate else 24.0


def probe_video(path) -> VideoInfo:
    """Frame count, fps, displayed size and audio presence, from the header and one decoded frame."""
    path = check_path(path)
    if is_animation(path):
        clip = probe_animation(path)
        return VideoInfo(clip.num_frames, clip.fps, clip.width, clip.height, False)
    with _open_video(path) as container:
        stream = container.streams.video[0]
        fps = _fps(stream)
        num_frames = stream.frames
        if not num_frames:
            seconds = (
                float(stream.duration * stream.time_base)
                if stream.duration
                else (container.duration or 0) / av.time_base
            )
            num_frames = round(seconds * fps)
        width, height = stream.codec_context.width, stream.codec_context.height
        try:
            first = next(container.decode(stream), None)
        except av.FFmpegError as error:
            raise InputError(f"{name(path)} has an undecodable video stream ({_reason(error)}); "
                             "re-export it.") from error
        if first is None:
            raise InputError(f"{name(path)} contains no video frames; pick a video with at least one frame.")
        if round((first.rotation or 0) / 90) % 2:
            width, height = height, width
        return VideoInfo(int(num_frames), fps, int(width), int(height), bool(container.streams.audio))


def _decoded(container, path: str) -> Iterator[av.VideoFrame]:
    try:
        yield from container.decode(container.streams.video[0])
    except av.FFmpegError as error:
        raise InputError(f"{name(path)} is damaged or truncated ({_reason(error)}); "
                         "re-export or re-download it.") from error


@contextmanager
def _frames(path: str) -> Iterator[tuple[Iterator[tuple[np.ndarray, float | None]], int, bool]]:
    """(frames, declared count, has audio) of a video: its frames as displayed, [H, W, 3] uint8 with their
    time in seconds, decoded by PyAV (or, for an animated image, composed by Pillow); the declared count is
    the container's exact one (0: unknown, or an animation)."""
    if is_animation(path):
        composed = animation_frames(path)  # Pillow names a cut-short animation itself: no count to check
        try:
            yield composed, 0, False
        finally:
            composed.close()  # its file, when the reader stopped early
        return
    with _open_video(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rgb = ((np.rot90(frame.to_ndarray(format="rgb24"), round((frame.rotation or 0) / 90)), frame.time)
               for frame in _decoded(container, path))
        yield rgb, stream.frames, bool(container.streams.audio)


def load_video(path, start: int = 0, end: int | None = None, max_frames: int | None = None, size: int | None = None,
               multiple: int = SIZE_MULTIPLE) -> Media:
    """Decode frames [start, end) (at most max_frames; long side to `size` when given, each side a multiple of
    `multiple`) -> Media."""
    path = check_path(path)
    check_range(start, end, max_frames)
    info = probe_video(path)
    check_side(path, info.width, info.height)
    H, W = (info.height, info.width) if size is None else target_size(info.height, info.width, size, multiple)
    expected = min(end or info.num_frames, info.num_frames) - start
    _check_budget(path, min(expected, max_frames or expected), H, W)
    limit = min(end - start if end is not None else np.inf, max_frames or np.inf)
    frames, first_time, decoded, cut_short = [], None, 0, False
    with _frames(path) as (decoded_frames, declared, has_audio):
        for index, (rgb, seconds) in enumerate(decoded_frames):
            decoded = index + 1
            if index < start:
                continue
            if len(frames) >= limit:
                cut_short = True
                break
            _check_budget(path, len(frames) + 1, H, W)  # headers can undercount frames
            first_time = seconds if first_time is None else first_time
            frames.append(resize(rgb[None].astype(np.float32) / 255.0, H, W)[0])
    # A truncated file decodes without an error but stops early: compare with the declared count.
    if declared and not cut_short and decoded < min(declared, start + limit):
        raise InputError(
            f"{name(path)} is truncated or damaged: only {decoded} of its {declared} frames could be read; "
            "re-export or re-download it."
        )
    if not frames:
        raise InputError(
            f"{name(path)} has no frames from frame {start} on ({info.num_frames} in all); pick an earlier start."
        )
    return Media(
        frames=np.stack(frames),
        fps=info.fps,
        is_video=True,
        audio_path=path if has_audio else None,
        audio_start=float(first_time) if first_time is not None else start / info.fps,
    )


def check_range(start: int = 0, end: int | None = None, max_frames: int | None = None) -> None:
    """InputError unless frames [start, end), at most max_frames, can hold a frame."""
    if start < 0 or (end is not None and end <= start) or (max_frames is not None and max_frames < 1):
        raise InputError(
            f"The frame range start={start}, end={end}, max_frames={max_frames} is empty; "
            "use 0 ≤ start < end and max_frames ≥ 1."
        )


def iter_video(path, start: int = 0, end: int | None = None, block: int = 16) -> Iterator[np.ndarray]:
    """Frames [start, end) at the video's own (displayed) resolution, `block` at a time: [n, H, W, 3] float32
    in [0, 1], decoded as `load_video` decodes them — for a video's full-resolution results, written without
    holding all of its frames (`outputs.FullVideo`)."""
    path = check_path(path)
    if block < 1:
        raise ValueError(f"block must be ≥ 1, not {block}")
    pending = []
    with _frames(path) as (decoded_frames, _, _):
        for index, (rgb, _) in enumerate(decoded_frames):
            if index < start:
                continue
            if end is not None and index >= end:
                break
            pending.append(rgb.astype(np.float32) / 255.0)
            if len(pending) == block:
                yield np.stack(pending)
                pending = []
    if pending:
        yield np.stack(pending)


def _copy_audio(output, source: str, start: float, duration: float) -> None:
    """Transcode `source`'s first audio stream, from `start` for `duration` seconds, into AAC."""
    with av.open(source) as container:
        if not container.streams.audio:
            return
        in_stream = container.streams.audio[0]
        rate = in_stream.rate if in_stream.rate in AAC_SAMPLE_RATES else 48000
        layout = "stereo" if in_stream.channels >= 2 else "mono"
        out_stream = output.add_stream("aac", rate=rate, layout=layout)
        resampler = av.AudioResampler(format="fltp", layout=layout, rate=rate)
        first, last = round(start * rate), round((start + duration) * rate)
        position = None  # sample index, in output samples, of the next resampled sample
        written = 0
        for frame in container.decode(in_stream):
            if position is None:
                position = round((frame.time or 0.0) * rate)
            for chunk in resampler.resample(frame):
                samples = chunk.to_ndarray()  # [channels, n] float32 planar
                keep = samples[:, max(first - position, 0) : max(last - position, 0)]
                position += samples.shape[1]
                if keep.shape[1] == 0:
                    continue
                out = av.AudioFrame.from_ndarray(np.ascontiguousarray(keep), format="fltp", layout=layout)
                out.sample_rate, out.pts, out.time_base = rate, written, Fraction(1, rate)
                written += keep.shape[1]
                for packet in out_stream.encode(out):
                    output.mux(packet)
            if position >= last:
                break
        for packet in out_stream.encode(None):
            output.mux(packet)


def save_video(path, frames, fps: float, audio_from=None, audio_start: float = 0.0,
               num_frames: int | None = None) -> None:
    """Write frames [T, H, W, 3] in [0, 1] as H.264 (yuv420p) mp4; audio from `audio_from` as AAC.

    `frames` may also be an iterable of such blocks, all of one size, with `num_frames` their total T: a long
    video written a block at a time (nothing is renamed into place unless exactly that many came).
    Odd sizes are padded by repeating the last row/column, since yuv420p needs even sides.
    """
    whole = isinstance(frames, np.ndarray)
    T = frames.shape[0] if whole else num_frames
    if not T or T < 0 or not fps or fps <= 0:
        raise InputError(f"Cannot write a video with {T} frames at {fps} fps; give at least one frame and fps > 0.")
    blocks = iter([frames] if whole else frames)
    rate = Fraction(fps).limit_denominator(1001)
    with atomic(path) as tmp:
        with av.open(tmp, "w", format="mp4", options={"movflags": "+faststart"}) as output:
            stream, index = None, 0
            for block in blocks:
                block = to_uint8(block)
                h, w = block.shape[1:3]
                block = np.pad(block, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
                if stream is None:  # the first block gives the size; the audio goes in before any picture
                    stream = output.add_stream("libx264", rate=rate, options={"crf": "18"})
                    stream.width, stream.height, stream.pix_fmt = block.shape[2], block.shape[1], "yuv420p"
                    if audio_from is not None:
                        try:
                            _copy_audio(output, os.fspath(audio_from), audio_start, T / float(rate))
                        except av.FFmpegError as error:
                            raise InputError(
                                f"The audio of {name(os.fspath(audio_from))} could not be copied ({_reason(error)}); "
                                "save without audio."
                            ) from error
                elif block.shape[1:3] != (stream.height, stream.width):
                    raise InputError(f"A video's frames must all have one size: {stream.width}×{stream.height}, "
                                     f"then {block.shape[2]}×{block.shape[1]}.")
                for rgb in block:
                    frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
                    frame.pts = index
                    index += 1
                    for packet in stream.encode(frame):
                        output.mux(packet)
            if index != T:
                raise InputError(f"{name(os.fspath(path))} got {index} frames where {T} were due; the source "
                                 "video may have changed while it was being relit: run it again.")
            for packet in stream.encode(None):
                output.mux(packet)
