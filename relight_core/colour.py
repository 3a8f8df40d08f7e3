"""Colour maths, done by colour-science: the sRGB curve, light colour from a temperature, CIEDE2000.

* `linear_to_srgb` / `srgb_to_linear`: the piecewise IEC 61966-2-1 curve (`12.92·x` below
  0.0031308, else `1.055·x^(1/2.4) − 0.055`; the released code's `rgb2srgb`), unclipped. Arrays go
  through colour-science's `eotf_inverse_sRGB` / `eotf_sRGB`; torch tensors, which the lighting
  encodings and the trainer's light mixing keep on the model's device, go through the same formula
  here (tests pin the two).
* `temperature_xy`: CIE 1931 xy of a light at a correlated colour temperature (kelvin) and a tint
  Δuv off the Planckian locus (Ohno 2013: the exact black body from the CIE 1931 2° observer).
* `xy_to_linear_srgb`: that chromaticity as linear sRGB / Rec.709 at luminance Y = 1;
  `luminance`: Y of linear sRGB (the middle row of colour-science's sRGB → XYZ matrix).
* `delta_e_2000`: CIEDE2000 between sRGB display values, via XYZ and CIE Lab under D65.

Everything is vectorised over leading axes. colour-science is imported on first use: importing
it takes seconds, and most runs (no temperature change, no evaluation) need none of it.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np
import torch

DELTA_E_BLOCK = 2**18                       # pixels per colour-science call: bounds its float64 temporaries


@functools.cache
def colour_science():
    """The `colour` package (colour-science), imported once, on first use."""
    with warnings.catch_warnings():
        # On import it warns that its SciPy-based features are unavailable; none of them is used here.
        warnings.filterwarnings("ignore", message='"SciPy" related API features are not available')
        import colour
    return colour


def _float_like(x, values) -> np.ndarray:
    """`values` as float64 when `x` is float64, else float32 (the project's image dtype)."""
    return np.asarray(values, dtype=np.float64 if np.asarray(x).dtype == np.float64 else np.float32)


def linear_to_srgb(x):
    """sRGB encoding of linear values (unclipped): an array in gives an array, a tensor a tensor."""
    if isinstance(x, torch.Tensor):
        # Clamp inside the power so the unused branch never produces NaN for tiny or negative x.
        return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)
    return _float_like(x, colour_science().models.eotf_inverse_sRGB(x))


def srgb_to_linear(x):
    """Inverse of `linear_to_srgb`: display values back to linear light (an array or a tensor, as in)."""
    if isinstance(x, torch.Tensor):
        return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)
    return _float_like(x, colour_science().models.eotf_sRGB(x))


def temperature_xy(kelvin, tint=0.0) -> np.ndarray:
    """CIE 1931 xy [..., 2] of light at `kelvin` with tint Δuv (+ greener, − more magenta; 0 = black body)."""
    colour = colour_science()
    cct_duv = np.stack(np.broadcast_arrays(np.asarray(kelvin, np.float64), np.asarray(tint, np.float64)), axis=-1)
    return colour.UCS_uv_to_xy(colour.temperature.CCT_to_uv_Ohno2013(cct_duv))


def xy_to_linear_srgb(xy) -> np.ndarray:
    """Linear sRGB [..., 3] (float64) of chromaticities xy [..., 2] at luminance Y = 1."""
    colour = colour_science()
    return colour.XYZ_to_RGB(colour.xy_to_XYZ(xy), "sRGB")


@functools.cache
def _luminance_weights() -> np.ndarray:
    return np.array(colour_science().RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ[1])


def luminance(linear) -> np.ndarray:
    """Y [...] of linear sRGB values [..., 3], in their float dtype (float32 for other input)."""
    linear = np.asarray(linear)
    return linear @ _luminance_weights().astype(np.result_type(linear.dtype, np.float32))


def delta_e_2000(srgb_a, srgb_b) -> np.ndarray:
    """CIEDE2000 [...] between two sets of sRGB display values [..., 3] in [0, 1] (D65 white, Lab 0–100)."""
    colour = colour_science()
    a, b = (np.asarray(x, np.float64) for x in (srgb_a, srgb_b))
    shape = np.broadcast_shapes(a.shape, b.shape)
    a, b = (np.broadcast_to(x, shape).reshape(-1, 3) for x in (a, b))
    white = colour.RGB_COLOURSPACES["sRGB"].whitepoint

    def lab(rgb: np.ndarray) -> np.ndarray:
        return colour.XYZ_to_Lab(colour.RGB_to_XYZ(rgb, "sRGB", apply_cctf_decoding=True), white)

    out = np.empty(a.shape[0])
    for start in range(0, a.shape[0], DELTA_E_BLOCK):
        block = slice(start, start + DELTA_E_BLOCK)
        out[block] = colour.difference.delta_E_CIE2000(lab(a[block]), lab(b[block]))
    return out.reshape(shape[:-1])


def permute_colours(images: torch.Tensor, order: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Every RGB triple of `images` along `dim` ([B,3k,H,W] by default; a panorama [B,h,w,3] with dim=-1) with its
    channels reordered by `order` [B,3] (a permutation per item: new channel j is old channel order[j]). The data
    engine renders each channel on its own, so an item's frames and probe reordered alike are the scene with its
    paints' and its light's colours swapped, as a render would show it (training's colour permutations)."""
    moved = images.movedim(dim, -1)
    triples = moved.reshape(*moved.shape[:-1], moved.shape[-1] // 3, 3)
    index = order.view(order.shape[0], *([1] * (triples.dim() - 2)), 3).expand_as(triples)
    return triples.gather(-1, index).reshape(moved.shape).movedim(-1, dim)
