"""Media I/O: images and videos in, frames `float32 [T, H, W, 3]` in [0, 1] out; mp4/png/exr back.

Formats are detected by content, never by extension: OpenEXR / Radiance magic bytes, then
anything Pillow can open (PNG, JPEG, WebP, ...; an animated file gives its first frame), then
anything PyAV can demux with a video stream. EXR/HDR images are shown with the plain display
transform `srgb(clamp(x, 0, 1))` (exposure 0, linear 1.0 = display white). Alpha is composited
over white, as the released inference does (`bg_color = (1, 1, 1)`). Every writer writes a
temporary file next to the target and renames it at the end, so a failure leaves nothing
half-written.
"""

import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from fractions import Fraction

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import
# OpenCV prints its own "[ERROR:0@0.4] global loadsave.cpp ..." lines for damaged files; our
# errors already say what went wrong in one sentence. OPENCV_LOG_LEVEL set by the user still wins.
_OPENCV_QUIET = "OPENCV_LOG_LEVEL" not in os.environ

import av  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from PIL import Image, ImageOps, UnidentifiedImageError  # noqa: E402

from relight_core.errors import InputError  # noqa: E402
from relight_core.stderr import quiet_about  # noqa: E402

if _OPENCV_QUIET:
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

MAX_SIDE = 8192  # pixels per side, checked from headers before decoding
MAX_DECODED_PIXELS = 2**28  # T·H·W after decoding (≈ 3.2 GB as float32 RGB)
SIZE_MULTIPLE = 16  # tokenizer 8× × patch 2
AAC_SAMPLE_RATES = (8000, 11025, 12000, 16000, 22050, 24000, 32000, 44100, 48000, 64000, 88200, 96000)

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_RADIANCE_MAGIC = b"#?"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_STILL_DEMUXERS = {"image2", "tty", "gif", "apng"}
_RADIANCE_SIZE = re.compile(rb"[-+]([XY])\s+(\d+)\s+[-+]([XY])\s+(\d+)")


@dataclass(frozen=True)
class Media:
    """Decoded frames plus what is needed to write a result back with the same timing and sound."""

    frames: np.ndarray  # [T, H, W, 3] float32 in [0, 1]
    fps: float | None  # None for images
    is_video: bool
    audio_path: str | None = None  # source file to copy the audio stream from
    audio_start: float = 0.0  # seconds into audio_path where frames[0] is shown


@dataclass(frozen=True)
class VideoInfo:
    """Video metadata read without decoding the clip."""

    num_frames: int  # from the container, or estimated from duration × fps
    fps: float
    width: int  # as displayed (after the rotation metadata)
    height: int
    has_audio: bool


# ---------------------------------------------------------------------------------------------
# Detection and checks
# ---------------------------------------------------------------------------------------------


def _name(path: str) -> str:
    return os.path.basename(path)


def _check_path(path) -> str:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"The file {path} does not exist; pick an existing image or video.")
    if os.path.getsize(path) == 0:
        raise InputError(f"The file {_name(path)} is empty; pick an image or video with content.")
    return path


def _check_side(path: str, width: int, height: int) -> None:
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise InputError(
            f"{_name(path)} is {width}×{height} pixels; use media at most {MAX_SIDE} pixels on a side."
        )


def _check_budget(path: str, num_frames: int, height: int, width: int) -> None:
    if num_frames * height * width > MAX_DECODED_PIXELS:
        raise InputError(
            f"{_name(path)} would decode to {num_frames} frames of {width}×{height}, more than this tool "
            "holds in memory; pass a smaller size, max_frames or a shorter start/end range."
        )


def _kind(path: str) -> str:
    """'linear' (EXR/HDR), 'image' or 'video', judged from the file's bytes."""
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic == _EXR_MAGIC or magic.startswith(_RADIANCE_MAGIC):
        return "linear"
    try:
        with Image.open(path):
            return "image"
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
                raise InputError(f"{_name(path)} contains no video stream; pick an image or a video with picture.")
    except av.FFmpegError:
        pass
    raise InputError(
        f"{_name(path)} is not a supported image or video; use PNG, JPEG, WebP, EXR, HDR, MP4, MOV or WebM."
    )


def _target_size(height: int, width: int, size: int, multiple: int = SIZE_MULTIPLE) -> tuple[int, int]:
    """(H, W) with the long side scaled to `size` and each side rounded to a multiple (≥ multiple)."""
    scale = size / max(height, width)
    return tuple(max(multiple, round(side * scale / multiple) * multiple) for side in (height, width))


