"""The tokenizer contract shared by every implementation: protocol, frame and size rules."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor

from relight_core.errors import InputError

SIGMA_DATA = 0.5  # Latents are multiplied by this after encoding (released EDM convention).
SIZE_MULTIPLE = 16  # 8× tokenizer × 2 DiT patch: H and W must be multiples of this.


@runtime_checkable
class Tokenizer(Protocol):
    """What the pipeline needs from a video tokenizer."""

    spatial_factor: int
    temporal_factor: int
    latent_channels: int

    def encode(self, video: Tensor) -> Tensor:
        """[B,3,T,H,W] in [-1,1] -> latents [B,16,t,h,w], already multiplied by sigma_data."""
        ...

    def decode(self, latents: Tensor) -> Tensor:
        """Latents [B,16,t,h,w] (× sigma_data) -> video [B,3,T,H,W] clamped to [-1,1]."""
        ...

    def latent_frames(self, num_frames: int) -> int:
        """Number of latent frames t for T pixel frames."""
        ...

    def check_frames(self, num_frames: int) -> None:
        """Raise InputError unless T = 1 + k·temporal_factor."""
        ...


def latent_frames(num_frames: int, temporal_factor: int) -> int:
    """t = 1 + (T-1) // temporal_factor: the first frame alone, then one per group."""
    return 1 + (num_frames - 1) // temporal_factor


def pixel_frames(num_latent_frames: int, temporal_factor: int) -> int:
    """T = 1 + (t-1)·temporal_factor, the inverse of `latent_frames` on valid lengths."""
    return 1 + (num_latent_frames - 1) * temporal_factor


def check_frames(num_frames: int, temporal_factor: int) -> None:
    """Raise InputError unless num_frames = 1 + k·temporal_factor (k ≥ 0)."""
    if num_frames < 1 or (num_frames - 1) % temporal_factor != 0:
        below = 1 + max(num_frames - 1, 0) // temporal_factor * temporal_factor
        raise InputError(
            f"A clip of {num_frames} frames cannot be tokenized: use 1 + k·{temporal_factor} frames "
            f"(e.g. {below} or {below + temporal_factor})."
        )


def check_size(height: int, width: int, multiple: int = SIZE_MULTIPLE) -> None:
    """Raise InputError unless H and W are positive multiples of `multiple` (16 = 8× tokenizer × 2 patch for
    the learned tokenizers; the pixel tokenizer needs only its patch)."""
    if height <= 0 or width <= 0 or height % multiple or width % multiple:
        raise InputError(
            f"A frame size of {width}×{height} cannot be tokenized: resize so that width and "
            f"height are multiples of {multiple}."
        )


def check_video(video: Tensor, temporal_factor: int, multiple: int = SIZE_MULTIPLE) -> None:
    """Raise InputError unless video is [B,3,T,H,W] with a valid T, and H and W multiples of `multiple`."""
    if video.ndim != 5 or video.shape[1] != 3:
        raise InputError(
            f"Expected a video tensor of shape [B,3,T,H,W], got {list(video.shape)}: "
            "add the batch and time axes."
        )
    check_frames(video.shape[2], temporal_factor)
    check_size(video.shape[3], video.shape[4], multiple)
