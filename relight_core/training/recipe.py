"""The UniRelight training recipe on latents: conditioning modes, lighting dropout, the EDM loss.

Per sample (paper §3.3, released `model_relight.py`):

* ``default``     (~70%): input clip given → denoise relit + albedo;
* ``albedo_only`` (~12%): input latent zeroed, albedo given → forward rendering from albedo
  (released ``gt_albedo``: the first and last thirds are both marked as conditions);
* ``both``        (~18%): input and albedo given → relit only.

Samples without an input clip (auto-labelled single-illumination videos) always train as
``albedo_only``. Independently, all three lighting latents and their masks are zeroed in ~10% of
samples (and always for samples without a probe), which trains the no-probe "random illumination"
mode and classifier-free guidance. Our addition: in ~10% of video samples the first latent frame of
the relit and albedo clips is also given, which is how `Relighter` continues a long video chunk by
chunk. Condition clips enter the network exactly as at inference (`ConditionedDenoiser`: clean
latent plus σ = 0.001 noise), so training and sampling agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import torch

from relight_core.diffusion import (ConditionedDenoiser, EDMPrecond, edm_loss, get_sigmas_karras,
                                    sample_training_sigma)
from relight_core.dit import NUM_CLIPS, JointDiT, network  # network: the one DiT-as-denoiser adapter

MODES = ("default", "albedo_only", "both")
SIGMA_MAX = float(get_sigmas_karras(1)[0])  # where every sampling run starts (80)


@dataclass(frozen=True)
class Recipe:
    """Probabilities and constants of the conditioning mix and the loss."""

    p_albedo_only: float = 0.12          # input dropped, albedo is the only condition
    p_both: float = 0.18                 # input and albedo both given
    p_drop_lighting: float = 0.10        # all three lighting latents + masks zeroed
    p_continue: float = 0.10             # video only: first latent frame of relit/albedo given
    clip_weights: tuple[float, float, float] = (0.0, 1.0, 0.1)   # [input | relit | albedo]
    p_mean: float = 0.0                  # ln σ ~ N(p_mean, p_std²)
    p_std: float = 1.0
    augment_sigma: float = 0.001         # noise on condition clips (released inference value)
    p_sigma_max: float = 0.0             # share trained at σ_max = 80, the one-step sampler's only call
    residual: bool = False               # relit/albedo as offsets from the input (ModelSpec.residual)


@dataclass
class Example:
    """One assembled training batch: clean target x0, which frames are given, and the lighting."""

    x0: torch.Tensor               # [B,16,3t,h,w] = [input | relit | albedo]; input zeroed if dropped
    condition_mask: torch.Tensor   # [B,1,3t,1,1], 1 on given latent frames
    lighting: torch.Tensor         # [B,51,t,h,w], zeros (masks too) where lighting is dropped
    modes: torch.Tensor            # [B] int, index into MODES
    lighting_dropped: torch.Tensor  # [B] bool


def sample_modes(batch: int, recipe: Recipe, generator: torch.Generator,
                 has_input: torch.Tensor | None = None) -> torch.Tensor:
    """[B] mode indices into MODES; samples with no input clip are always albedo_only."""
    u = torch.rand(batch, generator=generator, device=generator.device)
    modes = torch.zeros(batch, dtype=torch.long, device=generator.device)
    modes[u < recipe.p_albedo_only + recipe.p_both] = MODES.index("both")
    modes[u < recipe.p_albedo_only] = MODES.index("albedo_only")
    if has_input is not None:
        modes[~has_input.bool().to(modes.device)] = MODES.index("albedo_only")
    return modes


def make_example(input_latent: torch.Tensor, relit: torch.Tensor, albedo: torch.Tensor,
                 lighting: torch.Tensor, recipe: Recipe, generator: torch.Generator,
                 has_input: torch.Tensor | None = None, has_lighting: torch.Tensor | None = None) -> Example:
    """Draw modes and dropouts for a batch of latents ([B,16,t,h,w] each, lighting [B,51,t,h,w])."""
    b, _, t = relit.shape[:3]
    modes = sample_modes(b, recipe, generator, has_input)
    device = generator.device                  # random draws on the generator's device (CPU or GPU)
    dropped = torch.rand(b, generator=generator, device=device) < recipe.p_drop_lighting
    if has_lighting is not None:
        dropped |= ~has_lighting.bool().to(device)
    continued = (torch.rand(b, generator=generator, device=device) < recipe.p_continue) & (t > 1)

    modes, dropped, continued = modes.to(relit.device), dropped.to(relit.device), continued.to(relit.device)
    keep_input = (modes != MODES.index("albedo_only")).to(relit.dtype).view(b, 1, 1, 1, 1)
    x0 = torch.cat([input_latent * keep_input, relit, albedo], dim=2)                # (B, 16, 3t, h, w)
    mask = torch.zeros(b, 1, NUM_CLIPS * t, 1, 1, dtype=relit.dtype, device=relit.device)  # (B, 1, 3t, 1, 1)
    mask[:, :, :t] = 1.0                               # the input clip is always a condition (zeroed or not)
    mask[modes != MODES.index("default"), :, 2 * t:] = 1.0                            # albedo given
    mask[continued, :, t] = 1.0                        # first relit latent frame given (chunk continuation)
    mask[continued, :, 2 * t] = 1.0
    lighting = lighting * (~dropped).to(lighting.dtype).view(b, 1, 1, 1, 1)           # (B, 51, t, h, w)
    return Example(x0, mask, lighting, modes, dropped)


def denoising_loss(dit: JointDiT, example: Example, recipe: Recipe, generator: torch.Generator
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """EDM loss of one batch: σ ~ log-normal, x = x0 + σ·n, conditions pinned; returns (loss, σ)."""
    x0 = example.x0
    device = generator.device
    sigma = sample_training_sigma(x0.shape[0], recipe.p_mean, recipe.p_std, generator)              # (B,)
    if recipe.p_sigma_max > 0:
        at_max = torch.rand(x0.shape[0], generator=generator, device=device) < recipe.p_sigma_max
        sigma = torch.where(at_max, torch.full_like(sigma, SIGMA_MAX), sigma)
    sigma = sigma.to(x0.device)
    noise = torch.randn(x0.shape, generator=generator, device=device).to(x0.device)          # (B, 16, 3t, h, w)
    seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator, device=device))
    denoiser = ConditionedDenoiser(EDMPrecond(partial(network, dit)), x0, example.condition_mask,
                                   augment_sigma=recipe.augment_sigma, seed=seed, residual=recipe.residual)
    denoised = denoiser(x0 + sigma.view(-1, 1, 1, 1, 1) * noise, sigma, lighting=example.lighting)
    loss = edm_loss(denoised, x0, sigma, recipe.clip_weights, condition_mask=example.condition_mask)
    return loss, sigma