def target_size(height: int, width: int, size: int, multiple: int = SIZE_MULTIPLE) -> tuple[int, int]:
    """The (H, W) that `resize_frames(frames, size, multiple)` gives for frames of height × width."""
    return _target_size(height, width, size, multiple)


def media_kind(path) -> str:
    """'image' (PNG, JPEG, EXR, HDR, ...) or 'video', judged from the file's bytes, not its name."""
    path = _check_path(path)
    return "video" if _kind(path) == "video" else "image"


# ---------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Piecewise sRGB encoding of linear values (same curve as the lighting encodings)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Inverse of `linear_to_srgb`: display values in [0, 1] back to linear light."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def _read_linear(path: str) -> np.ndarray:
    """EXR (OpenEXR) or Radiance (OpenCV) -> linear float32 [H, W, 3]."""
    with open(path, "rb") as f:
        head = f.read(4096)
    try:
        if head[:4] == _EXR_MAGIC:
            with OpenEXR.File(path, header_only=True) as f:
                (x0, y0), (x1, y1) = f.header()["dataWindow"]
            _check_side(path, int(x1 - x0 + 1), int(y1 - y0 + 1))
            with OpenEXR.File(path) as f:  # pixel arrays are only valid inside the block
                channels = f.channels()
                name = next((n for n in ("RGB", "RGBA", "Y") if n in channels), None)
                if name is None:
                    raise InputError(f"{_name(path)} has no RGB or Y channels; export it as a plain RGB OpenEXR.")
                pixels = np.array(channels[name].pixels, dtype=np.float32)
        else:
            match = _RADIANCE_SIZE.search(head)
            if match is None:
                raise InputError(f"{_name(path)} has no Radiance resolution line; re-export it as .hdr or .exr.")
            sides = {match.group(1): int(match.group(2)), match.group(3): int(match.group(4))}
            _check_side(path, sides[b"X"], sides[b"Y"])
            bgr = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            if bgr is None:
                raise InputError(f"{_name(path)} could not be decoded as Radiance HDR; re-export it.")
            pixels = bgr[..., 2::-1].astype(np.float32)
    except InputError:
        raise
    except Exception as error:  # OpenEXR raises RuntimeError/ValueError/... on damaged files
        raise InputError(f"{_name(path)} could not be read as OpenEXR ({error}); re-export it.") from error
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return np.repeat(pixels, 3, axis=-1) if pixels.shape[-1] == 1 else pixels[..., :3]


