"""Procedural base-colour textures (checker, stripes, noise, wood) generated with numpy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Texture kinds per split: the held-out test split uses a kind the train split never sees.
TEXTURE_KINDS = {"train": ("checker", "stripes", "noise"), "test": ("wood",)}


@dataclass(frozen=True)
class TextureSpec:
    """A procedural two-colour texture; colours are sRGB in [0, 1]."""

    kind: str                           # one of TEXTURE_KINDS
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    frequency: float                    # pattern repeats per unit of uv
    angle: float                        # pattern orientation, radians
    seed: int                           # noise seed


def make_texture(spec: TextureSpec, size: int = 256) -> np.ndarray:
    """Render the texture as sRGB float32 [size, size, 3], tileable in u and v."""
    v, u = (np.mgrid[0:size, 0:size].astype(np.float32) + 0.5) / size  # [S,S] each
    # Integer frequencies keep every pattern tileable on the unit uv square.
    f = max(1, round(spec.frequency))
    if spec.kind == "checker":
        weight = ((np.floor(u * f) + np.floor(v * f)) % 2).astype(np.float32)
    elif spec.kind == "stripes":
        # Only the axis-aligned and diagonal directions tile; pick the nearest one.
        k = round(2 * spec.angle / np.pi) % 2
        phase = u + v if k else u
        weight = 0.5 + 0.5 * np.tanh(6.0 * np.sin(2 * np.pi * f * phase))
    elif spec.kind == "noise":
        weight = _fractal_noise(size, spec.seed, base=max(2, f))
        weight = np.clip((weight - weight.min()) / (np.ptp(weight) + 1e-6), 0, 1)
    elif spec.kind == "wood":
        # Grain lines across the patch, bent by periodic noise: tileable like the stripes.
        turb = _fractal_noise(size, spec.seed, base=2)
        across = v if round(2 * spec.angle / np.pi) % 2 else u
        weight = (0.5 + 0.5 * np.sin(2 * np.pi * (f * across + 1.5 * turb))) ** 3
    else:
        raise ValueError(f"unknown texture kind {spec.kind!r}")
    a, b = np.asarray(spec.color_a, np.float32), np.asarray(spec.color_b, np.float32)
    return a + (b - a) * weight[..., None]


def _fractal_noise(size: int, seed: int, base: int, octaves: int = 4) -> np.ndarray:
    """Tileable value noise: bilinear-upsampled periodic random grids, octaves summed."""
    rng = np.random.default_rng(seed)
    total = np.zeros((size, size), np.float32)
    for octave in range(octaves):
        cells = base * 2**octave
        grid = rng.random((cells, cells), dtype=np.float32)
        pos = (np.arange(size, dtype=np.float32) + 0.5) * cells / size - 0.5
        i0 = np.floor(pos).astype(int)
        t = pos - i0
        i0, i1 = i0 % cells, (i0 + 1) % cells  # wrap: periodic, hence tileable
        rows = grid[i0] * (1 - t)[:, None] + grid[i1] * t[:, None]  # [S, cells]
        total += (rows[:, i0] * (1 - t) + rows[:, i1] * t) * 0.5**octave
    return total
