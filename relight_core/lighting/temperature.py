"""The light's colour temperature: a white-balance change of a linear probe, warmer or cooler.

`light_gains(kelvin, tint)` is the colour of light at that correlated colour temperature and tint
divided by the colour of a black body at `NEUTRAL_KELVIN` (6500 K, so the default changes nothing),
in linear sRGB/Rec.709, scaled to unit luminance so the light only changes colour, not brightness.
The colour maths is colour-science's (`relight_core.colour`): CCT and Δuv → CIE xy (Ohno 2013, the
exact Planckian locus) → linear sRGB. Lower kelvin: warmer (orange) light; higher: cooler (blue);
a positive tint is greener, a negative one more magenta.

`adjust_light` is the one place a probe gets its exposure and colour: the pipeline and the studio
preview both call it, so the light previewed is the light the model is given.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_core import colour
from relight_core.errors import InputError
from relight_core.lighting.probe import HDR_MAX, clean_hdr

NEUTRAL_KELVIN = 6500.0
MIN_KELVIN = 1700.0
MAX_KELVIN = 25000.0
MAX_TINT = 0.02  # |Δuv|: beyond it a light is no longer "white" (ANSI C78.377 allows ±0.006)
MIN_GAIN = 1e-3  # 1700 K has almost no blue; a zero gain would lose that channel for good


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def check_temperature(kelvin: float) -> float:
    """`kelvin` as a float; InputError unless it is a finite temperature in [MIN_KELVIN, MAX_KELVIN]."""
    value = _number(kelvin)
    if not (math.isfinite(value) and MIN_KELVIN <= value <= MAX_KELVIN):
        raise InputError(f"The light colour temperature {kelvin} K is out of range; use {MIN_KELVIN:.0f} to "
                         f"{MAX_KELVIN:.0f} K ({NEUTRAL_KELVIN:.0f} K is neutral, lower is warmer).")
    return value


def check_tint(tint: float) -> float:
    """`tint` as a float; InputError unless it is a finite Δuv within ±MAX_TINT."""
    value = _number(tint)
    if not (math.isfinite(value) and abs(value) <= MAX_TINT):
        raise InputError(f"The light tint {tint} is out of range; use -{MAX_TINT} (magenta) to {MAX_TINT} "
                         "(green), 0 is none.")
    return value


def _checked(kelvin, tint) -> tuple[np.ndarray, np.ndarray]:
    """Temperatures and tints (numbers or arrays) as float64 arrays, each value checked."""
    return (np.vectorize(check_temperature, otypes=[np.float64])(kelvin),
            np.vectorize(check_tint, otypes=[np.float64])(tint))


def planckian_xy(kelvin, tint=0.0) -> np.ndarray:
    """CIE 1931 xy [..., 2] of light at `kelvin` (a number or an array) and tint Δuv (0: a black body)."""
    return colour.temperature_xy(*_checked(kelvin, tint))


def light_gains(kelvin=NEUTRAL_KELVIN, tint=0.0) -> torch.Tensor:
    """Per-channel linear gains [..., 3] (float32) that give neutral light the colour of `kelvin` and
    `tint` at unit luminance; arrays of temperatures give one row each, in one colour-science call."""
    kelvin, tint = _checked(kelvin, tint)
    if np.all(kelvin == NEUTRAL_KELVIN) and np.all(tint == 0):
        return torch.ones(np.broadcast_shapes(kelvin.shape, tint.shape) + (3,))
    neutral = colour.xy_to_linear_srgb(colour.temperature_xy(NEUTRAL_KELVIN))
    gains = np.maximum(colour.xy_to_linear_srgb(colour.temperature_xy(kelvin, tint)) / neutral, MIN_GAIN)
    return torch.from_numpy(gains / colour.luminance(gains)[..., None]).float()


def white_balance(probe, kelvin: float = NEUTRAL_KELVIN, tint: float = 0.0) -> torch.Tensor:
    """A linear probe [..., 3] with its light's colour set to `kelvin` and `tint` (clamped to HDR_MAX)."""
    probe = torch.as_tensor(probe, dtype=torch.float32)
    if check_temperature(kelvin) == NEUTRAL_KELVIN and check_tint(tint) == 0:
        return probe
    return (probe * light_gains(kelvin, tint).to(probe.device)).clamp_(0.0, HDR_MAX)  # in place: a new tensor


def adjust_light(probe, intensity: float = 1.0, kelvin: float = NEUTRAL_KELVIN, tint: float = 0.0) -> torch.Tensor:
    """The probe as the model gets it: cleaned and scaled by `intensity` (`clean_hdr`), then white-balanced."""
    return white_balance(clean_hdr(probe, intensity), kelvin, tint)