def _composite(rgb: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    return rgb if alpha is None else rgb * alpha + (1.0 - alpha)  # over white


def _png_is_16bit_colour(path: str) -> bool:
    with open(path, "rb") as f:
        head = f.read(26)
    # IHDR: byte 24 is the bit depth, byte 25 the colour type (2 = RGB, 6 = RGBA).
    return head[:8] == _PNG_MAGIC and head[24] == 16 and head[25] in (2, 6)


def _read_pillow(path: str) -> np.ndarray:
    """Any Pillow image -> float32 [H, W, 3] in [0, 1], EXIF-oriented, alpha over white."""
    try:
        with Image.open(path) as image:
            _check_side(path, *image.size)
            orientation = image.getexif().get(0x0112, 1)
            if _png_is_16bit_colour(path):
                # Pillow reduces 16-bit colour PNGs to 8 bits; OpenCV keeps them (as BGR[A]).
                raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
                if raw is None:
                    raise OSError("OpenCV could not decode the 16-bit PNG")
                values = raw[..., [2, 1, 0, 3][: raw.shape[-1]]].astype(np.float32) / 65535.0
                rgb, alpha = values[..., :3], values[..., 3:] if values.shape[-1] == 4 else None
                return _orient(_composite(rgb, alpha), orientation)
            image = ImageOps.exif_transpose(image)
            if image.mode in ("I;16", "I;16L", "I;16B", "I"):
                grey = np.asarray(image, dtype=np.float32) / 65535.0  # 16-bit greyscale PNG/TIFF
                return np.repeat(np.clip(grey, 0, 1)[..., None], 3, axis=-1)
            if image.mode == "F":
                return np.repeat(np.clip(np.asarray(image, np.float32), 0, 1)[..., None], 3, axis=-1)
            has_alpha = image.mode in ("RGBA", "LA", "PA") or "transparency" in image.info
            values = np.asarray(image.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except InputError:
        raise
    except Image.DecompressionBombError as error:
        raise InputError(f"{_name(path)} is too large to decode safely; use a smaller image.") from error
    except (OSError, ValueError, SyntaxError) as error:  # truncated or damaged data
        raise InputError(f"{_name(path)} is damaged or truncated ({error}); re-export or re-download it.") from error
    return _composite(values[..., :3], values[..., 3:] if has_alpha else None)


def _orient(rgb: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation tag (1–8) to an array, as ImageOps.exif_transpose does."""
    ops = {2: (0, True), 3: (2, False), 4: (2, True), 5: (3, True), 6: (3, False), 7: (1, True), 8: (1, False)}
    turns, mirror = ops.get(orientation, (0, False))
    rgb = np.rot90(rgb, turns)  # counter-clockwise quarter turns
    return np.ascontiguousarray(rgb[:, ::-1] if mirror else rgb)


def load_image(path) -> np.ndarray:
    """Read one image (PNG/JPEG/WebP/...; EXR/HDR via srgb(clamp(x, 0, 1))) -> [1, H, W, 3] float32."""
    path = _check_path(path)
    kind = _kind(path)
    if kind == "video":
        raise InputError(f"{_name(path)} is a video, not an image; load it with load_media or load_video.")
    if kind == "linear":
        with quiet_about(path):  # OpenEXR prints its own line about a damaged file; ours says it
            linear = _read_linear(path)
        rgb = linear_to_srgb(np.clip(np.nan_to_num(linear, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0))
    else:
        rgb = _read_pillow(path)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)[None]


# ---------------------------------------------------------------------------------------------
# Videos
# ---------------------------------------------------------------------------------------------


def _reason(error: av.FFmpegError) -> str:
    """FFmpeg's reason in words ("invalid data found when processing input"), without its error number
    and the server-side path that str(error) carries."""
    words = getattr(error, "strerror", None) or str(error)
    return words[:1].lower() + words[1:]


def _open_video(path: str) -> av.container.InputContainer:
    try:
        container = av.open(path)
    except av.FFmpegError as error:
        raise InputError(f"{_name(path)} could not be opened as a video ({_reason(error)}); "
                         "re-export it as MP4.") from error
    if not container.streams.video:
        container.close()
        raise InputError(f"{_name(path)} contains no video stream; pick a video with picture.")
    return container


def _fps(stream) -> float:
    rate = stream.average_rate or stream.guessed_rate or stream.base_rate
    return float(rate) if rate else 24.0


def probe_video(path) -> VideoInfo:
    """Frame count, fps, displayed size and audio presence, from the header and one decoded frame."""
    path = _check_path(path)
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
            raise InputError(f"{_name(path)} has an undecodable video stream ({_reason(error)}); "
                             "re-export it.") from error
        if first is None:
            raise InputError(f"{_name(path)} contains no video frames; pick a video with at least one frame.")
        if round((first.rotation or 0) / 90) % 2:
            width, height = height, width
        return VideoInfo(int(num_frames), fps, int(width), int(height), bool(container.streams.audio))


def _decoded(container, path: str) -> Iterator[av.VideoFrame]:
    try:
        yield from container.decode(container.streams.video[0])
    except av.FFmpegError as error:
        raise InputError(f"{_name(path)} is damaged or truncated ({_reason(error)}); "
                         "re-export or re-download it.") from error


def _resize(frames: np.ndarray, H: int, W: int) -> np.ndarray:
    """Antialiased bilinear resize of [T, h, w, 3] to [T, H, W, 3]."""
    if frames.shape[1:3] == (H, W):
        return frames
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)  # [T, 3, h, w]
    out = F.interpolate(x, size=(H, W), mode="bilinear", antialias=True, align_corners=False)
    return out.clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()


def load_video(path, start: int = 0, end: int | None = None, max_frames: int | None = None, size: int | None = None) -> Media:
    """Decode frames [start, end) (at most max_frames; long side to `size` when given) -> Media."""
    path = _check_path(path)
    if start < 0 or (end is not None and end <= start) or (max_frames is not None and max_frames < 1):
        raise InputError(
            f"The frame range start={start}, end={end}, max_frames={max_frames} is empty; "
            "use 0 ≤ start < end and max_frames ≥ 1."
        )
    info = probe_video(path)
    _check_side(path, info.width, info.height)
    H, W = (info.height, info.width) if size is None else _target_size(info.height, info.width, size)
    expected = min(end or info.num_frames, info.num_frames) - start
    _check_budget(path, min(expected, max_frames or expected), H, W)
    limit = min(end - start if end is not None else np.inf, max_frames or np.inf)
    frames, first_time, decoded, cut_short = [], None, 0, False
    with _open_video(path) as container:
        declared = container.streams.video[0].frames  # exact count from the container (0: unknown)
        container.streams.video[0].thread_type = "AUTO"
        for index, frame in enumerate(_decoded(container, path)):
            decoded = index + 1
            if index < start:
                continue
            if len(frames) >= limit:
                cut_short = True
                break
            _check_budget(path, len(frames) + 1, H, W)  # headers can undercount frames
            first_time = frame.time if first_time is None else first_time
            rgb = np.rot90(frame.to_ndarray(format="rgb24"), round((frame.rotation or 0) / 90))
            frames.append(_resize(rgb[None].astype(np.float32) / 255.0, H, W)[0])
        has_audio = bool(container.streams.audio)
    # A truncated file decodes without an error but stops early: compare with the declared count.
    if declared and not cut_short and decoded < min(declared, start + limit):
        raise InputError(
            f"{_name(path)} is truncated or damaged: only {decoded} of its {declared} frames could be read; "
            "re-export or re-download it."
        )
    if not frames:
        raise InputError(
            f"{_name(path)} has no frames from frame {start} on ({info.num_frames} in all); pick an earlier start."
        )
    return Media(
        frames=np.stack(frames),
        fps=info.fps,
        is_video=True,
        audio_path=path if has_audio else None,
        audio_start=float(first_time) if first_time is not None else start / info.fps,
    )


def load_media(
    path, *, max_frames: int | None = None, start: int = 0, end: int | None = None, size: int | None = None
) -> Media:
    """Image or video, detected by content -> Media (images: T = 1, fps None; start/end ignored)."""
    path = _check_path(path)
    if _kind(path) == "video":
        return load_video(path, start=start, end=end, max_frames=max_frames, size=size)
    frames = load_image(path)
    if size is not None:
        frames = resize_frames(frames, size)
    return Media(frames=frames, fps=None, is_video=False)


def resize_frames(frames: np.ndarray, size: int, multiple: int = SIZE_MULTIPLE) -> np.ndarray:
    """Long side to `size`, each side rounded to a multiple of `multiple` (≥ it), antialiased bilinear."""
    _, h, w, _ = frames.shape
    H, W = _target_size(h, w, size, multiple)
    return _resize(np.asarray(frames, dtype=np.float32), H, W)


# ---------------------------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------------------------


@contextmanager
def _atomic(path) -> Iterator[str]:
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


def _to_uint8(frames: np.ndarray) -> np.ndarray:
    return (np.clip(np.asarray(frames, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_image(path, frame: np.ndarray) -> None:
    """Write one [H, W, 3] frame in [0, 1] as an 8-bit PNG."""
    with _atomic(path) as tmp:
        Image.fromarray(_to_uint8(frame)).save(tmp, format="PNG")


def save_exr(path, linear: np.ndarray, half: bool = False) -> None:
    """Write a linear [H, W, 3] image as OpenEXR (float32, or half when `half`), ZIP-compressed."""
    data = np.ascontiguousarray(linear, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with _atomic(path) as tmp:
        OpenEXR.File(header, {"RGB": data}).write(tmp)


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


def save_video(path, frames: np.ndarray, fps: float, audio_from=None, audio_start: float = 0.0) -> None:
    """Write frames [T, H, W, 3] in [0, 1] as H.264 (yuv420p) mp4; audio from `audio_from` as AAC.

    Odd sizes are padded by repeating the last row/column, since yuv420p needs even sides.
    """
    frames = _to_uint8(frames)
    T, h, w, _ = frames.shape
    if T == 0 or not fps or fps <= 0:
        raise InputError(f"Cannot write a video with {T} frames at {fps} fps; give at least one frame and fps > 0.")
    frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    rate = Fraction(fps).limit_denominator(1001)
    with _atomic(path) as tmp:
        with av.open(tmp, "w", format="mp4", options={"movflags": "+faststart"}) as output:
            stream = output.add_stream("libx264", rate=rate, options={"crf": "18"})
            stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
            if audio_from is not None:
                try:
                    _copy_audio(output, os.fspath(audio_from), audio_start, T / float(rate))
                except av.FFmpegError as error:
                    raise InputError(
                        f"The audio of {_name(os.fspath(audio_from))} could not be copied ({_reason(error)}); "
                        "save without audio."
                    ) from error
            for index, rgb in enumerate(frames):
                frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
                frame.pts = index
                for packet in stream.encode(frame):
                    output.mux(packet)
            for packet in stream.encode(None):
                output.mux(packet)
