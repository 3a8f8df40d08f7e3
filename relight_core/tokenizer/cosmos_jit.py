"""The released Cosmos CV8x8x8 tokenizer: TorchScript encoder.jit / decoder.jit, frozen.

Released calling convention (Cosmos-Predict1 `JITVAE` / `VideoJITTokenizer`):

* input video in [-1,1], cast to bf16 before the encoder; outputs cast back to the caller's dtype;
* the encoder returns a tensor or a tuple whose first element is the latent;
* latents are normalised as (z - mean) / std; `mean_std.pt` holds (mean, std) for video,
  reshaped to [16, n] = per channel and per latent frame, of which the first t are used;
  `image_mean_std.pt` holds per-channel (mean, std) used when T = 1;
* decode undoes the normalisation and runs the decoder in bf16;
* the release encodes each clip whole (its chunk length is the clip length) and only splits the
  batch to bound memory. Longer videos are cut into 8N+1-frame clips by the pipeline.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from relight_core.errors import InputError
from relight_core.tokenizer.base import SIGMA_DATA, check_frames, check_video, latent_frames, pixel_frames


def _load_mean_std(path: Path, channels: int) -> tuple[Tensor, Tensor]:
    """(mean, std), each [channels, n] float32, from a torch.load-able (mean, std) pair."""
    try:
        pair = torch.load(path, map_location="cpu", weights_only=True)
        mean, std = (torch.as_tensor(v, dtype=torch.float32).reshape(channels, -1) for v in pair)
    except (RuntimeError, ValueError, TypeError) as error:
        raise InputError(f"Latent statistics file {path} is not a (mean, std) pair of tensors: {error}.") from error
    return mean, std


class CosmosJITTokenizer:
    """The released Cosmos CV8x8x8 tokenizer (TorchScript encoder.jit / decoder.jit), frozen."""

    spatial_factor = 8
    temporal_factor = 8
    latent_channels = 16

    def __init__(
        self,
        encoder_path: str | Path,
        decoder_path: str | Path,
        *,
        mean_std_path: str | Path | None = None,  # Video latent statistics (mean_std.pt).
        image_mean_std_path: str | Path | None = None,  # Single-image statistics (image_mean_std.pt).
        dtype: torch.dtype = torch.bfloat16,  # The release runs both networks in bf16.
        device: str | torch.device = "cpu",
        max_batch: int = 4,  # Clips per network call, to bound memory.
        sigma_data: float = SIGMA_DATA,
    ):
        self.dtype = dtype
        self.device = torch.device(device)
        self.max_batch = max_batch
        self.sigma_data = sigma_data
        self.encoder = self._load(encoder_path)
        self.decoder = self._load(decoder_path)
        self.video_stats = _load_mean_std(Path(mean_std_path), 16) if mean_std_path else None
        # Without an image file, the video statistics of the first latent frame stand in: causality
        # makes that frame an encoding of the first image alone.
        self.image_stats = (
            _load_mean_std(Path(image_mean_std_path), 16)
            if image_mean_std_path
            else None if self.video_stats is None else tuple(s[:, :1] for s in self.video_stats)
        )

    def _load(self, path: str | Path) -> torch.jit.ScriptModule:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"Tokenizer file {path} does not exist: download the Cosmos tokenizer there.")
        module = torch.jit.load(str(path), map_location=self.device)
        module.to(self.dtype).eval()
        for parameter in module.parameters():
            parameter.requires_grad_(False)
        return module

    def set_dtype(self, dtype: torch.dtype) -> None:
        """Compute in `dtype` from now on (the Relighter's precision; the spec's dtype is only a default)."""
        if dtype != self.dtype:
            self.dtype = dtype
            self.encoder.to(dtype)
            self.decoder.to(dtype)

    def latent_frames(self, num_frames: int) -> int:
        """Number of latent frames t for T pixel frames."""
        return latent_frames(num_frames, self.temporal_factor)

    def check_frames(self, num_frames: int) -> None:
        """Raise InputError unless T = 1 + 8k."""
        check_frames(num_frames, self.temporal_factor)

    def _stats(self, t: int) -> tuple[Tensor, Tensor] | None:
        """(mean, std) shaped [1,16,t,1,1] for t latent frames, or None without statistics."""
        stats = self.image_stats if t == 1 else self.video_stats
        if stats is None:
            return None
        mean, std = stats
        frames = mean.shape[1]
        if frames == 1:  # Per-channel statistics broadcast over time.
            return mean.reshape(1, 16, 1, 1, 1), std.reshape(1, 16, 1, 1, 1)
        if frames < t:
            raise InputError(
                f"The latent statistics cover {frames} latent frames but the clip needs {t}: "
                f"use clips of at most {pixel_frames(frames, self.temporal_factor)} frames."
            )
        # Causality: the first t latent frames of a longer clip are those of a t-frame clip.
        return mean[:, :t].reshape(1, 16, t, 1, 1), std[:, :t].reshape(1, 16, t, 1, 1)

    @torch.no_grad()
    def encode(self, video: Tensor) -> Tensor:
        """[B,3,T,H,W] in [-1,1] -> normalised latents × sigma_data, [B,16,t,h,w]."""
        check_video(video, self.temporal_factor)
        pieces = []
        for clip in video.split(self.max_batch):
            latent = self.encoder(clip.to(self.device, self.dtype))
            pieces.append(latent[0] if isinstance(latent, (tuple, list)) else latent)
        latents = torch.cat(pieces).float()  # (B, 16, t, h, w)
        stats = self._stats(latents.shape[2])
        if stats is not None:
            mean, std = (s.to(latents.device) for s in stats)
            latents = (latents - mean) / std
        return (latents * self.sigma_data).to(video.dtype)

    @torch.no_grad()
    def decode(self, latents: Tensor) -> Tensor:
        """Latents [B,16,t,h,w] (× sigma_data) -> video [B,3,T,H,W] clamped to [-1,1]."""
        z = latents.float() / self.sigma_data
        stats = self._stats(z.shape[2])
        if stats is not None:
            mean, std = (s.to(z.device) for s in stats)
            z = z * std + mean
        pieces = [self.decoder(clip.to(self.device, self.dtype)) for clip in z.split(self.max_batch)]
        return torch.cat(pieces).float().clamp(-1.0, 1.0).to(latents.dtype)
