"""Long videos as overlapping chunks of 1 + k·factor frames, and their seamless stitching."""

from __future__ import annotations

import math

import numpy as np


def plan_chunks(num_frames: int, chunk: int, overlap: int) -> list[tuple[int, int]]:
    """(start, length) of each chunk; lengths are `chunk`, except a short video's single chunk."""
    if num_frames <= chunk:
        return [(0, num_frames)]
    stride = chunk - overlap
    starts = list(range(0, num_frames - chunk + 1, stride))
    if starts[-1] + chunk < num_frames:
        starts.append(num_frames - chunk)  # the last chunk ends flush with the video
    return [(s, chunk) for s in starts]


def pad_to_valid(frames: np.ndarray, temporal_factor: int) -> np.ndarray:
    """Repeat the last frame until the count is 1 + k·temporal_factor (a causal tokenizer's rule)."""
    t = frames.shape[0]
    valid = 1 + math.ceil((t - 1) / temporal_factor) * temporal_factor
    if valid == t:
        return frames
    return np.concatenate([frames, np.repeat(frames[-1:], valid - t, axis=0)], axis=0)


def crossfade_weights(overlap: int) -> np.ndarray:
    """Weights of the new chunk over the shared frames, rising strictly inside (0, 1)."""
    return (np.arange(1, overlap + 1, dtype=np.float32) / (overlap + 1))


def stitch(out: np.ndarray, chunk: np.ndarray, start: int, weights: np.ndarray | None) -> None:
    """Write `chunk` into `out` at `start`, cross-fading its first len(weights) frames."""
    if weights is None:
        out[start:start + chunk.shape[0]] = chunk
        return
    k = weights.shape[0]
    w = weights[:, None, None, None]
    out[start:start + k] = (1 - w) * out[start:start + k] + w * chunk[:k]
    out[start + k:start + chunk.shape[0]] = chunk[k:]
