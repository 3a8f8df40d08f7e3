"""HDR probe files and the per-pixel lighting encodings the model is conditioned on.

Formulas from the released `rendering_utils.py` / `utils_env_proj.hdr_mapping`:
`env_ldr = srgb(clamp(reinhard(x, white=16), 0, 1))` with the per-channel extended Reinhard
`x·(1 + x/16²)/(1 + x)`, `env_log = clamp(srgb(log1p(x)/log1p(10000)), 0, 1)`, where `srgb` is the
piecewise sRGB curve (`relight_core.colour.linear_to_srgb`), not gamma 2.2.
"""

import os

import numpy as np
import torch

from relight_core.colour import linear_to_srgb
from relight_core.errors import InputError
from relight_core.lighting.panorama import panorama_directions

HDR_MAX = 65504.0  # largest finite half float: the released clamp
REINHARD_WHITE = 16.0  # radiance that maps to display white in env_ldr
LOG_SCALE = 10000.0  # radiance that maps to 1 in env_log
MAX_PROBE_SIDE = 16384  # larger files are refused before decoding
MAX_PROBE_PIXELS = 16384 * 8192


# ---------------------------------------------------------------------------------------------
# Cleaning and tone curves
# ---------------------------------------------------------------------------------------------


def clean_hdr(x, intensity: float = 1.0) -> torch.Tensor:
    """Scale by intensity, then NaN/−Inf → 0, +Inf → 65504, clamp to [0, 65504] (released order)."""
    x = torch.as_tensor(x, dtype=torch.float32) * intensity  # a new tensor: cleaned in place
    return x.nan_to_num_(nan=0.0, posinf=HDR_MAX, neginf=0.0).clamp_(0.0, HDR_MAX)


def reinhard(x: torch.Tensor, white: float = REINHARD_WHITE) -> torch.Tensor:
    """Per-channel extended Reinhard x·(1 + x/white²)/(1 + x); maps `white` to exactly 1."""
    return x * (1 + x / white**2) / (1 + x)


def env_ldr(x: torch.Tensor) -> torch.Tensor:
    """Tone-mapped probe in [0, 1]: srgb(clamp(reinhard(x), 0, 1))."""
    return linear_to_srgb(reinhard(x).clamp(0.0, 1.0))


def env_log(x: torch.Tensor) -> torch.Tensor:
    """Log-encoded probe in [0, 1]: clamp(srgb(log1p(x)/log1p(10000)), 0, 1)."""
    return linear_to_srgb(torch.log1p(x) / np.log1p(LOG_SCALE)).clamp(0.0, 1.0)


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


def _check_size(path: str, w: int, h: int) -> None:
    if h < 2 or w < 2 or h > MAX_PROBE_SIDE or w > MAX_PROBE_SIDE or h * w > MAX_PROBE_PIXELS:
        raise InputError(
            f"The light probe {os.path.basename(path)} is {w}×{h} pixels; "
            f"use a lat-long map between 2 and {MAX_PROBE_SIDE} pixels on a side."
        )


def load_probe(path, intensity: float = 1.0) -> torch.Tensor:
    """Read an .exr/.hdr lat-long probe (detected by content) -> cleaned linear [h, w, 3] float32."""
    # Imported here, not at the top: the lighting maths imports without the file readers.
    from relight_core.media.hdr import read_hdr

    path = os.fspath(path)
    name = os.path.basename(path)
    if not np.isfinite(intensity) or intensity <= 0:  # 0 would light the scene with black
        raise InputError(f"The light intensity {intensity} is invalid; use a finite number above 0.")
    if not os.path.isfile(path):
        raise InputError(f"The light probe {path} does not exist; pick an existing .exr or .hdr file.")
    pixels = read_hdr(path, f"The light probe {name}", lambda w, h: _check_size(path, w, h))
    finite = pixels[np.isfinite(pixels)]
    if finite.size == 0 or finite.max() <= 0:
        raise InputError(f"The light probe {name} contains no finite light; use a probe with positive values.")
    return clean_hdr(pixels, intensity)
