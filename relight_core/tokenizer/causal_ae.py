"""The project's small trainable causal video autoencoder (8× space, causal 1/2/4/8× time, 16 ch).

Internally every tensor is frame-major, [(B·T), C, H, W], so spatial layers are plain 2D convs
(fast on CPU) and temporal layers are free reshapes to [B, T, C, H, W]. Nothing mixes a frame
with later frames, which is what makes the whole network causal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from relight_core.errors import InputError
from relight_core.tokenizer.base import SIGMA_DATA, check_frames, check_video, latent_frames


@dataclass(frozen=True)
class TokenizerConfig:
    """Sizes of the small causal video autoencoder."""

    channels: tuple[int, int, int] = (32, 64, 128)  # Width after each 2× spatial downsample.
    num_res_blocks: int = 1  # Residual blocks per level, in the encoder and the decoder.
    latent_channels: int = 16  # The Cosmos latent contract.
    temporal_factor: int = 8  # 1, 2, 4 or 8; 8 is the Cosmos CV8x8x8 contract.
    sigma_data: float = SIGMA_DATA  # Latent scale expected by the EDM denoiser.

    def __post_init__(self) -> None:
        if self.temporal_factor not in (1, 2, 4, 8):
            raise InputError(
                f"Tokenizer temporal_factor {self.temporal_factor} is not supported: use 1, 2, 4 or 8."
            )
        if len(self.channels) != 3:
            raise InputError(
                f"Tokenizer channels {self.channels} must list three widths, one per 2× downsample."
            )


TOKENIZER_PRESETS: dict[str, TokenizerConfig] = {
    "tiny": TokenizerConfig(channels=(8, 16, 16), num_res_blocks=1),
    "small": TokenizerConfig(channels=(32, 64, 128), num_res_blocks=2),
}


def _group_norm(channels: int) -> nn.GroupNorm:
    # Per-frame statistics: a norm over [T,H,W] would leak future frames into past ones.
    return nn.GroupNorm(min(8, channels), channels)


class CausalTimeMix(nn.Module):
    """Mixes each frame with the previous one (the first frame sees itself): a causal 2-tap conv."""

    def __init__(self, channels: int):
        super().__init__()
        self.proj = nn.Conv2d(2 * channels, channels, 1)

    def forward(self, x: Tensor, batch: int) -> Tensor:
        bt, c, h, w = x.shape
        frames = x.view(batch, bt // batch, c, h, w)  # (B, T, C, H, W)
        previous = torch.cat([frames[:, :1], frames[:, :-1]], dim=1)  # (B, T, C, H, W)
        pair = torch.stack([previous, frames], dim=2)  # (B, T, 2, C, H, W)
        return self.proj(pair.view(bt, 2 * c, h, w))  # ((B T), C, H, W)


class ResBlock(nn.Module):
    """Two per-frame 3×3 convs plus a causal temporal mix, with a residual connection."""

    def __init__(self, channels: int):
        super().__init__()
        self.norm1 = _group_norm(channels)
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.norm2 = _group_norm(channels)
        self.time_mix = CausalTimeMix(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        # Zero-initialised output so each block starts as the identity.
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)

    def forward(self, x: Tensor, batch: int) -> Tensor:
        h = self.conv1(F.silu(self.norm1(x)))  # ((B T), C, H, W)
        h = self.time_mix(F.silu(self.norm2(h)), batch)  # ((B T), C, H, W)
        return x + self.conv2(h)  # ((B T), C, H, W)


class CausalTimeDown(nn.Module):
    """Halves time causally: frame 0 pairs with itself, then frames (1,2), (3,4), ... pair up."""

    def __init__(self, channels: int):
        super().__init__()
        self.proj = nn.Conv2d(2 * channels, channels, 1)

    def forward(self, x: Tensor, batch: int) -> Tensor:
        bt, c, h, w = x.shape
        frames = x.view(batch, bt // batch, c, h, w)  # (B, T, C, H, W), T = 1 + 2k
        padded = torch.cat([frames[:, :1], frames], dim=1)  # (B, 2 + 2k, C, H, W)
        pairs = padded.reshape(batch * (padded.shape[1] // 2), 2 * c, h, w)  # ((B t), 2C, H, W)
        return self.proj(pairs)  # ((B t), C, H, W), t = 1 + k


class CausalTimeUp(nn.Module):
    """Doubles time causally: latent frame 0 gives one frame, every later one gives two."""

    def __init__(self, channels: int):
        super().__init__()
        self.proj = nn.Conv2d(channels, 2 * channels, 1)

    def forward(self, x: Tensor, batch: int) -> Tensor:
        bt, c, h, w = x.shape
        pairs = self.proj(x).view(batch, 2 * (bt // batch), c, h, w)  # (B, 2t, C, H, W)
        return pairs[:, 1:].reshape(-1, c, h, w)  # ((B (2t-1)), C, H, W)


class Level(nn.Module):
    """One resolution level: optional causal time resampling and residual blocks."""

    def __init__(self, channels: int, num_res_blocks: int, time: type[nn.Module] | None, time_first: bool):
        super().__init__()
        self.time = time(channels) if time is not None else None
        self.time_first = time_first
        self.blocks = nn.ModuleList(ResBlock(channels) for _ in range(num_res_blocks))

    def forward(self, x: Tensor, batch: int) -> Tensor:
        if self.time is not None and self.time_first:
            x = self.time(x, batch)
        for block in self.blocks:
            x = block(x, batch)
        if self.time is not None and not self.time_first:
            x = self.time(x, batch)
        return x


class CausalVideoAutoencoder(nn.Module):
    """Small trainable causal VAE: 8× space by three stride-2 convs, causal time, 16 channels."""

    spatial_factor = 8

    def __init__(self, config: TokenizerConfig = TOKENIZER_PRESETS["small"]):
        super().__init__()
        self.config = config
        self.temporal_factor = config.temporal_factor
        self.latent_channels = config.latent_channels
        c0, c1, c2 = config.channels
        n, z = config.num_res_blocks, config.latent_channels
        # Time is halved at the first log2(temporal_factor) levels, the finest first: the fewer
        # frames reach the expensive high-resolution layers, the cheaper the model.
        halvings = int(math.log2(config.temporal_factor))
        down = [CausalTimeDown if i < halvings else None for i in range(3)]
        up = [CausalTimeUp if i < halvings else None for i in range(3)]

        self.encoder_in = nn.Conv2d(3, c0, 3, stride=2, padding=1)  # H/2
        self.encoder_levels = nn.ModuleList(
            [Level(c0, n, down[0], True), Level(c1, n, down[1], True), Level(c2, n, down[2], True)]
        )
        self.encoder_downs = nn.ModuleList(
            [nn.Conv2d(c0, c1, 3, stride=2, padding=1), nn.Conv2d(c1, c2, 3, stride=2, padding=1)]
        )  # H/4, H/8
        self.encoder_out = nn.Sequential(_group_norm(c2), nn.SiLU(), nn.Conv2d(c2, 2 * z, 3, padding=1))

        self.decoder_in = nn.Conv2d(z, c2, 3, padding=1)
        self.decoder_levels = nn.ModuleList(
            [Level(c2, n, up[2], False), Level(c1, n, up[1], False), Level(c0, n, up[0], False)]
        )
        # Upsampling by a conv to 4× channels and a pixel shuffle: the conv runs at low resolution.
        self.decoder_ups = nn.ModuleList(
            [nn.Conv2d(c2, 4 * c1, 3, padding=1), nn.Conv2d(c1, 4 * c0, 3, padding=1)]
        )  # H/4, H/2
        self.decoder_out = nn.Sequential(_group_norm(c0), nn.SiLU(), nn.Conv2d(c0, 4 * 3, 3, padding=1))

    # --- shapes ---------------------------------------------------------------------------------

    def latent_frames(self, num_frames: int) -> int:
        """Number of latent frames t for T pixel frames."""
        return latent_frames(num_frames, self.temporal_factor)

    def check_frames(self, num_frames: int) -> None:
        """Raise InputError unless T = 1 + k·temporal_factor."""
        check_frames(num_frames, self.temporal_factor)

    # --- network --------------------------------------------------------------------------------

    def posterior(self, video: Tensor) -> tuple[Tensor, Tensor]:
        """Unscaled Gaussian posterior (mean, logvar), each [B,16,t,h,w], of video [B,3,T,H,W]."""
        b, _, t, h, w = video.shape
        x = video.permute(0, 2, 1, 3, 4).reshape(b * t, 3, h, w)  # ((B T), 3, H, W)
        x = self.encoder_in(x)  # ((B T), c0, H/2, W/2)
        x = self.encoder_levels[0](x, b)  # ((B T'), c0, H/2, W/2)
        x = self.encoder_levels[1](self.encoder_downs[0](x), b)  # ((B T''), c1, H/4, W/4)
        x = self.encoder_levels[2](self.encoder_downs[1](x), b)  # ((B t), c2, H/8, W/8)
        moments = self.encoder_out(x)  # ((B t), 32, h, w)
        moments = moments.view(b, -1, *moments.shape[1:]).permute(0, 2, 1, 3, 4)  # (B, 32, t, h, w)
        mean, logvar = moments.chunk(2, dim=1)  # (B, 16, t, h, w) each
        return mean, logvar.clamp(-30.0, 20.0)

    def decode_raw(self, z: Tensor) -> Tensor:
        """Unscaled latents [B,16,t,h,w] -> unclamped video [B,3,T,H,W]."""
        b, c, t, h, w = z.shape
        x = z.permute(0, 2, 1, 3, 4).reshape(b * t, c, h, w)  # ((B t), 16, h, w)
        x = self.decoder_levels[0](self.decoder_in(x), b)  # ((B T''), c2, h, w)
        x = F.pixel_shuffle(self.decoder_ups[0](x), 2)  # ((B T''), c1, 2h, 2w)
        x = F.pixel_shuffle(self.decoder_ups[1](self.decoder_levels[1](x, b)), 2)  # (.., c0, 4h, 4w)
        x = F.pixel_shuffle(self.decoder_out(self.decoder_levels[2](x, b)), 2)  # ((B T), 3, H, W)
        x = x.view(b, -1, 3, *x.shape[-2:])  # (B, T, 3, H, W)
        return x.permute(0, 2, 1, 3, 4)  # (B, 3, T, H, W)

    def forward(self, video: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Training pass: (reconstruction [B,3,T,H,W], mean, logvar); samples z while training."""
        mean, logvar = self.posterior(video)
        z = mean + torch.randn_like(mean) * torch.exp(0.5 * logvar) if self.training else mean
        return self.decode_raw(z), mean, logvar

    # --- Tokenizer protocol ---------------------------------------------------------------------

    @torch.no_grad()
    def encode(self, video: Tensor) -> Tensor:
        """[B,3,T,H,W] in [-1,1] -> posterior mean × sigma_data, [B,16,t,h,w] (deterministic)."""
        check_video(video, self.temporal_factor)
        mean, _ = self.posterior(video)
        return (mean * self.config.sigma_data).to(video.dtype)

    @torch.no_grad()
    def decode(self, latents: Tensor) -> Tensor:
        """Latents [B,16,t,h,w] (× sigma_data) -> video [B,3,T,H,W] clamped to [-1,1]."""
        video = self.decode_raw(latents / self.config.sigma_data)
        return video.clamp(-1.0, 1.0).to(latents.dtype)


def tokenizer_loss(model: CausalVideoAutoencoder, video: Tensor, kl_weight: float = 1e-4) -> dict[str, Tensor]:
    """Training loss of the autoencoder on video [B,3,T,H,W]: L1 reconstruction + kl_weight·KL.

    The small KL term keeps the posterior mean near unit scale, so that latents × sigma_data have
    roughly the spread the EDM denoiser expects. Returns {"loss", "l1", "kl"} (scalars).
    """
    recon, mean, logvar = model(video)
    l1 = (recon.float() - video.float()).abs().mean()
    kl = 0.5 * (mean.float().square() + logvar.float().exp() - 1.0 - logvar.float()).mean()
    return {"loss": l1 + kl_weight * kl, "l1": l1, "kl": kl}
