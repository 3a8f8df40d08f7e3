"""Full-resolution output: carry what the model predicted at its size onto the input's resolution.

The model works at its training size (e.g. 128 px); photos and videos come at 720p and more. What
relighting changes is mostly low-frequency (shading, shadows, colour casts), while the input already
holds the high-frequency detail. So the prediction is transferred as a *ratio*:

    ratio  = small_output / max(small_input, ratio_eps)     at the model's size, per channel
    ratio  → resized to the full size, then edge-aware smoothed by a guided filter
             (He et al. 2013, `cv2.ximgproc.guidedFilter`) guided by the full-resolution input,
             so its edges snap to the input's edges instead of the model grid's blur
    result = clip(full_input × ratio, 0, 1)

The guided filter is linear in the filtered signal, so it is applied to `ratio − c` (c the
per-channel median ratio) and c is added back: a constant ratio comes through exactly (to float32
rounding, ~1e-7).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from relight_core.errors import InputError  # noqa: E402

RATIO_EPS = 1.0 / 255.0     # darkest input value a ratio is taken against (one 8-bit step)
GUIDE_EPS = 1e-2            # guided-filter regularisation, in squared [0, 1] guide units (measured best)


def guided_filter(guide: np.ndarray, source: np.ndarray, radius: int, eps: float, device=None) -> np.ndarray:
    """He et al.'s guided filter of `source` [..., H,W,C] by a colour `guide` [..., H,W,3] (float32; leading
    dimensions are frames filtered one by one): opencv-contrib's `cv2.ximgproc.guidedFilter` where this OpenCV
    has it, else `guided_filter_torch`, the same filter (a machine with plain OpenCV, such as a GPU machine's
    image, computes the training's filtered frames alike; on `device`, a torch device, there)."""
    if not hasattr(cv2, "ximgproc"):
        return guided_filter_torch(guide, source, radius, eps, device)
    if guide.ndim == 3:
        return cv2.ximgproc.guidedFilter(guide, source, int(radius), float(eps))
    frames = [cv2.ximgproc.guidedFilter(np.ascontiguousarray(g), np.ascontiguousarray(p), int(radius), float(eps))
              for g, p in zip(guide.reshape(-1, *guide.shape[-3:]), source.reshape(-1, *source.shape[guide.ndim - 3:]))]
    return np.stack(frames).reshape(source.shape).astype(np.float32)


def guided_filter_torch(guide: np.ndarray, source: np.ndarray, radius: int, eps: float, device=None) -> np.ndarray:
    """The colour guided filter (He et al. 2013, section 3.5) as `cv2.ximgproc.guidedFilter` computes it: box
    means over (2r+1)² windows with the border mirrored as OpenCV's BORDER_REFLECT (edge pixel repeated), the
    guide's 3×3 covariance + eps·I inverted per pixel; float64 inside, float32 out (within ~1e-7 of OpenCV's).
    `guide` [..., H,W,3], `source` [..., H,W] or [..., H,W,C] with the same leading dimensions; computed on
    `device` (None: the CPU), a few frames at a time on a CPU (~15 ms a 128² frame), many on a GPU."""
    import torch

    lead = guide.shape[:-3]
    h, w = guide.shape[-3:-1]
    guides = np.asarray(guide, dtype=np.float32).reshape(-1, h, w, 3)
    src = np.asarray(source, dtype=np.float32)
    flat = src.ndim == guide.ndim - 1
    sources = src.reshape(len(guides), h, w, -1)
    device = torch.device(device or "cpu")
    chunk = 2 if device.type == "cpu" else 64        # a CPU's caches hold two frames' sums; more only slows it
    parts = []
    for start in range(0, len(guides), chunk):
        image = torch.from_numpy(guides[start:start + chunk]).to(device, torch.float64).permute(0, 3, 1, 2)
        p = torch.from_numpy(sources[start:start + chunk]).to(device, torch.float64).permute(0, 3, 1, 2)
        parts.append(_guided_frames(image, p, int(radius), eps).permute(0, 2, 3, 1).cpu().numpy().astype(np.float32))
    result = np.concatenate(parts) if parts else np.zeros((0, h, w, sources.shape[-1]), np.float32)
    return result.reshape(*lead, h, w) if flat else result.reshape(*lead, h, w, sources.shape[-1])


def _guided_frames(image, p, r: int, eps: float):
    """`guided_filter_torch` on tensors: guides [N,3,H,W] and sources [N,C,H,W] (float64) → [N,C,H,W]."""
    import torch
    import torch.nn.functional as F

    h, w = image.shape[-2:]

    def mirrored(x: torch.Tensor, dim: int) -> torch.Tensor:
        """`x` with r pixels mirrored on at both ends of `dim` (the edge pixel repeated, again and again past it)."""
        n = x.shape[dim]
        if r <= n:
            return torch.cat([x.narrow(dim, 0, r).flip(dim), x, x.narrow(dim, n - r, r).flip(dim)], dim)
        index = torch.arange(-r, n + r, device=x.device) % (2 * n)
        return x.index_select(dim, torch.where(index >= n, 2 * n - 1 - index, index))

    def box(x: torch.Tensor) -> torch.Tensor:
        """Window means by running sums along each axis in turn (O(1) a pixel whatever the radius)."""
        k = 2 * r + 1
        for dim in (2, 3):
            sums = F.pad(mirrored(x, dim).cumsum(dim), (1, 0) if dim == 3 else (0, 0, 1, 0))
            x = sums.narrow(dim, k, sums.shape[dim] - k) - sums.narrow(dim, 0, sums.shape[dim] - k)
        return x / (k * k)

    n = len(image)
    mean_i, mean_p = box(image), box(p)
    pairs = [(i, j) for i in range(3) for j in range(3)]
    cov = box(torch.stack([image[:, i] * image[:, j] for i, j in pairs], 1)) \
        - torch.stack([mean_i[:, i] * mean_i[:, j] for i, j in pairs], 1)                 # [N,9,H,W]
    inverse = torch.linalg.inv(cov.permute(0, 2, 3, 1).reshape(n, h, w, 3, 3)
                               + eps * torch.eye(3, dtype=cov.dtype, device=cov.device))
    channels = p.shape[1]
    cross = (box((image[:, None] * p[:, :, None]).reshape(n, 3 * channels, h, w)).reshape(n, channels, 3, h, w)
             - mean_i[:, None] * mean_p[:, :, None])                                      # [N,C,3,H,W]
    a = torch.einsum("nhwij,ncjhw->ncihw", inverse, cross)
    b = mean_p - (a * mean_i[:, None]).sum(2)                                             # [N,C,H,W]
    return (box(a.reshape(n, 3 * channels, h, w)).reshape(n, channels, 3, h, w) * image[:, None]).sum(2) + box(b)


def guided_ratio_upsample(full_input: np.ndarray, small_input: np.ndarray, small_output: np.ndarray,
                          radius: int | None = None, eps: float = GUIDE_EPS,
                          ratio_eps: float = RATIO_EPS) -> np.ndarray:
    """The model's output at the full input's resolution, by guided ratio transfer (module docstring).

    `full_input` [T,H,W,3] (or [H,W,3]) in [0,1] is what the user gave; `small_input` [T,h,w,3] the
    frames the model saw (a resize of it) and `small_output` [T,h,w,3] what it returned for them.
    Returns float32 [T,H,W,3] (or [H,W,3]) in [0,1]. When the sizes already agree the output is
    returned as it is. `radius` defaults to a quarter of the upsampling factor, at least 1 pixel
    (measured: wider windows blur the ratio across texture edges, where it should not change).
    """
    full = np.asarray(full_input, dtype=np.float32)
    small_in = np.asarray(small_input, dtype=np.float32)
    small_out = np.asarray(small_output, dtype=np.float32)
    single = full.ndim == 3
    if single:
        full, small_in, small_out = full[None], small_in[None], small_out[None]
    if full.ndim != 4 or full.shape[-1] != 3 or small_in.shape != small_out.shape or \
            small_in.ndim != 4 or small_in.shape[0] != full.shape[0] or small_in.shape[-1] != 3:
        raise InputError(f"Full-resolution output needs frames [T,H,W,3] with matching frame counts; got "
                         f"{list(np.shape(full_input))}, {list(np.shape(small_input))} and "
                         f"{list(np.shape(small_output))}.")
    _, H, W, _ = full.shape
    _, h, w, _ = small_in.shape
    if (H, W) == (h, w):
        out = np.clip(small_out, 0.0, 1.0)
        return out[0] if single else out
    if radius is None:
        radius = max(1, round(max(H / h, W / w) / 4))
    ratios = small_out / np.maximum(small_in, ratio_eps)                              # [T, h, w, 3]
    out = np.empty_like(full)
    for t in range(full.shape[0]):
        ratio = cv2.resize(ratios[t], (W, H), interpolation=cv2.INTER_LINEAR)          # [H, W, 3]
        centre = np.median(ratios[t].reshape(-1, 3), axis=0).astype(np.float32)
        guide = np.ascontiguousarray(full[t])
        detail = guided_filter(guide, np.ascontiguousarray(ratio - centre), radius, eps)
        out[t] = np.clip(full[t] * (detail + centre), 0.0, 1.0)
    return out[0] if single else out


def smooth_offset(guide: np.ndarray, output: np.ndarray, radius: int, eps: float = GUIDE_EPS, device=None) -> np.ndarray:
    """What a residual model changed, edge-aware smoothed: clip(guide + GF(output − guide), 0, 1).

    `guide` [T,H,W,3] is the input the model saw and `output` [T,H,W,3] (same size) its relit or
    albedo result, both in [0, 1]. A briefly trained model's offset carries blotches of its own; the
    guided filter (guide = the input) averages them away inside regions and keeps the input's edges
    (measured on held-out scenes: docs/QUALITY.md). `radius` 0 returns `output` unchanged. The filter
    is linear in the offset, so an offset that is constant in each window comes through unchanged.
    """
    if radius <= 0:
        return output
    guide = np.asarray(guide, dtype=np.float32)
    output = np.asarray(output, dtype=np.float32)
    if guide.shape != output.shape or guide.ndim != 4 or guide.shape[-1] != 3:
        raise InputError(f"Smoothing an offset needs two clips [T,H,W,3] of one size; got "
                         f"{list(guide.shape)} and {list(output.shape)}.")
    return np.clip(guide + guided_filter(guide, output - guide, radius, eps, device), 0.0, 1.0)


def plain_upsample(small_output: np.ndarray, height: int, width: int) -> np.ndarray:
    """The baseline: the model's output [T,h,w,3] resized to [T,height,width,3] (bilinear, antialiased)."""
    import torch
    import torch.nn.functional as F

    frames = np.asarray(small_output, dtype=np.float32)
    if frames.shape[1:3] == (height, width):
        return frames
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)
    x = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return x.clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()
