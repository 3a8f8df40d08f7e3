"""EDM formulas, noise schedules, the per-clip loss, samplers and denoiser wrappers."""

import math

import pytest
import torch

from relight_core.diffusion import (
    SAMPLERS, ConditionedDenoiser, EDMPrecond, edm_loss, edm_scalings, get_sigmas_karras, guided, network_calls,
    sample_euler, sample_heun, sample_res2ab, sample_training_sigma, sampling_sigmas,
)


class Counting:
    """A denoiser that counts its calls and records its inputs."""

    def __init__(self, fn):
        self.fn, self.calls = fn, []

    def __call__(self, x, sigma, **extra):
        self.calls.append((x.clone(), sigma.clone(), extra))
        return self.fn(x, sigma, **extra)


def gaussian_denoiser(mu, s):
    """Exact E[x0 | x] for data N(mu, s²) per element."""
    def denoise(x, sigma, **_):
        sigma = sigma.view(-1, *([1] * (x.ndim - 1)))
        return mu + s ** 2 / (s ** 2 + sigma ** 2) * (x - mu)
    return denoise


def gaussian_exact(x_t, mu, s, sigma_t, sigma_end):
    """Probability-flow ODE solution at sigma_end, then the exact denoiser there."""
    x_end = mu + (x_t - mu) * math.sqrt(s ** 2 + sigma_end ** 2) / math.sqrt(s ** 2 + sigma_t ** 2)
    return mu + s ** 2 / (s ** 2 + sigma_end ** 2) * (x_end - mu)


# ---------------------------------------------------------------- preconditioning


@pytest.mark.parametrize("sigma, expected", [
    (0.5, (0.5, 0.35355339, 1.41421356, -0.17328680)),
    (1.0, (0.2, 0.44721360, 0.89442719, 0.0)),
    (80.0, (3.9060974e-5, 0.49999023, 0.012499756, 1.09550666)),
])
def test_edm_scalings_match_hand_computed(sigma, expected):
    got = edm_scalings(torch.tensor(sigma, dtype=torch.float64))
    for value, want in zip(got, expected):
        assert float(value) == pytest.approx(want, rel=1e-6, abs=1e-9)


def test_edm_precond_feeds_scaled_input_and_combines():
    seen = {}

    def net(x_in, c_noise, **cond):
        seen.update(x_in=x_in, c_noise=c_noise, cond=cond)
        return torch.full_like(x_in, 2.0)

    x = torch.randn(2, 3, 4)
    sigma = torch.tensor([0.5, 80.0])
    out = EDMPrecond(net)(x, sigma, lighting="L")
    c_skip, c_out, c_in, c_noise = edm_scalings(sigma)
    torch.testing.assert_close(seen["x_in"], c_in.view(2, 1, 1) * x)
    torch.testing.assert_close(seen["c_noise"], c_noise)
    assert seen["cond"] == {"lighting": "L"}
    torch.testing.assert_close(out, c_skip.view(2, 1, 1) * x + c_out.view(2, 1, 1) * 2.0)


# ---------------------------------------------------------------- noise levels and loss


def test_karras_sigmas_endpoints_and_monotonic():
    sigmas = get_sigmas_karras(35)
    assert len(sigmas) == 36
    assert float(sigmas[0]) == pytest.approx(80.0)
    assert float(sigmas[-1]) == pytest.approx(0.002)
    assert bool((sigmas[1:] < sigmas[:-1]).all())
    # rho = 1 is a linear ramp
    torch.testing.assert_close(get_sigmas_karras(4, 1.0, 5.0, rho=1.0),
                               torch.tensor([5.0, 4.0, 3.0, 2.0, 1.0], dtype=torch.float64))


def test_training_sigma_is_log_normal():
    sigma = sample_training_sigma(20000, generator=torch.Generator().manual_seed(0))
    assert (sigma > 0).all()
    assert float(sigma.log().mean()) == pytest.approx(0.0, abs=0.03)
    assert float(sigma.log().std()) == pytest.approx(1.0, abs=0.03)
    shifted = sample_training_sigma(20000, p_mean=-1.0, p_std=0.5, generator=torch.Generator().manual_seed(0))
    assert float(shifted.log().mean()) == pytest.approx(-1.0, abs=0.02)


