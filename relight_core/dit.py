"""The UniRelight joint DiT: a Cosmos-Predict1 video transformer over [input | relit | albedo].

Three latent clips of equal length are concatenated along time and denoised together; full
self-attention runs over all of them, so the relit video and its albedo see each other and the
input. Each token carries the 72 channels spelled out in `CHANNELS`; the last three are a learned
clip-type embedding appended here. The blocks follow the released Cosmos-Predict1 7B network
(AdaLN-LoRA modulation, RMSNorm on queries and keys, 3D RoPE repeated per clip, GELU MLP), and
`convert_released_state_dict` maps a released checkpoint onto these modules by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from relight_core.rope import rms_norm_rope, rope_angles

#################################################################################
#                         Token layout: the 72 input channels                   #
#################################################################################

LATENT_CHANNELS = 16
NUM_CLIPS = 3                                    # [input | relit | albedo] along time
LIGHTING_KEYS = ("env_ldr", "env_log", "env_dir")  # released `condition_keys` order (env_dir = env_nrm)
LIGHTING_CHANNELS = len(LIGHTING_KEYS) * (LATENT_CHANNELS + 1)  # 51: each latent + its mask


def channel_layout(latent: int = LATENT_CHANNELS) -> dict[str, slice]:
    """Named channel slices of a token for `latent` latent channels (16 for the released model:
    72 channels; the pixel tokenizer's 192 give 4·192 + 8 = 776)."""
    names = ["noisy", "condition_mask"]
    widths = [latent, 1]
    for key in LIGHTING_KEYS:
        names += [key, f"{key}_mask"]
        widths += [latent, 1]
    names += ["padding_mask", "clip_type"]
    widths += [1, 3]
    layout, start = {}, 0
    for name, width in zip(names, widths):
        layout[name] = slice(start, start + width)
        start += width
    return layout


CHANNELS: dict[str, slice] = channel_layout()
# For 16 latent channels (the released model):
#   noisy 0:16 (c_in-scaled) · condition_mask 16 (1 on given frames) · env_ldr 17:33 + mask 33 ·
#   env_log 34:50 + mask 50 · env_dir 51:67 + mask 67 (lighting non-zero in the relit clip only) ·
#   padding_mask 68 (1 on padded pixels; released inference: all zeros) · clip_type 69:72
#   (learned Embedding(3, 3), row = clip index).
ASSEMBLED_CHANNELS = CHANNELS["padding_mask"].stop   # 69, what `assemble_inputs` returns
TOKEN_CHANNELS = CHANNELS["clip_type"].stop          # 72, what the patch embedding sees


def pack_lighting(env_ldr: torch.Tensor | None, env_log: torch.Tensor | None,
                  env_dir: torch.Tensor | None) -> torch.Tensor:
    """[B,51,t,h,w] from the three lighting latents; a missing one is zeros with mask 0 (dropped)."""
    given = next(z for z in (env_ldr, env_log, env_dir) if z is not None)
    parts = []
    for latent in (env_ldr, env_log, env_dir):
        present = latent is not None
        latent = latent if present else torch.zeros_like(given)
        parts += [latent, torch.full_like(latent[:, :1], float(present))]
    return torch.cat(parts, dim=1)                                   # (B, 51, t, h, w)


def assemble_inputs(noisy: torch.Tensor, condition_mask: torch.Tensor, lighting: torch.Tensor | None,
                    padding_mask: torch.Tensor | None) -> torch.Tensor:
    """[B,69,3t,h,w]: noisy latent, condition mask, lighting (relit clip only), padding mask."""
    b, c, frames, h, w = noisy.shape
    t = frames // NUM_CLIPS
    mask = condition_mask.to(noisy.dtype).expand(b, 1, frames, h, w)               # (B, 1, 3t, h, w)
    light = noisy.new_zeros(b, len(LIGHTING_KEYS) * (c + 1), frames, h, w)         # (B, 51, 3t, h, w)
    if lighting is not None:
        light[:, :, t:2 * t] = lighting.to(noisy.dtype)                            # relit clip only
    if padding_mask is None:
        pad = noisy.new_zeros(b, 1, frames, h, w)                                  # (B, 1, 3t, h, w)
    else:
        pad = F.interpolate(padding_mask.to(noisy.dtype), size=(h, w), mode="nearest")  # (B, 1, h, w)
        pad = pad[:, :, None].expand(b, 1, frames, h, w)                           # (B, 1, 3t, h, w)
    return torch.cat([noisy, mask, light, pad], dim=1)                             # (B, 69, 3t, h, w)


def network(dit: "JointDiT", x_in: torch.Tensor, c_noise: torch.Tensor, lighting: torch.Tensor,
            condition_mask: torch.Tensor) -> torch.Tensor:
    """The raw DiT on EDM-preconditioned input, the one adapter training and `Relighter` share:
    x_in [B,C,3t,h,w], c_noise [B] or [1], lighting [B or 1,51·k,3t,h,w], condition_mask [B,1,3t,1,1]
    are assembled into the token channels and run; returns [B,C,3t,h,w] in float32."""
    b, _, frames, h, w = x_in.shape
    mask = condition_mask.expand(b, 1, frames, h, w)
    tokens = assemble_inputs(x_in, mask, lighting.expand(b, -1, -1, -1, -1), None)   # (B, 69+, 3t, h, w)
    return dit(tokens, c_noise.expand(b)).float()                                  # (B, C, 3t, h, w)


#################################################################################
#                                    Config                                     #
#################################################################################

@dataclass(frozen=True)
class DiTConfig:
    """Size and options of a JointDiT; the token layout (72 channels, 3 clips) is fixed."""

    width: int = 384                       # model channels D
    depth: int = 8                         # number of transformer blocks
    num_heads: int = 6                     # attention heads; head dim = width / num_heads
    mlp_ratio: float = 4.0                 # MLP hidden = mlp_ratio · width
    adaln_lora_dim: int = 64               # rank of the AdaLN-LoRA modulation
    patch_spatial: int = 2                 # latent pixels per token side
    patch_temporal: int = 1                # latent frames per token
    out_channels: int = LATENT_CHANNELS    # latent channels in and out (192 for the pixel tokenizer)
    cross_attention: bool = False          # the released model has it (its context is all zeros)
    context_dim: int = 1024                # T5 embedding width of the released model
    rope_extrapolation: tuple[float, float, float] = (1.0, 1.0, 2.0)  # (h, w, t) NTK ratios
    rope_theta: float = 10000.0

    @property
    def head_dim(self) -> int:
        return self.width // self.num_heads


DIT_PRESETS: dict[str, DiTConfig] = {
    # milliseconds on a CPU; for tests
    "tiny": DiTConfig(width=64, depth=2, num_heads=2, adaln_lora_dim=16),
    # the CPU default model, ~16.5M parameters
    "small": DiTConfig(width=384, depth=8, num_heads=6, adaln_lora_dim=64),
    # the released UniRelight weights (Cosmos-Predict1-7B), ~7.23B parameters
    "unirelight-7b": DiTConfig(width=4096, depth=28, num_heads=32, adaln_lora_dim=256, cross_attention=True),
}


#################################################################################
#          Embedding layers: timestep, normalisation (3D RoPE: rope.py)          #
#################################################################################

class RMSNorm(nn.Module):
    """RMS normalisation with a learned scale, computed in fp32 so bf16 autocast stays stable."""

    def __init__(self, dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.rms_norm(x.float(), x.shape[-1:], self.weight.float(), self.eps).to(x.dtype)


def modulated_layer_norm(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Affine-free LayerNorm (eps 1e-6), then x·(1 + scale) + shift; x [B, L, D], shift/scale [B, D].

    LayerNorm runs on x's own dtype: its kernel keeps the statistics in fp32 even for bf16. With one
    sample the modulation is the LayerNorm's affine, so the whole thing is a single pass.
    """
    if x.shape[0] == 1:
        return F.layer_norm(x, x.shape[-1:], (1 + scale[0]).to(x.dtype), shift[0].to(x.dtype), eps=1e-6)
    normed = F.layer_norm(x, x.shape[-1:], eps=1e-6)
    return torch.addcmul(shift.unsqueeze(1), normed, 1 + scale.unsqueeze(1))   # (B, L, D)


class TimestepEmbedder(nn.Module):
    """c_noise → (normalised sinusoid for the modulations, shared AdaLN-LoRA term [B, 3D])."""

    def __init__(self, width: int):
        super().__init__()
        self.width = width
        self.linear_1 = nn.Linear(width, width, bias=False)
        self.linear_2 = nn.Linear(width, 3 * width, bias=False)
        self.norm = RMSNorm(width)

    def sinusoid(self, c_noise: torch.Tensor) -> torch.Tensor:
        half = self.width // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=c_noise.device) / half)
        angles = c_noise.float()[:, None] * freqs[None]                  # (B, D/2)
        return torch.cat([torch.cos(angles), torch.sin(angles)], dim=-1)  # (B, D), cos first

    def forward(self, c_noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sin = self.sinusoid(c_noise).to(self.linear_1.weight.dtype)     # (B, D)
        adaln_lora = self.linear_2(F.silu(self.linear_1(sin)))          # (B, 3D)
        # With AdaLN-LoRA the released model feeds the raw sinusoid (normalised) to every block.
        return self.norm(sin), adaln_lora


#################################################################################
#                                 Core DiT model                                #
#################################################################################

class Attention(nn.Module):
    """Multi-head attention with RMSNorm on per-head queries and keys; self- or cross-attention."""

    def __init__(self, width: int, num_heads: int, context_dim: int | None = None):
        super().__init__()
        self.num_heads = num_heads
        head_dim = width // num_heads
        kv_dim = width if context_dim is None else context_dim
        self.q_proj = nn.Linear(width, width, bias=False)
        self.k_proj = nn.Linear(kv_dim, width, bias=False)
        self.v_proj = nn.Linear(kv_dim, width, bias=False)
        self.q_norm = RMSNorm(head_dim)
        self.k_norm = RMSNorm(head_dim)
        self.out_proj = nn.Linear(width, width, bias=False)

    def heads(self, x: torch.Tensor) -> torch.Tensor:
        return x.unflatten(-1, (self.num_heads, -1)).transpose(1, 2)           # (B, heads, L, hd)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None,
                rope: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        source = x if context is None else context                             # (B, L or M, ·)
        q, k = self.heads(self.q_proj(x)), self.heads(self.k_proj(source))     # (B, heads, L|M, hd)
        if rope is not None:
            q = rms_norm_rope(q, self.q_norm.weight, *rope, self.q_norm.eps)
            k = rms_norm_rope(k, self.k_norm.weight, *rope, self.k_norm.eps)
        else:
            q, k = self.q_norm(q), self.k_norm(k)
        v = self.heads(self.v_proj(source))                                    # (B, heads, L|M, hd)
        out = F.scaled_dot_product_attention(q, k, v)                          # (B, heads, L, hd)
        return self.out_proj(out.transpose(1, 2).flatten(2))                   # (B, L, D)


class MLP(nn.Module):
    def __init__(self, width: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(width, hidden, bias=False)
        self.fc2 = nn.Linear(hidden, width, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))                                   # exact (erf) GELU, as released


class AdaLNModulation(nn.Module):
    """Low-rank per-layer modulation added to the shared AdaLN-LoRA term: `chunks` × [B, D]."""

    def __init__(self, width: int, lora_dim: int, chunks: int):
        super().__init__()
        self.chunks = chunks
        self.down = nn.Linear(width, lora_dim, bias=False)
        self.up = nn.Linear(lora_dim, chunks * width, bias=False)

    def forward(self, emb: torch.Tensor, adaln_lora: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.up(self.down(F.silu(emb))) + adaln_lora[:, :self.up.out_features]  # (B, chunks·D)
        return out.chunk(self.chunks, dim=-1)


class JointDiTBlock(nn.Module):
    """Self-attention over all three clips, optional cross-attention, MLP; each AdaLN-modulated."""

    def __init__(self, config: DiTConfig):
        super().__init__()
        d, r = config.width, config.adaln_lora_dim
        self.self_attn = Attention(d, config.num_heads)
        self.self_attn_mod = AdaLNModulation(d, r, 3)
        if config.cross_attention:
            self.cross_attn = Attention(d, config.num_heads, context_dim=config.context_dim)
            self.cross_attn_mod = AdaLNModulation(d, r, 3)
        else:
            self.cross_attn = self.cross_attn_mod = None
        self.mlp = MLP(d, int(d * config.mlp_ratio))
        self.mlp_mod = AdaLNModulation(d, r, 3)

    def forward(self, x, emb, adaln_lora, rope, context=None):
        shift, scale, gate = self.self_attn_mod(emb, adaln_lora)                      # 3 × (B, D)
        h = self.self_attn(modulated_layer_norm(x, shift, scale), rope=rope)          # (B, L, D)
        x = torch.addcmul(x, gate.unsqueeze(1), h)                                    # x + gate·h
        # A zero context gives exactly zero cross-attention (no biases, RMSNorm(0) = 0): skip it.
        if self.cross_attn is not None and context is not None:
            shift, scale, gate = self.cross_attn_mod(emb, adaln_lora)                 # 3 × (B, D)
            h = self.cross_attn(modulated_layer_norm(x, shift, scale), context)       # (B, L, D)
            x = torch.addcmul(x, gate.unsqueeze(1), h)
        shift, scale, gate = self.mlp_mod(emb, adaln_lora)                            # 3 × (B, D)
        h = self.mlp(modulated_layer_norm(x, shift, scale))                           # (B, L, D)
        return torch.addcmul(x, gate.unsqueeze(1), h)                                 # (B, L, D)


class FinalLayer(nn.Module):
    """AdaLN-modulated projection of each token back to a patch of latent channels."""

    def __init__(self, config: DiTConfig):
        super().__init__()
        patch = config.patch_spatial ** 2 * config.patch_temporal
        self.modulation = AdaLNModulation(config.width, config.adaln_lora_dim, 2)
        self.linear = nn.Linear(config.width, patch * config.out_channels, bias=False)

    def forward(self, x, emb, adaln_lora):
        shift, scale = self.modulation(emb, adaln_lora)                                # 2 × (B, D)
        return self.linear(modulated_layer_norm(x, shift, scale))                      # (B, L, p·p·pt·C)


class JointDiT(nn.Module):
    """Denoiser network F(c_in·x, c_noise) over [input | relit | albedo] latent clips."""

    def __init__(self, config: DiTConfig):
        super().__init__()
        self.config = config
        c = config
        layout = channel_layout(c.out_channels)
        token_channels = layout["clip_type"].stop
        patch_in = token_channels * c.patch_temporal * c.patch_spatial ** 2
        self.clip_type_embed = nn.Embedding(NUM_CLIPS, token_channels - layout["padding_mask"].stop)
        self.patch_embed = nn.Linear(patch_in, c.width, bias=False)
        self.t_embedder = TimestepEmbedder(c.width)
        self.blocks = nn.ModuleList([JointDiTBlock(c) for _ in range(c.depth)])
        self.final_layer = FinalLayer(c)
        self.initialize_weights()

    def initialize_weights(self):
        # Linear layers: Xavier uniform (DiT / Cosmos convention).
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
        nn.init.normal_(self.clip_type_embed.weight, std=0.02)
        # Timestep MLP: small normal init, as DiT.
        nn.init.normal_(self.t_embedder.linear_1.weight, std=0.02)
        # adaLN-zero: every modulation starts at zero, including the shared LoRA term, so each block
        # is the identity and training starts from a stable residual stack.
        nn.init.zeros_(self.t_embedder.linear_2.weight)
        for block in self.blocks:
            for mod in (block.self_attn_mod, block.cross_attn_mod, block.mlp_mod):
                if mod is not None:
                    nn.init.zeros_(mod.up.weight)
        # Zero output: the initial network predicts F = 0, so x0 = c_skip·x.
        nn.init.zeros_(self.final_layer.modulation.up.weight)
        nn.init.zeros_(self.final_layer.linear.weight)

    def embed_inputs(self, x: torch.Tensor) -> torch.Tensor:
        """Append the learned clip-type embedding: [B,69,3t,h,w] → [B,72,3t,h,w]."""
        b, _, frames, h, w = x.shape
        clip = torch.arange(NUM_CLIPS, device=x.device).repeat_interleave(frames // NUM_CLIPS)  # (3t,)
        types = self.clip_type_embed(clip).T.to(x.dtype)                   # (3, 3t)
        types = types[None, :, :, None, None].expand(b, -1, -1, h, w)      # (B, 3, 3t, h, w)
        return torch.cat([x, types], dim=1)                                # (B, 72, 3t, h, w)

    def patchify(self, x: torch.Tensor) -> torch.Tensor:
        """[B,C,T,H,W] → [B, T'·H'·W', C·pt·p·p], features ordered (c, t, h, w) like the release."""
        b, c, t, h, w = x.shape
        pt, p = self.config.patch_temporal, self.config.patch_spatial
        x = x.reshape(b, c, t // pt, pt, h // p, p, w // p, p)
        x = x.permute(0, 2, 4, 6, 1, 3, 5, 7)                              # (B, T', H', W', C, pt, p, p)
        return x.reshape(b, (t // pt) * (h // p) * (w // p), c * pt * p * p)

    def unpatchify(self, x: torch.Tensor, t: int, h: int, w: int) -> torch.Tensor:
        """[B, L, p·p·pt·C] (features ordered h, w, t, c like the release) → [B,C,T,H,W]."""
        b = x.shape[0]
        pt, p, c = self.config.patch_temporal, self.config.patch_spatial, self.config.out_channels
        x = x.reshape(b, t // pt, h // p, w // p, p, p, pt, c)
        x = x.permute(0, 7, 1, 6, 2, 4, 3, 5)                              # (B, C, T', pt, H', p, W', p)
        return x.reshape(b, c, t, h, w)

    def rope(self, t: int, h: int, w: int, device) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin [3·t·h·w, hd/2] in token units: one clip's 3D RoPE, repeated for each clip."""
        c = self.config
        angles = rope_angles(c.head_dim, t, h, w, c.rope_extrapolation, c.rope_theta, device)  # (thw, hd)
        angles = angles[:, :c.head_dim // 2].repeat(NUM_CLIPS, 1)          # (3·thw, hd/2)
        return angles.cos(), angles.sin()                                  # broadcast over heads

    def forward(self, x: torch.Tensor, c_noise: torch.Tensor, context: torch.Tensor | None = None
                ) -> torch.Tensor:
        """x [B,69,3t,h,w] (see CHANNELS), c_noise [B], context [B,M,1024] or None → [B,16,3t,h,w]."""
        if context is not None and not self.config.cross_attention:
            raise ValueError("this DiTConfig has cross_attention=False; pass context=None")
        _, _, frames, h, w = x.shape
        if frames % NUM_CLIPS:
            raise ValueError(f"{frames} latent frames do not split into {NUM_CLIPS} equal clips")
        pt, p = self.config.patch_temporal, self.config.patch_spatial
        dtype = self.patch_embed.weight.dtype                              # bf16 weights, fp32 input
        x = x.to(dtype)
        context = None if context is None else context.to(dtype)
        tokens = self.patch_embed(self.patchify(self.embed_inputs(x)))     # (B, L, D), L = 3t·h'·w'
        rope = self.rope(frames // NUM_CLIPS // pt, h // p, w // p, x.device)  # 2 × (L, hd)
        emb, adaln_lora = self.t_embedder(c_noise)                         # (B, D), (B, 3D)
        for block in self.blocks:
            tokens = block(tokens, emb, adaln_lora, rope, context)         # (B, L, D)
        out = self.final_layer(tokens, emb, adaln_lora)                    # (B, L, p·p·pt·16)
        return self.unpatchify(out, frames, h, w)                          # (B, 16, 3t, h, w)


def param_count(config: DiTConfig) -> int:
    """Number of parameters of a JointDiT, counted on the meta device (no memory)."""
    with torch.device("meta"):
        model = JointDiT(config)
    return sum(p.numel() for p in model.parameters())
