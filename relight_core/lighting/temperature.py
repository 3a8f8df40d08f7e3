"""The light's colour temperature: a white-balance change of a linear probe, warmer or cooler.

`light_gains(kelvin)` is the colour of a black body at that temperature divided by the colour of
one at `NEUTRAL_KELVIN` (6500 K, so the default changes nothing), in linear sRGB/Rec.709, scaled to
unit luminance so the light only changes colour, not brightness. The Planckian locus uses Kang et
al. (2002), the CCT → CIE xy approximation colour-science calls `CCT_to_xy_Kang2002` (error under
1e-3 in xy over 1667–25000 K). Lower kelvin: warmer (orange) light; higher: cooler (blue).

`adjust_light` is the one place a probe gets its exposure and colour: the pipeline and the studio
preview both call it, so the light previewed is the light the model is given.
"""

from __future__ import annotations

import math

import torch

from relight_core.errors import InputError
from relight_core.lighting.probe import HDR_MAX, clean_hdr

NEUTRAL_KELVIN = 6500.0
MIN_KELVIN = 1700.0   # Kang 2002 holds from 1667 K
MAX_KELVIN = 25000.0

_XYZ_TO_LINEAR_SRGB = torch.tensor([[3.2404542, -1.5371385, -0.4985314],
                                    [-0.9692660, 1.8760108, 0.0415560],
                                    [0.0556434, -0.2040259, 1.0572252]], dtype=torch.float64)
_LUMINANCE = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)  # Rec.709 Y of linear RGB


def check_temperature(kelvin: float) -> float:
    """`kelvin` as a float; InputError unless it is a finite temperature in [MIN_KELVIN, MAX_KELVIN]."""
    try:
        value = float(kelvin)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and MIN_KELVIN <= value <= MAX_KELVIN):
        raise InputError(f"The light colour temperature {kelvin} K is out of range; use {MIN_KELVIN:.0f} to "
                         f"{MAX_KELVIN:.0f} K ({NEUTRAL_KELVIN:.0f} K is neutral, lower is warmer).")
    return value


def planckian_xy(kelvin: float) -> tuple[float, float]:
    """CIE 1931 xy chromaticity of a black body at `kelvin` (Kang et al. 2002)."""
    t = check_temperature(kelvin)
    if t <= 4000:
        x = -0.2661239e9 / t**3 - 0.2343589e6 / t**2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t**3 + 2.1070379e6 / t**2 + 0.2226347e3 / t + 0.240390
    if t <= 2222:
        y = -1.1063814 * x**3 - 1.34811020 * x**2 + 2.18555832 * x - 0.20219683
    elif t <= 4000:
        y = -0.9549476 * x**3 - 1.37418593 * x**2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x**3 - 5.87338670 * x**2 + 3.75112997 * x - 0.37001483
    return x, y


def _linear_rgb(kelvin: float) -> torch.Tensor:
    x, y = planckian_xy(kelvin)
    xyz = torch.tensor([x / y, 1.0, (1.0 - x - y) / y], dtype=torch.float64)
    return _XYZ_TO_LINEAR_SRGB @ xyz


def light_gains(kelvin: float = NEUTRAL_KELVIN) -> torch.Tensor:
    """Per-channel linear gains [3] (float32) that give neutral light the colour of `kelvin`, at unit luminance."""
    if check_temperature(kelvin) == NEUTRAL_KELVIN:
        return torch.ones(3)
    gains = (_linear_rgb(kelvin) / _linear_rgb(NEUTRAL_KELVIN)).clamp(min=1e-3)  # 1700 K has almost no blue
    return (gains / (gains @ _LUMINANCE)).float()


def white_balance(probe, kelvin: float = NEUTRAL_KELVIN) -> torch.Tensor:
    """A linear probe [..., 3] with its light's colour temperature set to `kelvin` (clamped to HDR_MAX)."""
    probe = torch.as_tensor(probe, dtype=torch.float32)
    if check_temperature(kelvin) == NEUTRAL_KELVIN:
        return probe
    return (probe * light_gains(kelvin).to(probe.device)).clamp(0.0, HDR_MAX)


def adjust_light(probe, intensity: float = 1.0, kelvin: float = NEUTRAL_KELVIN) -> torch.Tensor:
    """The probe as the model gets it: cleaned and scaled by `intensity` (`clean_hdr`), then white-balanced."""
    return white_balance(clean_hdr(probe, intensity), kelvin)