def _loss_with_error_in(clip, **kwargs):
    target = torch.zeros(2, 16, 6, 4, 4)
    denoised = target.clone()
    denoised[:, :, 2 * clip:2 * clip + 2] = 1.0                # unit error on one clip (t = 2)
    return float(edm_loss(denoised, target, torch.tensor([1.0, 1.0]), **kwargs))


def test_edm_loss_per_clip_weights():
    lam = (1.0 + 0.25) / (1.0 * 0.5) ** 2                       # λ(σ=1) = 5
    third = 1 / 3                                              # error covers one third of elements
    assert _loss_with_error_in(0) == 0.0                       # input clip is a condition
    assert _loss_with_error_in(1) == pytest.approx(lam * third)
    assert _loss_with_error_in(2) == pytest.approx(0.1 * lam * third)
    assert _loss_with_error_in(0, clip_weights=(1.0, 1.0, 1.0)) == pytest.approx(lam * third)


def test_edm_loss_skips_condition_frames_and_weights_sigma():
    mask = torch.zeros(2, 1, 6, 1, 1)
    mask[:, :, 4:] = 1.0                                       # albedo given (forward rendering)
    assert _loss_with_error_in(2, condition_mask=mask) == 0.0
    target = torch.zeros(1, 1, 3, 1, 1)
    denoised = torch.ones(1, 1, 3, 1, 1)
    sigma = torch.tensor([2.0])
    want = (4 + 0.25) / (2 * 0.5) ** 2 * (0 + 1 + 0.1) / 3
    assert float(edm_loss(denoised, target, sigma)) == pytest.approx(want)


# ---------------------------------------------------------------- samplers


@pytest.mark.parametrize("name, evals", [("euler", 1), ("res2ab", 1), ("heun", 2)])
def test_sampler_call_count_and_callback(name, evals):
    steps = 7
    denoiser = Counting(lambda x, sigma, **_: torch.zeros_like(x))
    reports = []
    SAMPLERS[name](denoiser, torch.randn(2, 3), get_sigmas_karras(steps), callback=reports.append)
    assert len(denoiser.calls) == evals * steps + 1 == network_calls(steps, sampler=name)
    assert len(reports) == len(denoiser.calls)
    assert [r["i"] for r in reports] == list(range(len(reports)))
    assert all(r["total"] == len(reports) for r in reports)
    assert set(reports[0]) == {"i", "total", "sigma", "x", "denoised"}
    assert reports[0]["sigma"] == pytest.approx(80.0)
    assert reports[-1]["sigma"] == pytest.approx(0.002)  # the final clean x0 at the last σ


def test_a_schedule_without_the_clean_up_call_ends_at_zero():
    torch.testing.assert_close(sampling_sigmas(1, final_denoise=False), torch.tensor([80.0, 0.0], dtype=torch.float64))
    with_call, without = sampling_sigmas(6), sampling_sigmas(6, final_denoise=False)
    torch.testing.assert_close(with_call, get_sigmas_karras(6))
    assert len(without) == 7 and without[-1] == 0 and without[-2] == pytest.approx(0.002)
    torch.testing.assert_close(without[:-1], get_sigmas_karras(5))
    assert (network_calls(6), network_calls(6, final_denoise=False)) == (7, 6)
    with pytest.raises(ValueError):
        sampling_sigmas(0, final_denoise=False)


@pytest.mark.parametrize("name, calls", [("euler", 5), ("res2ab", 5), ("heun", 9)])
def test_samplers_land_on_the_last_x0_where_the_schedule_ends_at_zero(name, calls):
    # x0 moves with σ so that "the last evaluation's x0" and "one more call at σ_min" differ
    denoiser = Counting(lambda x, sigma, **_: 0.1 * x + sigma.view(-1, 1))
    reports = []
    x = 80.0 * torch.randn(2, 3, generator=torch.Generator().manual_seed(3))
    out = SAMPLERS[name](denoiser, x, sampling_sigmas(5, final_denoise=False), callback=reports.append)
    assert len(denoiser.calls) == len(reports) == calls == network_calls(5, final_denoise=False, sampler=name)
    assert all(r["total"] == calls for r in reports) and [r["i"] for r in reports] == list(range(calls))
    assert all(r["sigma"] > 0 for r in reports)                 # the network never sees σ = 0
    assert torch.equal(out, reports[-1]["denoised"])
    assert reports[-1]["sigma"] == pytest.approx(0.002)


