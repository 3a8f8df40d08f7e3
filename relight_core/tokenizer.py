"""Video tokenizers: pixels [B,3,T,H,W] in [-1,1] <-> latents [B,16,t,h,w] scaled by sigma_data.

Two implementations share the `Tokenizer` protocol:

* `CausalVideoAutoencoder` — the project's small trainable tokenizer (8× space, causal 1/2/4/8× time,
  16 channels), cheap enough for a laptop CPU;
* `CosmosJITTokenizer` — the released Cosmos CV8x8x8 TorchScript encoder/decoder pair that the
  UniRelight 7B weights were trained with.

Time is causal in both: the first frame is encoded alone (an image is one latent frame) and every
further group of `temporal_factor` frames becomes one latent frame, so `T = 1 + k·temporal_factor`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from safetensors.torch import load_file
from torch import Tensor, nn

from relight_core.errors import InputError

SIGMA_DATA = 0.5  # Latents are multiplied by this after encoding (released EDM convention).
SIZE_MULTIPLE = 16  # 8× tokenizer × 2 DiT patch: H and W must be multiples of this.


# ----------------------------------------------------------------------------------------------
# Protocol and shared checks
# ----------------------------------------------------------------------------------------------


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


def check_size(height: int, width: int) -> None:
    """Raise InputError unless H and W are positive multiples of 16 (8× tokenizer × 2 patch)."""
    if height <= 0 or width <= 0 or height % SIZE_MULTIPLE or width % SIZE_MULTIPLE:
        raise InputError(
            f"A frame size of {width}×{height} cannot be tokenized: resize so that width and "
            f"height are multiples of {SIZE_MULTIPLE}."
        )


def check_video(video: Tensor, temporal_factor: int) -> None:
    """Raise InputError unless video is [B,3,T,H,W] with a valid T, H and W."""
    if video.ndim != 5 or video.shape[1] != 3:
        raise InputError(
            f"Expected a video tensor of shape [B,3,T,H,W], got {list(video.shape)}: "
            "add the batch and time axes."
        )
    check_frames(video.shape[2], temporal_factor)
    check_size(video.shape[3], video.shape[4])


# ----------------------------------------------------------------------------------------------
# Small causal video autoencoder
# ----------------------------------------------------------------------------------------------
# Internally every tensor is frame-major, [(B·T), C, H, W], so spatial layers are plain 2D convs
# (fast on CPU) and temporal layers are free reshapes to [B, T, C, H, W]. Nothing mixes a frame
# with later frames, which is what makes the whole network causal.


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


# ----------------------------------------------------------------------------------------------
# Released Cosmos CV8x8x8 TorchScript tokenizer
# ----------------------------------------------------------------------------------------------
# Released calling convention (Cosmos-Predict1 `JITVAE` / `VideoJITTokenizer`):
# * input video in [-1,1], cast to bf16 before the encoder; outputs cast back to the caller's dtype;
# * the encoder returns a tensor or a tuple whose first element is the latent;
# * latents are normalised as (z - mean) / std; `mean_std.pt` holds (mean, std) for video,
#   reshaped to [16, n] = per channel and per latent frame, of which the first t are used;
#   `image_mean_std.pt` holds per-channel (mean, std) used when T = 1;
# * decode undoes the normalisation and runs the decoder in bf16;
# * the release encodes each clip whole (its chunk length is the clip length) and only splits the
#   batch to bound memory. Longer videos are cut into 8N+1-frame clips by the pipeline.


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


# ----------------------------------------------------------------------------------------------
# Building from a JSON-able spec
# ----------------------------------------------------------------------------------------------


def _resolve(name: str, weights_dir: Path | None) -> Path:
    """A file named in a spec, relative to weights_dir; InputError naming it when missing."""
    path = Path(name) if weights_dir is None else Path(weights_dir) / name
    if not path.is_file():
        raise InputError(f"Tokenizer file {path} does not exist: check the model folder and its config.")
    return path


def build_tokenizer(
    spec: dict, weights_dir: Path | None = None, device: str | torch.device = "cpu"
) -> Tokenizer:
    """Build a tokenizer from a JSON-able spec; file names are relative to weights_dir.

    `{"type": "causal-ae", "preset": "small", "weights": "tokenizer.safetensors", **config fields}`
    or `{"type": "cosmos-jit", "encoder": "encoder.jit", "decoder": "decoder.jit",
    "mean_std": "mean_std.pt", "image_mean_std": "image_mean_std.pt", "dtype": "bfloat16"}`.
    """
    spec = dict(spec)
    kind = spec.pop("type", None)
    if kind == "causal-ae":
        preset = spec.pop("preset", "small")
        if preset not in TOKENIZER_PRESETS:
            raise InputError(f"Unknown tokenizer preset {preset!r}: use one of {sorted(TOKENIZER_PRESETS)}.")
        weights = spec.pop("weights", None)
        fields = {f.name for f in dataclasses.fields(TokenizerConfig)}
        unknown = sorted(set(spec) - fields)
        if unknown:
            raise InputError(f"Unknown tokenizer config keys {unknown}: use only {sorted(fields)}.")
        if "channels" in spec:
            spec["channels"] = tuple(spec["channels"])
        model = CausalVideoAutoencoder(dataclasses.replace(TOKENIZER_PRESETS[preset], **spec))
        if weights is not None:
            model.load_state_dict(load_file(_resolve(weights, weights_dir)))
        return model.to(device).eval()
    if kind == "cosmos-jit":
        dtype = getattr(torch, spec.get("dtype", "bfloat16"), None)
        if not isinstance(dtype, torch.dtype):
            raise InputError(f"Unknown tokenizer dtype {spec['dtype']!r}: use bfloat16 or float32.")
        optional = {key: _resolve(spec[key], weights_dir) for key in ("mean_std", "image_mean_std") if spec.get(key)}
        return CosmosJITTokenizer(
            _resolve(spec.get("encoder", "encoder.jit"), weights_dir),
            _resolve(spec.get("decoder", "decoder.jit"), weights_dir),
            mean_std_path=optional.get("mean_std"),
            image_mean_std_path=optional.get("image_mean_std"),
            dtype=dtype,
            device=device,
        )
    raise InputError(f"Unknown tokenizer type {kind!r}: use 'causal-ae' or 'cosmos-jit'.")
