"""Images: any Pillow format (16-bit PNGs through OpenCV) and EXR/HDR pictures in, PNG out, and the
resizing every frame goes through."""

from __future__ import annotations

import os

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from PIL import Image, ImageOps  # noqa: E402

from relight_core.colour import linear_to_srgb  # noqa: E402
from relight_core.errors import InputError  # noqa: E402
from relight_core.media.base import atomic, check_path, check_side, kind, name  # noqa: E402
from relight_core.media.hdr import read_hdr  # noqa: E402

SIZE_MULTIPLE = 16  # tokenizer 8× × patch 2

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _composite(rgb: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    return rgb if alpha is None else rgb * alpha + (1.0 - alpha)  # over white


def _png_is_16bit_colour(path: str) -> bool:
    with open(path, "rb") as f:
        head = f.read(26)
    # IHDR: byte 24 is the bit depth, byte 25 the colour type (2 = RGB, 6 = RGBA).
    return head[:8] == _PNG_MAGIC and head[24] == 16 and head[25] in (2, 6)


def pillow_rgb(image: Image.Image) -> np.ndarray:
    """An open 8-bit Pillow image (its current frame) -> float32 [H, W, 3] in [0, 1], alpha over white."""
    has_alpha = image.mode in ("RGBA", "LA", "PA") or "transparency" in image.info
    values = np.asarray(image.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    return _composite(values[..., :3], values[..., 3:] if has_alpha else None)


def pillow_error(path: str, error: Exception, what: str = "image") -> InputError:
    """The one sentence for a file Pillow could not decode: too large, or damaged or truncated."""
    if isinstance(error, Image.DecompressionBombError):
        return InputError(f"{name(path)} is too large to decode safely; use a smaller {what}.")
    return InputError(f"{name(path)} is damaged or truncated ({error or type(error).__name__}); "
                      "re-export or re-download it.")


def _read_pillow(path: str) -> np.ndarray:
    """Any Pillow image -> float32 [H, W, 3] in [0, 1], EXIF-oriented, alpha over white."""
    try:
        with Image.open(path) as image:
            check_side(path, *image.size)
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
            return pillow_rgb(image)
    except InputError:
        raise
    except (Image.DecompressionBombError, OSError, ValueError, SyntaxError) as error:  # too large, damaged data
        raise pillow_error(path, error) from error


def _orient(rgb: np.ndarray, orientation: int) -> np.ndarray:
    """Apply an EXIF orientation tag (1–8) to an array, as ImageOps.exif_transpose does."""
    ops = {2: (0, True), 3: (2, False), 4: (2, True), 5: (3, True), 6: (3, False), 7: (1, True), 8: (1, False)}
    turns, mirror = ops.get(orientation, (0, False))
    rgb = np.rot90(rgb, turns)  # counter-clockwise quarter turns
    return np.ascontiguousarray(rgb[:, ::-1] if mirror else rgb)


def load_image(path) -> np.ndarray:
    """Read one image (PNG/JPEG/WebP/...; EXR/HDR via srgb(clamp(x, 0, 1))) -> [1, H, W, 3] float32."""
    path = check_path(path)
    found = kind(path)
    if found == "video":
        raise InputError(f"{name(path)} is a video, not an image; load it with load_media or load_video.")
    if found == "linear":
        linear = read_hdr(path, check_size=lambda width, height: check_side(path, width, height))
        rgb = linear_to_srgb(np.clip(np.nan_to_num(linear, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0))
    else:
        rgb = _read_pillow(path)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)[None]


def to_uint8(frames: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (clipped) as rounded 8-bit."""
    return (np.clip(np.asarray(frames, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_image(path, frame: np.ndarray) -> None:
    """Write one [H, W, 3] frame in [0, 1] as an 8-bit PNG."""
    with atomic(path) as tmp:
        Image.fromarray(to_uint8(frame)).save(tmp, format="PNG")


# ---------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------


def target_size(height: int, width: int, size: int, multiple: int = SIZE_MULTIPLE) -> tuple[int, int]:
    """The (H, W) that `resize_frames(frames, size, multiple)` gives for frames of height × width:
    the long side scaled to `size`, each side rounded to a multiple (≥ multiple)."""
    scale = size / max(height, width)
    return tuple(max(multiple, round(side * scale / multiple) * multiple) for side in (height, width))


def resize(frames: np.ndarray, H: int, W: int) -> np.ndarray:
    """Antialiased bilinear resize of [T, h, w, 3] to [T, H, W, 3]."""
    if frames.shape[1:3] == (H, W):
        return frames
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)  # [T, 3, h, w]
    out = F.interpolate(x, size=(H, W), mode="bilinear", antialias=True, align_corners=False)
    return out.clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()


def resize_frames(frames: np.ndarray, size: int, multiple: int = SIZE_MULTIPLE) -> np.ndarray:
    """Long side to `size`, each side rounded to a multiple of `multiple` (≥ it), antialiased bilinear."""
    _, h, w, _ = frames.shape
    H, W = target_size(h, w, size, multiple)
    return resize(np.asarray(frames, dtype=np.float32), H, W)