@pytest.mark.parametrize("sampler", [sample_euler, sample_heun, sample_res2ab])
def test_samplers_without_the_clean_up_call_still_converge(sampler):
    mu, s = 0.4, 0.5
    x = 80.0 * torch.randn(64, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    exact = gaussian_exact(x, mu, s, 80.0, 0.0)
    errors = [float((sampler(gaussian_denoiser(mu, s), x, sampling_sigmas(n, final_denoise=False)) - exact).abs().max())
              for n in (8, 32, 128)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.05


def test_one_step_residual_gain_applies_once_without_the_clean_up_call_and_twice_with_it():
    condition, mask = _conditioned_setup()
    offset = 0.3 * torch.randn(1, 16, 6, 2, 2, generator=torch.Generator().manual_seed(4))
    net = EDMPrecond(lambda x_in, c_noise, **_: offset / 0.5)    # F such that x0 ≈ offset at σ = 80
    gain = (0.8, 0.5)
    x = 80.0 * torch.randn(1, 16, 6, 2, 2, generator=torch.Generator().manual_seed(5))
    base = condition[:, :, :2].repeat(1, 1, 3, 1, 1)

    def sample(final_denoise, gains):
        den = ConditionedDenoiser(net, condition, mask, residual=True, residual_gain=gains)
        return sample_res2ab(den, x, sampling_sigmas(1, final_denoise))

    x0_80 = EDMPrecond(lambda x_in, c_noise, **_: offset / 0.5)(x - base, torch.tensor([80.0]))
    once = sample(False, gain)
    for clip, g in ((slice(2, 4), gain[0]), (slice(4, 6), gain[1])):
        torch.testing.assert_close(once[:, :, clip], base[:, :, clip] + g * x0_80[:, :, clip])   # exactly
    twice = sample(True, gain)
    squared = sample(False, tuple(g * g for g in gain))
    torch.testing.assert_close(twice[:, :, 2:], squared[:, :, 2:], atol=1e-2, rtol=0)   # c_out(σ_min)·F apart
    assert (twice[:, :, 4:] - once[:, :, 4:]).abs().max() > 0.05                        # not the same gain


@pytest.mark.parametrize("sampler", [sample_euler, sample_heun, sample_res2ab])
def test_samplers_pass_extra_args(sampler):
    denoiser = Counting(lambda x, sigma, **_: torch.zeros_like(x))
    sampler(denoiser, torch.randn(1, 2), get_sigmas_karras(3), extra_args={"lighting": 7})
    assert all(extra == {"lighting": 7} for _, _, extra in denoiser.calls)


@pytest.mark.parametrize("sampler", [sample_euler, sample_heun, sample_res2ab])
def test_samplers_reach_a_point_distribution(sampler):
    mu = torch.tensor([[0.3, -0.7, 1.1]])
    denoiser = gaussian_denoiser(mu, 0.0)                      # data = a single point
    x = 80.0 * torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
    out = sampler(denoiser, x, get_sigmas_karras(10))
    torch.testing.assert_close(out, mu.expand(4, 3))


@pytest.mark.parametrize("sampler", [sample_euler, sample_heun, sample_res2ab])
def test_samplers_converge_on_gaussian_data(sampler):
    mu, s = 0.4, 0.5
    x = 80.0 * torch.randn(64, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    exact = gaussian_exact(x, mu, s, 80.0, 0.002)
    errors = [float((sampler(gaussian_denoiser(mu, s), x, get_sigmas_karras(n)) - exact).abs().max())
              for n in (8, 32, 128)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.05


def test_res2ab_more_accurate_than_euler_at_working_step_counts():
    mu, s = -0.2, 0.5
    x = 80.0 * torch.randn(256, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    exact = gaussian_exact(x, mu, s, 80.0, 0.002)
    # 35 is the released step count. (At ~10 steps the multistep history spans very uneven
    # σ-steps and RES 2ab is no better than Euler on this toy problem.)
    for steps in (20, 35):
        sigmas = get_sigmas_karras(steps)
        err_euler = float((sample_euler(gaussian_denoiser(mu, s), x, sigmas) - exact).abs().mean())
        err_res = float((sample_res2ab(gaussian_denoiser(mu, s), x, sigmas) - exact).abs().mean())
        assert err_res < 0.6 * err_euler


def test_res2ab_is_exact_for_constant_x0():
    # With a constant x0 the data-prediction ODE solution is x0 + (σ'/σ)(x − x0) at every step.
    mu = torch.tensor([[1.5]])
    reports = []
    x = torch.tensor([[10.0]])
    sample_res2ab(gaussian_denoiser(mu, 0.0), x, get_sigmas_karras(5), callback=reports.append)
    for r in reports:
        want = 1.5 + (r["sigma"] / 80.0) * (10.0 - 1.5)
        assert float(r["x"]) == pytest.approx(want, rel=1e-6)


# ---------------------------------------------------------------- wrappers


def test_guidance_zero_never_evaluates_unconditional():
    denoiser = Counting(lambda x, sigma, lighting, **_: x * 0 + lighting)
    den = guided(denoiser, {"lighting": 1.0}, {"lighting": 0.0}, guidance=0.0)
    sample_res2ab(den, torch.randn(1, 4), get_sigmas_karras(6))
    assert len(denoiser.calls) == 7
    assert all(extra["lighting"] == 1.0 for _, _, extra in denoiser.calls)


def test_guidance_evaluates_both_branches_with_released_formula():
    denoiser = Counting(lambda x, sigma, lighting, **_: x * 0 + lighting)
    den = guided(denoiser, {"lighting": 1.0}, {"lighting": 0.25}, guidance=2.0)
    out = den(torch.zeros(1, 4), torch.tensor([1.0]))
    torch.testing.assert_close(out, torch.full((1, 4), 1.0 + 2.0 * (1.0 - 0.25)))
    denoiser.calls.clear()
    sample_euler(den, torch.randn(1, 4), get_sigmas_karras(6))
    assert len(denoiser.calls) == 2 * (6 + 1)


def _conditioned_setup():
    torch.manual_seed(0)
    condition = torch.randn(1, 16, 6, 2, 2)
    mask = torch.zeros(1, 1, 6, 1, 1)
    mask[:, :, :2] = 1.0                                          # the input clip is given
    condition[:, :, 2:] = 0.0
    return condition, mask


def test_conditioned_denoiser_pins_condition_clips_exactly():
    condition, mask = _conditioned_setup()
    inner = Counting(lambda x, sigma, **_: torch.randn_like(x))
    den = ConditionedDenoiser(inner, condition, mask)
    reports = []
    out = sample_res2ab(den, 80.0 * torch.randn(1, 16, 6, 2, 2), get_sigmas_karras(5), callback=reports.append)
    assert torch.equal(out[:, :, :2], condition[:, :, :2])
    assert all(torch.equal(r["denoised"][:, :, :2], condition[:, :, :2]) for r in reports)
    assert not torch.equal(out[:, :, 2:], condition[:, :, 2:])   # generated clips are the model's
    assert all(torch.equal(extra["condition_mask"], mask) for _, _, extra in inner.calls)


def test_conditioned_denoiser_feeds_almost_clean_condition_at_any_sigma():
    condition, mask = _conditioned_setup()
    inner = Counting(lambda x, sigma, **_: torch.zeros_like(x))
    den = ConditionedDenoiser(inner, condition, mask, augment_sigma=0.001)
    x = 80.0 * torch.randn(1, 16, 6, 2, 2)
    for sigma in (80.0, 1.0, 0.01):
        den(x, torch.tensor([sigma]))
        x_in = inner.calls[-1][0]
        c_in = 1 / math.sqrt(sigma ** 2 + 0.25)
        # After EDMPrecond multiplies by c_in(σ), the network sees the condition at c_in(σ_aug).
        seen = x_in[:, :, :2] * c_in
        torch.testing.assert_close(seen, condition[:, :, :2] / math.sqrt(0.001 ** 2 + 0.25), atol=0.01, rtol=0)
        assert not torch.equal(x_in[:, :, :2] * c_in, condition[:, :, :2] / math.sqrt(0.001 ** 2 + 0.25))
        assert torch.equal(x_in[:, :, 2:], x[:, :, 2:])       # generated clips untouched


def test_residual_denoiser_with_a_zero_network_copies_the_input_into_relit_and_albedo():
    condition, mask = _conditioned_setup()
    den = ConditionedDenoiser(EDMPrecond(lambda x, c_noise, **_: torch.zeros_like(x)), condition, mask, residual=True)
    out = sample_res2ab(den, 80.0 * torch.randn(1, 16, 6, 2, 2), get_sigmas_karras(1))
    for clip in (slice(2, 4), slice(4, 6)):                   # relit and albedo = the input clip
        torch.testing.assert_close(out[:, :, clip], condition[:, :, :2], atol=0.05, rtol=0)  # c_skip·noise
    assert torch.equal(out[:, :, :2], condition[:, :, :2])
    plain = ConditionedDenoiser(EDMPrecond(lambda x, c_noise, **_: torch.zeros_like(x)), condition, mask)
    out = sample_res2ab(plain, 80.0 * torch.randn(1, 16, 6, 2, 2), get_sigmas_karras(1))
    assert out[:, :, 2:].abs().max() < 0.05                   # a plain model's zero output is zero


def test_residual_denoiser_sees_the_offset_and_adds_the_input_back():
    condition, mask = _conditioned_setup()
    mask[:, :, 4] = 1.0                                       # first albedo frame given: no offset there
    condition[:, :, 4] = 3.0
    inner = Counting(lambda x, sigma, **_: x)                 # returns what it was handed
    den = ConditionedDenoiser(inner, condition, mask, residual=True)
    x = torch.randn(1, 16, 6, 2, 2)
    out = den(x, torch.tensor([1.0]))
    seen = inner.calls[-1][0]
    torch.testing.assert_close(seen[:, :, 2:4], x[:, :, 2:4] - condition[:, :, :2])
    torch.testing.assert_close(seen[:, :, 5], x[:, :, 5] - condition[:, :, 1])
    torch.testing.assert_close(out[:, :, 2:4], x[:, :, 2:4])   # offset in, offset + input out
    assert torch.equal(out[:, :, 4], condition[:, :, 4])       # the given frame is pinned as before


def test_residual_gain_scales_each_generated_clips_offset_and_nothing_else():
    condition, mask = _conditioned_setup()
    mask[:, :, 4] = 1.0                                       # a given albedo frame stays pinned
    condition[:, :, 4] = 3.0
    offset = torch.randn(1, 16, 6, 2, 2)
    inner = lambda x, sigma, **_: offset                      # noqa: E731 — the network's x0 offset
    plain = ConditionedDenoiser(inner, condition, mask, residual=True)
    gained = ConditionedDenoiser(inner, condition, mask, residual=True, residual_gain=(0.5, 0.25))
    x, sigma = torch.randn(1, 16, 6, 2, 2), torch.tensor([80.0])
    a, b = plain(x, sigma), gained(x, sigma)
    base = condition[:, :, :2]
    torch.testing.assert_close(b[:, :, 2:4] - base, 0.5 * (a[:, :, 2:4] - base))      # relit: half the offset
    torch.testing.assert_close(b[:, :, 5] - base[:, :, 1], 0.25 * (a[:, :, 5] - base[:, :, 1]))  # albedo
    assert torch.equal(b[:, :, :2], condition[:, :, :2]) and torch.equal(b[:, :, 4], condition[:, :, 4])


def test_tiny_joint_model_samples_end_to_end():
    from relight_core.dit import DIT_PRESETS, JointDiT, assemble_inputs

    torch.manual_seed(0)
    dit = JointDiT(DIT_PRESETS["tiny"])
    with torch.no_grad():
        for p in dit.parameters():
            p.normal_(std=0.1)

    def net(x_in, c_noise, lighting, condition_mask):
        b, _, frames, h, w = x_in.shape
        return dit(assemble_inputs(x_in, condition_mask.expand(b, 1, frames, h, w), lighting, None), c_noise)

    condition, mask = _conditioned_setup()
    lighting = torch.randn(1, 51, 2, 2, 2)
    for guidance, calls in ((0.0, 5), (1.5, 10)):
        counted = Counting(EDMPrecond(net))
        den = ConditionedDenoiser(guided(counted, {"lighting": lighting}, {"lighting": lighting * 0}, guidance),
                                  condition, mask)
        out = sample_res2ab(den, 80.0 * torch.randn(1, 16, 6, 2, 2), get_sigmas_karras(4))
        assert out.shape == (1, 16, 6, 2, 2) and torch.isfinite(out).all()
        assert torch.equal(out[:, :, :2], condition[:, :, :2])
        assert len(counted.calls) == calls
