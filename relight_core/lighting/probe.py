"""HDR probe files and the per-pixel lighting encodings the model is conditioned on.

Formulas from the released `rendering_utils.py` / `utils_env_proj.hdr_mapping`:
`env_ldr = srgb(clamp(reinhard(x, white=16), 0, 1))` with the per-channel extended Reinhard
`x·(1 + x/16²)/(1 + x)`, `env_log = clamp(srgb(log1p(x)/log1p(10000)), 0, 1)`, where `srgb` is the
piecewise sRGB curve (`12.92·x` below 0.0031308, else `1.055·x^(1/2.4) − 0.055`), not gamma 2.2.
"""

import os
import re

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import

_OPENCV_QUIET = "OPENCV_LOG_LEVEL" not in os.environ  # our one-sentence errors replace OpenCV's log lines

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from relight_core.errors import InputError  # noqa: E402
from relight_core.stderr import quiet_about  # noqa: E402

if _OPENCV_QUIET:  # e.g. "[ERROR:0@0.4] global loadsave.cpp ..." before our message for a truncated .hdr
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
from relight_core.lighting.panorama import panorama_directions  # noqa: E402

HDR_MAX = 65504.0  # largest finite half float: the released clamp
REINHARD_WHITE = 16.0  # radiance that maps to display white in env_ldr
LOG_SCALE = 10000.0  # radiance that maps to 1 in env_log
MAX_PROBE_SIDE = 16384  # larger files are refused before decoding
MAX_PROBE_PIXELS = 16384 * 8192

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_RADIANCE_MAGIC = b"#?"
_RADIANCE_SIZE = re.compile(rb"([-+][XY])\s+(\d+)\s+([-+][XY])\s+(\d+)")


# ---------------------------------------------------------------------------------------------
# Cleaning and tone curves
# ---------------------------------------------------------------------------------------------


def clean_hdr(x, intensity: float = 1.0) -> torch.Tensor:
    """Scale by intensity, then NaN/−Inf → 0, +Inf → 65504, clamp to [0, 65504] (released order)."""
    x = torch.as_tensor(x, dtype=torch.float32) * intensity
    return torch.nan_to_num(x, nan=0.0, posinf=HDR_MAX, neginf=0.0).clamp(0.0, HDR_MAX)


def rgb_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Piecewise sRGB encoding of linear values (the released `rgb2srgb`)."""
    # Clamp inside the power so the unused branch never produces NaN for tiny or negative x.
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def reinhard(x: torch.Tensor, white: float = REINHARD_WHITE) -> torch.Tensor:
    """Per-channel extended Reinhard x·(1 + x/white²)/(1 + x); maps `white` to exactly 1."""
    return x * (1 + x / white**2) / (1 + x)


def env_ldr(x: torch.Tensor) -> torch.Tensor:
    """Tone-mapped probe in [0, 1]: srgb(clamp(reinhard(x), 0, 1))."""
    return rgb_to_srgb(reinhard(x).clamp(0.0, 1.0))


def env_log(x: torch.Tensor) -> torch.Tensor:
    """Log-encoded probe in [0, 1]: clamp(srgb(log1p(x)/log1p(10000)), 0, 1)."""
    return rgb_to_srgb(torch.log1p(x) / np.log1p(LOG_SCALE)).clamp(0.0, 1.0)


def encode_lighting(env) -> dict[str, torch.Tensor]:
    """env [T, H, W, 3] linear camera-frame panoramas -> env_ldr, env_log, env_dir, each [T, H, W, 3] in [−1, 1]."""
    env = torch.as_tensor(env, dtype=torch.float32)
    T, H, W, _ = env.shape
    return {
        "env_ldr": 2 * env_ldr(env) - 1,
        "env_log": 2 * env_log(env) - 1,
        "env_dir": panorama_directions(H, W).expand(T, H, W, 3).contiguous(),
    }


def tonemap_display(probe) -> np.ndarray:
    """uint8 [h, w, 3] preview of a probe with the env_ldr curve (what the model sees)."""
    ldr = env_ldr(torch.as_tensor(probe, dtype=torch.float32))
    return (ldr * 255 + 0.5).clamp(0, 255).to(torch.uint8).numpy()


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


def _check_size(path: str, h: int, w: int) -> None:
    if h < 2 or w < 2 or h > MAX_PROBE_SIDE or w > MAX_PROBE_SIDE or h * w > MAX_PROBE_PIXELS:
        raise InputError(
            f"The light probe {os.path.basename(path)} is {w}×{h} pixels; "
            f"use a lat-long map between 2 and {MAX_PROBE_SIDE} pixels on a side."
        )


def _read_exr(path: str) -> np.ndarray:
    import OpenEXR  # here, not at the top: lighting maths must import without an EXR reader

    try:
        with OpenEXR.File(path, header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
        _check_size(path, int(y1 - y0 + 1), int(x1 - x0 + 1))
        with OpenEXR.File(path) as f:  # pixel arrays are only valid inside the block
            channels = f.channels()
            for name in ("RGB", "RGBA", "Y"):
                if name in channels:
                    pixels = np.array(channels[name].pixels, dtype=np.float32)
                    break
            else:
                raise InputError(
                    f"The light probe {os.path.basename(path)} has no RGB or Y channels "
                    f"(found {sorted(channels)}); export it as a plain RGB OpenEXR."
                )
    except InputError:
        raise
    except Exception as error:  # OpenEXR raises RuntimeError/ValueError/... on damaged files
        raise InputError(
            f"The light probe {os.path.basename(path)} could not be read as OpenEXR ({error}); "
            "re-export or re-download it."
        ) from error
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=-1)
    return pixels[..., :3]


def _read_radiance(path: str) -> np.ndarray:
    with open(path, "rb") as f:
        header = f.read(4096)
    match = _RADIANCE_SIZE.search(header)
    if match is None:
        raise InputError(
            f"The light probe {os.path.basename(path)} has no Radiance resolution line; "
            "re-export it as a .hdr or .exr file."
        )
    sizes = {match.group(1)[1:]: int(match.group(2)), match.group(3)[1:]: int(match.group(4))}
    _check_size(path, sizes[b"Y"], sizes[b"X"])
    bgr = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.ndim != 3:
        raise InputError(
            f"The light probe {os.path.basename(path)} could not be decoded as Radiance HDR; "
            "re-export or re-download it."
        )
    return np.ascontiguousarray(bgr[..., 2::-1], dtype=np.float32)  # OpenCV gives BGR


def load_probe(path, intensity: float = 1.0) -> torch.Tensor:
    """Read an .exr/.hdr lat-long probe (detected by content) -> cleaned linear [h, w, 3] float32."""
    path = os.fspath(path)
    name = os.path.basename(path)
    if not np.isfinite(intensity) or intensity <= 0:  # 0 would light the scene with black
        raise InputError(f"The light intensity {intensity} is invalid; use a finite number above 0.")
    if not os.path.isfile(path):
        raise InputError(f"The light probe {path} does not exist; pick an existing .exr or .hdr file.")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic == _EXR_MAGIC:
        with quiet_about(path):  # OpenEXR prints its own line about a damaged file; ours says it
            pixels = _read_exr(path)
    elif magic.startswith(_RADIANCE_MAGIC):
        pixels = _read_radiance(path)
    else:
        raise InputError(f"The light probe {name} is not an OpenEXR or Radiance HDR file; use .exr or .hdr.")
    finite = pixels[np.isfinite(pixels)]
    if finite.size == 0 or finite.max() <= 0:
        raise InputError(f"The light probe {name} contains no finite light; use a probe with positive values.")
    return clean_hdr(pixels, intensity)
