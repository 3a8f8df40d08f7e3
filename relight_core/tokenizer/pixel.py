"""A fixed, lossless pixel tokenizer: space-to-depth patches, nothing to train.

Each `patch`×`patch` block of RGB pixels becomes one latent pixel of 3·patch² channels (channel
order (c, dy, dx)), so a 128² image is a 16×16 latent of 192 channels at patch 8 — the same 8×
spatial grid as the learned tokenizers, with the detail kept exactly instead of squeezed into 16
channels. Time is not compressed (temporal factor 1: every frame is its own latent frame), so any
frame count is valid and a video is relit frame-chunk by frame-chunk by the pipeline.

Pixels in [-1, 1] of natural images already have a standard deviation near σ_data = 0.5, so the
latents are the pixels themselves (scaled by `scale`, 1 by default). Pixel-space diffusion with
large patches works when the network predicts the clean signal (JiT, Li & He 2025); EDM's
preconditioning does so at the noise levels that matter.
"""

from __future__ import annotations

import torch
from torch import nn

from relight_core.tokenizer.base import check_frames, check_video, latent_frames


class PixelTokenizer(nn.Module):
    """[B,3,T,H,W] in [-1,1] ⇄ [B,3·p²,T,H/p,W/p]; decode(encode(x)) == x exactly."""

    temporal_factor = 1
    decode_is_cheap = True   # a reshape: previews decode exactly instead of fitting a linear map

    def __init__(self, patch: int = 8, scale: float = 1.0):
        super().__init__()
        if patch < 1:
            raise ValueError(f"patch must be ≥ 1, not {patch}")
        self.spatial_factor = patch
        self.latent_channels = 3 * patch * patch
        self.scale = scale

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        check_video(video, self.temporal_factor, self.spatial_factor)  # whole patches; the DiT's own patch is
        # the pipeline's to check (`Relighter.frame_multiple`: 8 px for the default model, so 128×72 for 16:9)
        b, c, t, h, w = video.shape
        p = self.spatial_factor
        x = video.reshape(b, c, t, h // p, p, w // p, p)
        x = x.permute(0, 1, 4, 6, 2, 3, 5)                                 # (B, 3, p, p, T, h, w)
        return x.reshape(b, c * p * p, t, h // p, w // p) * self.scale    # (B, 3p², T, h, w)

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        b, _, t, h, w = latents.shape
        p = self.spatial_factor
        x = (latents / self.scale).reshape(b, 3, p, p, t, h, w)
        x = x.permute(0, 1, 4, 5, 2, 6, 3)                                 # (B, 3, T, h, p, w, p)
        return x.reshape(b, 3, t, h * p, w * p).clamp(-1, 1)

    def latent_frames(self, num_frames: int) -> int:
        return latent_frames(num_frames, self.temporal_factor)

    def check_frames(self, num_frames: int) -> None:
        check_frames(num_frames, self.temporal_factor)
