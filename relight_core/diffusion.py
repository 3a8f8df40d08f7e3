"""EDM maths and samplers: preconditioning, noise levels, the training loss, ODE solvers.

A *denoiser* is any callable `denoiser(x, sigma, **extra) -> x0` with `sigma` a [B] tensor; the
samplers know nothing else about the model. Wrappers compose: `EDMPrecond` turns a raw network
into a denoiser, `guided` adds classifier-free guidance, `ConditionedDenoiser` pins the given
(condition) clips. A schedule that ends at σ_min (`get_sigmas_karras`) ends with one more clean x0
evaluation there, as the released Cosmos sampler does; one that ends at 0 (`sampling_sigmas(...,
final_denoise=False)`, Karras et al. 2022, Alg. 1) lands its last step on the x0 of that step's evaluation
and needs no clean-up call. Every evaluation is reported through `callback` — previews live there.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import nn

from relight_core.dit import NUM_CLIPS  # [input | relit | albedo] along time

Denoiser = Callable[..., torch.Tensor]


def append_dims(x: torch.Tensor, ndim: int) -> torch.Tensor:
    """Append trailing singleton dims so `x` broadcasts against a tensor of `ndim` dims."""
    return x.reshape(x.shape + (1,) * (ndim - x.ndim))


#################################################################################
#                     Preconditioning (Karras et al. 2022, Table 1)             #
#################################################################################

def edm_scalings(sigma: torch.Tensor, sigma_data: float = 0.5):
    """EDM (c_skip, c_out, c_in, c_noise) for noise level σ."""
    sigma = torch.as_tensor(sigma)
    c_skip = sigma_data ** 2 / (sigma ** 2 + sigma_data ** 2)
    c_out = sigma * sigma_data / (sigma ** 2 + sigma_data ** 2).sqrt()
    c_in = 1 / (sigma ** 2 + sigma_data ** 2).sqrt()
    c_noise = 0.25 * sigma.log()
    return c_skip, c_out, c_in, c_noise


class EDMPrecond(nn.Module):
    """x0 = c_skip·x + c_out·F(c_in·x, c_noise, **cond) around any network F."""

    def __init__(self, net: Callable[..., torch.Tensor],
                 sigma_data: float = 0.5):   # Expected standard deviation of the training data.
        super().__init__()
        self.net = net
        self.sigma_data = sigma_data

    def forward(self, x: torch.Tensor, sigma: torch.Tensor, **cond) -> torch.Tensor:
        sigma = torch.as_tensor(sigma, dtype=torch.float32, device=x.device).expand(x.shape[0])  # (B,)
        c_skip, c_out, c_in, c_noise = (append_dims(c, x.ndim) for c in edm_scalings(sigma, self.sigma_data))
        f_x = self.net(c_in * x, c_noise.flatten(), **cond)
        return c_skip * x + c_out * f_x.to(x.dtype)


#################################################################################
#                          Noise levels and training loss                       #
#################################################################################

def get_sigmas_karras(n: int, sigma_min: float = 0.002, sigma_max: float = 80.0, rho: float = 7.0,
                      device=None) -> torch.Tensor:
    """n steps ⇒ n + 1 σ from sigma_max down to sigma_min (Karras et al. 2022, eq. 5; no trailing 0)."""
    ramp = torch.linspace(0, 1, n + 1, dtype=torch.float64, device=device)
    inv_max, inv_min = sigma_max ** (1 / rho), sigma_min ** (1 / rho)
    return (inv_max + ramp * (inv_min - inv_max)) ** rho


def sampling_sigmas(steps: int, final_denoise: bool = True, sigma_min: float = 0.002,
                    sigma_max: float = 80.0) -> torch.Tensor:
    """The σ a sampler walks for `steps` steps. With `final_denoise` (the released inference) the n + 1
    Karras σ down to σ_min, after which the sampler evaluates once more at σ_min to clean x0: n + 1
    network calls. Without it n Karras σ down to σ_min and then 0, the last step landing on its
    evaluation's x0 (EDM's own schedule): n calls. For one step that is a single call at σ_max, whose
    x0 the clean-up call at σ_min would change only by c_out(σ_min) ≈ 0.002 of the network's output."""
    if steps < 1:
        raise ValueError(f"sampling takes at least one step, not {steps}")
    if final_denoise:
        return get_sigmas_karras(steps, sigma_min, sigma_max)
    return torch.cat([get_sigmas_karras(steps - 1, sigma_min, sigma_max), torch.zeros(1, dtype=torch.float64)])


