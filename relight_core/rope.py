"""The 3D rotary position embedding of the UniRelight DiT, fused with the RMSNorm on queries and keys.

Angles are computed for one clip ([t | h | w] split of the head dim, NTK-scaled extrapolation per
axis, the released order) and the DiT repeats them for each of its three clips.
"""

from __future__ import annotations

import torch


def rope_angles(head_dim: int, t: int, h: int, w: int, extrapolation=(1.0, 1.0, 2.0),
                theta: float = 10000.0, device=None) -> torch.Tensor:
    """[t·h·w, head_dim] rotary angles for one clip, laid out [t | h | w] twice (released order)."""
    dim_h = head_dim // 6 * 2                     # 42 for head dim 128
    dim_t = head_dim - 2 * dim_h                  # 44 for head dim 128

    def axis(length: int, dim: int, ratio: float) -> torch.Tensor:
        ntk = ratio ** (dim / (dim - 2))          # NTK-aware base scaling for extrapolation
        freqs = 1.0 / (theta * ntk) ** (torch.arange(0, dim, 2, dtype=torch.float64, device=device) / dim)
        return torch.outer(torch.arange(length, dtype=torch.float64, device=device), freqs)

    ratio_h, ratio_w, ratio_t = extrapolation
    ang_t = axis(t, dim_t, ratio_t)[:, None, None].expand(t, h, w, -1)   # (t, h, w, dim_t/2)
    ang_h = axis(h, dim_h, ratio_h)[None, :, None].expand(t, h, w, -1)   # (t, h, w, dim_h/2)
    ang_w = axis(w, dim_h, ratio_w)[None, None, :].expand(t, h, w, -1)   # (t, h, w, dim_h/2)
    half = torch.cat([ang_t, ang_h, ang_w], dim=-1)                      # (t, h, w, hd/2)
    return torch.cat([half, half], dim=-1).reshape(t * h * w, head_dim).float()


def rms_norm_rope(x: torch.Tensor, weight: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor,
                  eps: float = 1e-6) -> torch.Tensor:
    """RoPE(RMSNorm(x)) for x [B, heads, L, hd] in few passes; returns a contiguous [B, heads, L, hd].

    The rotation turns dims i and i + hd/2 by the same angle (non-interleaved, as transformer_engine);
    `cos`, `sin` [L, hd/2] hold the first half of the angles (the second half repeats it). The norm's
    weight is folded into the [L, hd] rotation tables, and since a rotation keeps the vector's length
    the RMS scale (statistics in fp32) is applied last.
    """
    half = x.shape[-1] // 2
    w = weight.float()
    w_swapped = torch.cat([-w[half:], w[:half]])                                # weight of the swapped dims
    cos_w = (cos.unsqueeze(-2) * w.view(2, half)).flatten(-2).to(x.dtype)         # (L, hd)
    sin_w = (sin.unsqueeze(-2) * w_swapped.view(2, half)).flatten(-2).to(x.dtype)  # (L, hd)
    rms = torch.linalg.vector_norm(x, dim=-1, keepdim=True, dtype=torch.float32)  # (B, heads, L, 1)
    # Tables and scale in x's dtype: a mixed bf16·fp32 op on CPU would first copy x to fp32.
    inv_rms = torch.rsqrt(rms.square() / x.shape[-1] + eps).to(x.dtype)
    swapped = torch.cat([x[..., half:], x[..., :half]], dim=-1)                 # (B, heads, L, hd)
    return torch.addcmul(swapped * sin_w, x, cos_w) * inv_rms                    # (B, heads, L, hd)
