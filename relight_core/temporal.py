"""Steadier video results from an image model: a temporal filter guided by the input.

A model that relights a video frame by frame (`ModelSpec.chunk_frames` 1) makes each frame's mistakes anew, so
its results flicker where the input does not change: measured on 9-frame test clips, the frame-to-frame change
of its error level was 5.2/255 where the input's own was 4.1 (runs/video-temporal/). `temporal_filter` replaces
each output pixel by a weighted mean of the same pixel in the frames up to `radius` away, weighted by how alike
the *input* is there (a Gaussian of the RGB distance, scale `sigma`, in display units) and how alike the two
frames' target light is (a Gaussian of `light_distances`, scale `light`): where the input holds still under the
same light the frames' results average and their independent mistakes with them; where something moves, or the
light turns, the weights fall and the frame keeps its own result. A joint bilateral filter along time, as the
guided filter of `upsample` is one in space.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_core.errors import InputError

LIGHT_GRID = 16   # the panorama grid (rows) the light distance is measured on


def check_settings(settings) -> tuple[int, float, float]:
    """`ModelSpec.temporal_filter` as (radius, sigma, light); InputError in one sentence otherwise."""
    ok = (isinstance(settings, (list, tuple)) and len(settings) == 3
          and isinstance(settings[0], int) and not isinstance(settings[0], bool) and 0 <= settings[0] <= 16
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 < v <= 100
                  for v in settings[1:]))
    if not ok:
        raise InputError(f"The model's config.json has temporal_filter {settings!r}; it takes [radius in frames "
                         "from 0 to 16, the input's colour scale > 0, the light's scale > 0], or leave it out.")
    return int(settings[0]), float(settings[1]), float(settings[2])


def light_descriptor(panoramas: torch.Tensor) -> np.ndarray:
    """Camera-frame panoramas [T,H,W,3] (linear) → [T,16,16,3] (area means): what `light_distances` compares."""
    from relight_core import lighting

    size = min(LIGHT_GRID, panoramas.shape[1], panoramas.shape[2])
    return lighting.downsample_panorama(panoramas.float(), size).numpy()


def light_distances(descriptors: np.ndarray, radius: int) -> np.ndarray:
    """[radius, T]: row k − 1 holds, at t, the distance of frame t's light to frame t + k's (0 past the end) —
    the mean absolute difference of their descriptors over their mean brightness: 0 for the same light, ~0.45
    between frames of the test clips' light rotation. Memory grows with T · radius, not T²."""
    flat = descriptors.reshape(len(descriptors), -1).astype(np.float64)
    level = np.maximum(flat.mean(axis=1), 1e-12)
    out = np.zeros((radius, len(flat)))
    for k in range(1, min(radius, len(flat) - 1) + 1):
        out[k - 1, :-k] = np.abs(flat[k:] - flat[:-k]).mean(axis=1) / (0.5 * (level[k:] + level[:-k]))
    return out


def temporal_filter(guide: np.ndarray, outputs: list[np.ndarray], radius: int, sigma: float, light: float,
                    distances: np.ndarray | None = None, block: int = 32) -> list[np.ndarray]:
    """Each of `outputs` ([T,H,W,C], like `guide` [T,H,W,3]) filtered along time (module docstring);
    `distances` [≥ radius, T] from `light_distances`, None when every frame has the same light. Works through the
    video `block` frames at a time (each with its `radius` neighbours), so a long video needs only a few
    blocks' worth of memory beyond its results; the blocks change nothing in the result."""
    guide = np.asarray(guide, np.float32)
    frames = guide.shape[0]
    outputs = [np.asarray(o) for o in outputs]
    if radius == 0 or frames < 2:
        return outputs
    results = [np.empty_like(o) for o in outputs]
    for start in range(0, frames, block):
        end = min(frames, start + block)
        lo, hi = max(0, start - radius), min(frames, end + radius)
        near = None if distances is None else distances[:, lo:hi]
        parts = _filtered(guide[lo:hi], [o[lo:hi] for o in outputs], radius, sigma, light, near)
        for result, part in zip(results, parts):
            result[start:end] = part[start - lo:end - lo]
    return results


def _filtered(guide: np.ndarray, outputs: list[np.ndarray], radius: int, sigma: float, light: float,
              distances: np.ndarray | None) -> list[np.ndarray]:
    """`temporal_filter` of a whole (short) clip at once."""
    frames = guide.shape[0]
    sums = [o.astype(np.float32) for o in outputs]               # the frame itself, weight 1
    weights = np.ones(guide.shape[:3] + (1,), np.float32)
    for k in range(1, min(radius, frames - 1) + 1):
        w = np.exp(-((guide[k:] - guide[:-k]) ** 2).sum(-1, keepdims=True) / (2 * sigma ** 2))
        if distances is not None:
            w = w * np.exp(-(distances[k - 1, :-k] / light) ** 2).astype(np.float32)[:, None, None, None]
        for total, o in zip(sums, outputs):
            total[:-k] += w * o[k:]          # frame t gains frame t + k …
            total[k:] += w * o[:-k]          # … and frame t + k gains frame t, with the same weight
        weights[:-k] += w
        weights[k:] += w
    return [(total / weights).astype(o.dtype) for total, o in zip(sums, outputs)]