def calls_per_step(sampler: str = "res2ab") -> int:
    """Denoiser evaluations a step of `sampler` makes (no guidance): two for heun, one for the others."""
    return 2 if sampler == "heun" else 1


def network_calls(steps: int, final_denoise: bool = True, sampler: str = "res2ab") -> int:
    """Denoiser evaluations of one sampling run of `steps` steps (no guidance): `calls_per_step` a step (a
    heun step to 0 makes one), and the clean-up call with `final_denoise`."""
    per_step = calls_per_step(sampler)
    return per_step * steps + 1 if final_denoise else per_step * steps - (per_step - 1)


def sample_training_sigma(batch_size: int, p_mean: float = 0.0, p_std: float = 1.0,
                          generator: torch.Generator | None = None, device=None) -> torch.Tensor:
    """[B] training noise levels, ln σ ~ N(p_mean, p_std²) (EDM log-normal)."""
    noise = torch.randn(batch_size, generator=generator,
                        device=generator.device if generator is not None else None)
    return (p_mean + p_std * noise).exp().to(device)


def edm_loss(denoised: torch.Tensor, target: torch.Tensor, sigma: torch.Tensor,
             clip_weights: tuple[float, ...] = (0.0, 1.0, 0.1),
             condition_mask: torch.Tensor | None = None, sigma_data: float = 0.5) -> torch.Tensor:
    """λ(σ)-weighted MSE with one weight per time-third [input | relit | albedo]; conditions skipped.

    λ(σ) = (σ² + σd²)/(σ·σd)² (EDM). `condition_mask` [B,1,T,1,1] (1 = given frame) zeroes the loss
    on condition frames, as the released model does by pasting them into its prediction. Averaged
    over every element, like the released `loss_reduce="mean"`.
    """
    b, _, frames = denoised.shape[:3]
    clips = len(clip_weights)
    if frames % clips:
        raise ValueError(f"{frames} latent frames do not split into {clips} clips")
    weights = torch.tensor(clip_weights, dtype=denoised.dtype, device=denoised.device)
    weights = weights.repeat_interleave(frames // clips).view(1, 1, frames, 1, 1)   # (1, 1, T, 1, 1)
    if condition_mask is not None:
        weights = weights * (1 - condition_mask.to(denoised.dtype))                  # (B, 1, T, 1, 1)
    sigma = append_dims(torch.as_tensor(sigma, dtype=denoised.dtype, device=denoised.device).expand(b), 5)
    lam = (sigma ** 2 + sigma_data ** 2) / (sigma * sigma_data) ** 2                 # (B, 1, 1, 1, 1)
    return (lam * weights * (denoised - target) ** 2).mean()


#################################################################################
#                                    Samplers                                   #
#################################################################################

def _total(sigmas: torch.Tensor, sampler: str) -> int:
    """The evaluations `sampler` makes on `sigmas`: the clean-up call unless the schedule ends at 0."""
    return network_calls(len(sigmas) - 1, float(sigmas[-1]) > 0, sampler)


def _evaluate(denoiser, x, sigma, extra_args, callback, i, total):
    """One denoiser call at scalar σ, reported to `callback`."""
    sigma_b = x.new_full((x.shape[0],), float(sigma))
    denoised = denoiser(x, sigma_b, **extra_args)
    if callback is not None:
        callback({"i": i, "total": total, "sigma": float(sigma), "x": x, "denoised": denoised})
    return denoised


@torch.no_grad()
def sample_euler(denoiser: Denoiser, x: torch.Tensor, sigmas: torch.Tensor,
                 extra_args: dict | None = None, callback: Callable | None = None) -> torch.Tensor:
    """Euler on the probability-flow ODE (Karras et al. 2022, Alg. 1 without churn), then clean x0
    (no clean-up call where the schedule ends at 0: the last step lands on x0)."""
    extra_args = extra_args or {}
    steps, total = len(sigmas) - 1, _total(sigmas, "euler")
    for i in range(steps):
        sigma, sigma_next = float(sigmas[i]), float(sigmas[i + 1])
        denoised = _evaluate(denoiser, x, sigma, extra_args, callback, i, total)
        if sigma_next == 0:
            return denoised
        d = (x - denoised) / sigma                                       # dx/dσ
        x = x + d * (sigma_next - sigma)
    return _evaluate(denoiser, x, sigmas[-1], extra_args, callback, steps, total)


@torch.no_grad()
def sample_heun(denoiser: Denoiser, x: torch.Tensor, sigmas: torch.Tensor,
                extra_args: dict | None = None, callback: Callable | None = None) -> torch.Tensor:
    """Heun's 2nd-order method (Karras et al. 2022, Alg. 2 without churn), then clean x0 (where the
    schedule ends at 0 its last step is Euler's, landing on x0, as in Alg. 2)."""
    extra_args = extra_args or {}
    steps, total = len(sigmas) - 1, _total(sigmas, "heun")
    for i in range(steps):
        sigma, sigma_next = float(sigmas[i]), float(sigmas[i + 1])
        denoised = _evaluate(denoiser, x, sigma, extra_args, callback, 2 * i, total)
        if sigma_next == 0:
            return denoised
        d = (x - denoised) / sigma
        x_euler = x + d * (sigma_next - sigma)
        denoised_next = _evaluate(denoiser, x_euler, sigma_next, extra_args, callback, 2 * i + 1, total)
        d_next = (x_euler - denoised_next) / sigma_next
        x = x + (d + d_next) / 2 * (sigma_next - sigma)
    return _evaluate(denoiser, x, sigmas[-1], extra_args, callback, total - 1, total)


def _phi1(z: float) -> float:
    return math.expm1(z) / z


def _phi2(z: float) -> float:
    return (_phi1(z) - 1) / z


@torch.no_grad()
def sample_res2ab(denoiser: Denoiser, x: torch.Tensor, sigmas: torch.Tensor,
                  extra_args: dict | None = None, callback: Callable | None = None) -> torch.Tensor:
    """RES second-order multistep ("2ab", Zhang et al. 2023, arXiv:2308.02157), then clean x0.

    Exponential integrator in data-prediction form with λ = −ln σ and step h = λ_next − λ:
    x_next = e^{−h}·x + h·(b1·x0 + b2·x0_prev), c2 = (λ_prev − λ)/h, b2 = φ2(−h)/c2,
    b1 = φ1(−h) − b2. The first step, with no history, is the exact-x0 Euler step (b1 = φ1, b2 = 0).
    A step to σ = 0 (h → ∞) lands on its evaluation's x0, and no clean-up call follows.
    """
    extra_args = extra_args or {}
    steps, total = len(sigmas) - 1, _total(sigmas, "res2ab")
    previous = None                                                   # (x0, σ) of the last step
    for i in range(steps):
        sigma, sigma_next = float(sigmas[i]), float(sigmas[i + 1])
        denoised = _evaluate(denoiser, x, sigma, extra_args, callback, i, total)
        if sigma_next == 0:                                           # h → ∞: x lands on x0
            return denoised
        h = math.log(sigma / sigma_next)
        if previous is None:
            x = math.exp(-h) * x + h * _phi1(-h) * denoised
        else:
            denoised_prev, sigma_prev = previous
            c2 = math.log(sigma / sigma_prev) / h                        # negative: the past step
            b2 = _phi2(-h) / c2
            b1 = _phi1(-h) - b2
            x = math.exp(-h) * x + h * (b1 * denoised + b2 * denoised_prev)
        previous = (denoised, sigma)
    return _evaluate(denoiser, x, sigmas[-1], extra_args, callback, steps, total)


SAMPLERS: dict[str, Callable[..., torch.Tensor]] = {
    "res2ab": sample_res2ab,
    "euler": sample_euler,
    "heun": sample_heun,
}


#################################################################################
#                 Denoiser wrappers: condition clips and guidance               #
#################################################################################

class ConditionedDenoiser:
    """Feeds the given clips as clean latents and pastes them into every x0 (released inference).

    The released model corrupts condition frames with a fixed tiny noise (σ_aug = 0.001, one draw
    per sampling run) and scales them by c_in(σ_aug) rather than c_in(σ): the network always sees
    them as almost clean, whatever the current σ. That is reproduced here by handing the wrapped
    EDM denoiser x_cond · c_in(σ_aug) / c_in(σ) on those frames. The wrapped denoiser also receives
    `condition_mask` (the network's condition-mask channel is this same mask).
    Sampling σ must stay above `augment_sigma` (the default σ_min 0.002 does).
    With `residual=True` the frames to generate are handed over as offsets from the input clip and
    the input is added back to x0 (`residual_base`): EDM on relit − input and albedo − input.
    `residual_gain` (relit, albedo) scales the offset x0 of each generated clip before the input is
    added back: a calibration of a model whose offsets overshoot (`training.calibrate`); (1, 1) in
    training. A one-step schedule that ends at 0 gives exactly input + gain · (the network's offset); the
    clean-up call at σ_min of the released schedule applies the gain once more (input + gain² · offset,
    to c_out(σ_min) ≈ 0.002 of the network's output).
    """

    def __init__(self, denoiser: Denoiser,
                 condition_latent: torch.Tensor,    # [B,16,T,h,w] clean latents on condition frames
                 condition_mask: torch.Tensor,      # [B,1,T,1,1], 1 on condition frames
                 augment_sigma: float = 0.001,      # released condition_video_augment_sigma_in_inference
                 sigma_data: float = 0.5,
                 seed: int = 1,
                 residual: bool = False,            # relit/albedo diffused as offsets from the input
                 residual_gain: tuple[float, float] = (1.0, 1.0)):
        self.denoiser = denoiser
        self.residual = residual
        self.residual_gain = tuple(float(g) for g in residual_gain)
        self.condition_latent = condition_latent
        self.condition_mask = condition_mask
        self.augment_sigma = augment_sigma
        self.sigma_data = sigma_data
        generator = torch.Generator(device=condition_latent.device).manual_seed(seed)
        noise = torch.randn(condition_latent.shape, generator=generator,
                            device=condition_latent.device).to(condition_latent)
        self.augmented = condition_latent + augment_sigma * noise      # fixed for the whole run

    def __call__(self, x: torch.Tensor, sigma: torch.Tensor, **extra) -> torch.Tensor:
        given = self.condition_mask.bool()                                           # (B, 1, T, 1, 1)
        c_in = append_dims(edm_scalings(sigma, self.sigma_data)[2], x.ndim)           # (B, 1, 1, 1, 1)
        c_in_augment = edm_scalings(torch.tensor(self.augment_sigma), self.sigma_data)[2]
        x_cond = self.augmented.to(x.dtype) * (c_in_augment / c_in)
        base = self.residual_base(x.dtype) if self.residual else None
        if base is not None:
            x = x - base
        x0 = self.denoiser(torch.where(given, x_cond, x), sigma, condition_mask=self.condition_mask, **extra)
        if base is not None:
            if self.residual_gain != (1.0, 1.0):
                x0 = x0 * self._gain(x0)
            x0 = x0 + base
        return torch.where(given, self.condition_latent.to(x0.dtype), x0)

    def _gain(self, x0: torch.Tensor) -> torch.Tensor:
        """[1,1,3t,1,1]: 1 on the input clip, the relit and albedo gains on their clips."""
        t = x0.shape[2] // NUM_CLIPS
        gains = torch.ones(NUM_CLIPS, dtype=x0.dtype, device=x0.device)
        gains[1:] = torch.tensor(self.residual_gain, dtype=x0.dtype, device=x0.device)
        return gains.repeat_interleave(t).view(1, 1, -1, 1, 1)

    def residual_base(self, dtype: torch.dtype) -> torch.Tensor:
        """[input | input | input] on the frames to generate, 0 elsewhere: a residual model diffuses
        relit − input and albedo − input (EDM on the offset), so "copy the input" is its zero output
        and the input's detail is kept exactly; the input clip itself is always a condition."""
        frames = self.condition_latent.shape[2]
        if frames % NUM_CLIPS:
            raise ValueError(f"{frames} latent frames do not split into {NUM_CLIPS} clips")
        source = self.condition_latent[:, :, :frames // NUM_CLIPS]                 # (B, C, t, h, w)
        base = source.repeat(1, 1, NUM_CLIPS, 1, 1).to(dtype)                       # (B, C, 3t, h, w)
        return base * (1 - self.condition_mask.to(dtype))


def guided(denoiser: Denoiser, cond_args: dict, uncond_args: dict, guidance: float) -> Denoiser:
    """Classifier-free guidance x0 = cond + w·(cond − uncond) (released form); w = 0 runs cond only."""
    if guidance == 0:
        def conditional(x, sigma, **extra):
            return denoiser(x, sigma, **cond_args, **extra)
        return conditional

    def combined(x, sigma, **extra):
        cond = denoiser(x, sigma, **cond_args, **extra)
        uncond = denoiser(x, sigma, **uncond_args, **extra)
        return cond + guidance * (cond - uncond)
    return combined
