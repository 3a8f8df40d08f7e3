"""The paper's image metrics: PSNR and SSIM after a per-channel least-squares scale fit on a mask.

UniRelight §5 (after Kocsis et al. 2023, Neural Gaffer, DiffusionRenderer) removes the scale
ambiguity of relighting and albedo with "a three-channel scaling factor using least-squares error
minimization before computing the metrics", and masks the background of synthetic scenes. Here:

* images are display-referred values in [0, 1] (the dataset's sRGB PNGs, the model's output),
  `[T,H,W,3]` or `[H,W,3]`; masks `[T,H,W]` or `[H,W]`, 1 = foreground (geometry). A frame whose
  mask is empty counts all its pixels;
* `scale_fit`: s_c = Σ m·p_c·t_c / Σ m·p_c² over every frame of the item, p ← clip(s·p, 0, 1);
* `psnr`: 10·log10(1 / MSE), the MSE over the frame's mask pixels and three channels, capped at
  100 dB, averaged over frames;
* `ssim`: Wang et al. 2004 (11×11 Gaussian window, σ = 1.5, K1 = 0.01, K2 = 0.03, data range 1,
  'valid' windows) of the two images multiplied by the mask, averaged over the windows centred on
  mask pixels and over the channels, then over frames;
* `delta_e2000`: the mean CIEDE2000 colour difference (colour-science: sRGB display values → CIE
  Lab under D65) over the frame's mask pixels, averaged over frames; `albedo_metrics` adds it,
  on the scale-fitted albedo, to the PSNR/SSIM protocol;
* `steadiness` (clips of > 1 frame, in both): the temporal error and the flicker of the scale-fitted clip
  against its truth (runs/video-temporal/: an image model run frame by frame flickers).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from relight_core import colour

PSNR_CAP = 100.0     # dB for identical images
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _frames(images) -> np.ndarray:
    """[T,H,W,3] float64 (an [H,W,3] image becomes one frame)."""
    x = np.asarray(images, dtype=np.float64)
    return x[None] if x.ndim == 3 else x


def _mask(mask, shape: tuple) -> np.ndarray:
    """[T,H,W] float64 in {0, 1} for frames of `shape`; None, or an empty frame, means every pixel."""
    if mask is None:
        return np.ones(shape[:3])
    m = np.asarray(mask, dtype=np.float64)
    m = m[None] if m.ndim == 2 else m
    m = np.broadcast_to((m > 0.5).astype(np.float64), shape[:3]).copy()
    m[m.reshape(m.shape[0], -1).sum(axis=1) == 0] = 1.0
    return m


def scale_fit(pred, target, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """(clip(s·pred, 0, 1), s): s [3] the per-channel least-squares scale onto target over the mask."""
    p, t = _frames(pred), _frames(target)
    m = _mask(mask, p.shape)[..., None]
    numerator = (m * p * t).sum(axis=(0, 1, 2))
    denominator = (m * p * p).sum(axis=(0, 1, 2))
    scales = np.where(denominator > 0, numerator / np.maximum(denominator, 1e-300), 1.0)
    fitted = np.clip(p * scales, 0.0, 1.0)
    return (fitted[0] if np.ndim(pred) == 3 else fitted), scales


def psnr(pred, target, mask=None) -> float:
    """Mean over frames of 10·log10(1/MSE) on the mask (no scale fit; see `protocol_metrics`)."""
    p, t = _frames(pred), _frames(target)
    m = _mask(mask, p.shape)[..., None]
    mse = (m * (p - t) ** 2).sum(axis=(1, 2, 3)) / (3 * m.sum(axis=(1, 2, 3)))
    values = [PSNR_CAP if e <= 10 ** (-PSNR_CAP / 10) else -10 * math.log10(e) for e in mse]
    return float(np.mean(values))


def _gaussian_window(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    return g / g.sum()


def ssim(pred, target, mask=None) -> float:
    """Mean over frames of the Gaussian SSIM, averaged over windows centred on mask pixels."""
    p, t = _frames(pred), _frames(target)
    m = _mask(mask, p.shape)
    _, H, W, _ = p.shape
    size = min(SSIM_WINDOW, H, W)
    size -= 1 - size % 2                                         # odd, so a window has a centre pixel
    g = _gaussian_window(size, SSIM_SIGMA)
    a = torch.from_numpy(p * m[..., None]).permute(0, 3, 1, 2).reshape(-1, 1, H, W)   # (T·3, 1, H, W)
    b = torch.from_numpy(t * m[..., None]).permute(0, 3, 1, 2).reshape(-1, 1, H, W)

    def blur(x: torch.Tensor) -> torch.Tensor:                  # separable Gaussian, 'valid' windows
        return F.conv2d(F.conv2d(x, g.view(1, 1, -1, 1)), g.view(1, 1, 1, -1))

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a ** 2
    var_b = blur(b * b) - mu_b ** 2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    ssim_map = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    ssim_map = ssim_map.reshape(p.shape[0], 3, H - size + 1, W - size + 1).mean(dim=1).numpy()  # (T, h, w)
    half = size // 2
    centres = m[:, half:H - half, half:W - half]
    values = []
    for frame, weight in zip(ssim_map, centres):
        weight = weight if weight.sum() > 0 else np.ones_like(weight)
        values.append((frame * weight).sum() / weight.sum())
    return float(np.mean(values))


def delta_e2000(pred, target, mask=None) -> float:
    """Mean over frames of the mean CIEDE2000 on the mask (no scale fit; see `albedo_metrics`)."""
    p, t = _frames(pred), _frames(target)
    m = _mask(mask, p.shape) > 0.5                                            # [T,H,W]
    differences = colour.delta_e_2000(p[m], t[m])                           # every mask pixel of the clip at once
    per_frame = np.bincount(np.nonzero(m)[0], differences, minlength=p.shape[0]) / m.sum(axis=(1, 2))
    return float(per_frame.mean())


def steadiness(fitted, target, mask=None) -> dict[str, float]:
    """{"temporal", "flicker"} of a clip of > 1 frame ({} for an image), `fitted` already scale-fitted:
    "temporal" the RMS, over the pixels in the mask of both frames, of (fitted[t+1] − fitted[t]) −
    (target[t+1] − target[t]) — what changes between frames that should not, or does not that should;
    "flicker" the RMS over t and channels of the change of the mean error (fitted − target) on the mask
    from frame to frame — a clip that brightens and darkens against its truth."""
    p, t = _frames(fitted), _frames(target)
    if p.shape[0] < 2:
        return {}
    m = _mask(mask, p.shape)
    both = m[1:] * m[:-1]
    change = (p[1:] - p[:-1]) - (t[1:] - t[:-1])
    temporal = math.sqrt(float((both[..., None] * change ** 2).sum() / (3 * max(both.sum(), 1.0))))
    level = (m[..., None] * (p - t)).sum(axis=(1, 2)) / np.maximum(m.sum(axis=(1, 2)), 1.0)[:, None]   # [T,3]
    return {"temporal": temporal, "flicker": math.sqrt(float((np.diff(level, axis=0) ** 2).mean()))}


def protocol_metrics(pred, target, mask=None) -> dict[str, float]:
    """{"psnr", "ssim"} of pred against target after the per-channel scale fit on the mask; for a clip
    also its `steadiness` ("temporal", "flicker")."""
    return _fitted_metrics(scale_fit(pred, target, mask)[0], target, mask)


def _fitted_metrics(fitted, target, mask=None) -> dict[str, float]:
    """`protocol_metrics` of a prediction already scale-fitted."""
    return {"psnr": psnr(fitted, target, mask), "ssim": ssim(fitted, target, mask),
            **steadiness(fitted, target, mask)}


def protocol_psnr(pred, target, mask=None) -> float:
    """The protocol's PSNR alone (the "psnr" of `protocol_metrics`, without the SSIM's cost)."""
    return psnr(scale_fit(pred, target, mask)[0], target, mask)


def albedo_metrics(pred, target, mask=None) -> dict[str, float]:
    """`protocol_metrics` plus "delta_e2000" of the same scale-fitted prediction."""
    fitted, _ = scale_fit(pred, target, mask)
    return {**_fitted_metrics(fitted, target, mask), "delta_e2000": delta_e2000(fitted, target, mask)}
