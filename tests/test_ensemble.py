"""Ensembles (`ModelSpec.ensemble`, `RelightRequest.ensemble`): several samples averaged into one
result, every second one run on the mirror image under the mirrored light and flipped back; and each
sample's copies at half-token shifts (`ModelSpec.shift_average`), rolled back before the mean."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from relight_core.checkpoint import ModelSpec
from relight_core.dit import DiTConfig, JointDiT
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.tokenizer import build_tokenizer

PIXEL = {"type": "pixel", "patch": 8}


def _relighter(**spec_changes) -> Relighter:
    torch.manual_seed(0)
    config = DiTConfig(width=32, depth=1, num_heads=2, patch_spatial=1, patch_temporal=1, out_channels=192,
                       cross_attention=False, adaln_lora_dim=8)
    dit = JointDiT(config)
    torch.nn.init.normal_(dit.final_layer.linear.weight, std=0.05)   # offsets that depend on the inputs
    spec = ModelSpec(name="e", dit=config, tokenizer=PIXEL, chunk_frames=1, overlap_frames=0, size=32, steps=1,
                     lighting_size=8, residual=True, **spec_changes)
    return Relighter(spec, dit, build_tokenizer(PIXEL), precision="fp32")


def _probe() -> np.ndarray:
    """A probe brighter on one side, so that its mirror image differs."""
    probe = np.ones((16, 32, 3), np.float32)
    probe[:, :8] = 20.0
    return probe


def test_one_member_is_the_plain_sample_and_more_members_change_it():
    relighter = _relighter()
    frames = np.random.default_rng(1).random((1, 32, 32, 3)).astype(np.float32)
    request = RelightRequest(frames=frames, probe=_probe(), seed=5)
    plain = relighter.relight(request)
    one = relighter.relight(replace(request, ensemble=1))
    np.testing.assert_array_equal(one.relit, plain.relit)
    np.testing.assert_array_equal(one.albedo, plain.albedo)
    assert plain.info["ensemble"] == 1
    two = relighter.relight(replace(request, ensemble=2))
    assert two.info["ensemble"] == 2 and two.relit.shape == frames.shape and two.relit.dtype == np.float32
    assert np.abs(two.relit - plain.relit).mean() > 1e-4
    # The model's own default applies when the request does not say.
    by_default = _relighter(ensemble=2).relight(request)
    np.testing.assert_allclose(by_default.relit, two.relit, atol=1e-6)


def _built(relighter: Relighter, seed: int, members: int):
    """(frames, request, condition, mask, lighting) of `_members` for a random 32-px image under `_probe`."""
    frames = np.random.default_rng(seed).random((1, 32, 32, 3)).astype(np.float32)
    request = RelightRequest(frames=frames, probe=_probe())
    probe = relighter._prepared_probe(request)
    return (frames, request, *relighter._members(request, frames, None, probe, [request.rotation], None, members))


def _offsets(tok, patterns):
    """Latent offsets [entries,C,3,h,w] that decode to `patterns` [entries,3,1,H,W] in every clip."""
    return torch.stack([tok.encode(p[None])[0] for p in patterns]).repeat(1, 1, 3, 1, 1)


def test_the_mirrored_members_see_the_mirror_image_and_light_and_are_flipped_back():
    relighter = _relighter()
    tok = relighter.tokenizer
    frames, request, condition, mask, light = _built(relighter, 2, 3)
    assert condition.shape[0] == light.shape[0] == 3 and mask.shape[0] == 1
    t = condition.shape[2] // 3
    signed = torch.from_numpy(frames).permute(3, 0, 1, 2) * 2 - 1                     # (3, T, H, W)
    inputs = tok.decode(condition[:, :, :t])                                           # (3, 3, T, H, W)
    torch.testing.assert_close(inputs[0], signed, atol=1e-6, rtol=0)
    torch.testing.assert_close(inputs[1], signed.flip(-1), atol=1e-6, rtol=0)
    torch.testing.assert_close(inputs[2], inputs[0])
    # The light: radiance mirrored (u → 1 − u), env_dir (a direction per panorama pixel) unchanged.
    channels = light.shape[1] // 3
    ldr = tok.decode(light[:, :channels - 1])
    torch.testing.assert_close(ldr[1], ldr[0].flip(-1))
    assert not torch.allclose(ldr[1], ldr[0], atol=1e-3)
    torch.testing.assert_close(light[1, 2 * channels:], light[0, 2 * channels:])
    torch.testing.assert_close(light[2], light[0])

    # A model that proposes the offset `pattern` for the plain image and its mirror image for the
    # mirrored one: every member agrees once flipped back, so the mean is the pattern exactly.
    pattern = torch.from_numpy(np.random.default_rng(3).uniform(-0.2, 0.2, (3, 1, 32, 32)).astype(np.float32))

    def equivariant(x, sigma, **kwargs):
        return _offsets(tok, [pattern.flip(-1) if m % 2 else pattern for m in range(x.shape[0])]).to(x)

    relighter.denoiser = equivariant
    expected = np.clip(frames + pattern.permute(1, 2, 3, 0).numpy() / 2, 0, 1)
    for members in (2, 3):
        result = relighter.relight(replace(request, ensemble=members))
        np.testing.assert_allclose(result.relit, expected, atol=1e-5)
        np.testing.assert_allclose(result.albedo, expected, atol=1e-5)


def test_bad_ensemble_counts_are_refused_in_one_sentence(tmp_path):
    relighter = _relighter()
    frames = np.zeros((1, 32, 32, 3), np.float32)
    for bad in (0, 17, True, 2.5):
        with pytest.raises(InputError, match="ensemble takes a whole number of samples from 1 to 16"):
            relighter.relight(RelightRequest(frames=frames, probe=_probe(), ensemble=bad))
    data = json.loads(json.dumps(relighter.spec.to_json()))
    assert ModelSpec.from_json(data).ensemble == 1
    for bad in (0, "2", 99):
        with pytest.raises(InputError, match="config.json has ensemble"):
            ModelSpec.from_json({**data, "ensemble": bad})


def test_time_and_memory_estimates_count_the_members():
    relighter = _relighter()
    one = relighter.estimate_seconds(1, 64, 64, steps=2)
    four = relighter.estimate_seconds(1, 64, 64, steps=2, ensemble=4)
    assert four == pytest.approx(4 * one, rel=0.05)
    assert _relighter(ensemble=4).estimate_seconds(1, 64, 64, steps=2) == pytest.approx(four)
    host, model = relighter.memory_estimate(1, 64, 64)
    host4, model4 = relighter.memory_estimate(1, 64, 64, members=4)
    assert host4 == host and model4 == 4 * model


# -- copies at half-token shifts (`ModelSpec.shift_average`) ----------------------------------------------

SHIFTS = [(0, 0), (4, 4), (4, 0), (0, 4)]       # half of the pixel tokenizer's 8-px token


def test_shift_copies_see_the_frames_rolled_by_half_a_token_after_the_mirror():
    relighter = _relighter(shift_average=4)
    tok = relighter.tokenizer
    frames, request, condition, mask, light = _built(relighter, 4, 2)
    assert condition.shape[0] == light.shape[0] == 8 and mask.shape[0] == 1
    assert relighter.batch_members(2) == 8 and relighter.batch_members(None) == 4
    t = condition.shape[2] // 3
    signed = torch.from_numpy(frames).permute(3, 0, 1, 2) * 2 - 1                     # (3, T, H, W)
    inputs = tok.decode(condition[:, :, :t])
    for entry, (mirror, shift) in enumerate([(m, s) for m in (False, True) for s in SHIFTS]):
        seen = signed.flip(-1) if mirror else signed
        torch.testing.assert_close(inputs[entry], seen.roll(shift, dims=(-2, -1)), atol=1e-6, rtol=0)
        # the light follows the mirror only: a half-token shift does not turn the camera
        torch.testing.assert_close(light[entry], light[4 if mirror else 0])


def test_the_shift_average_undoes_each_shift_and_cancels_what_is_fixed_to_the_token_grid():
    relighter = _relighter(shift_average=4)
    tok = relighter.tokenizer
    frames = np.full((1, 32, 32, 3), 0.5, np.float32)
    request = RelightRequest(frames=frames, probe=_probe())
    variants = [(m, s) for m in (False, True) for s in SHIFTS]

    # A model that moves with the scene (proposes `pattern` shifted and mirrored as its input is): every
    # copy agrees once moved back, so the mean is the pattern exactly, borders included.
    pattern = torch.from_numpy(np.random.default_rng(5).uniform(-0.2, 0.2, (3, 1, 32, 32)).astype(np.float32))

    def equivariant(x, sigma, **kwargs):
        moved = [(pattern.flip(-1) if mirror else pattern).roll(shift, dims=(-2, -1))
                 for mirror, shift in variants[:x.shape[0]]]
        return _offsets(tok, moved).to(x)

    relighter.denoiser = equivariant
    expected = np.clip(frames + pattern.permute(1, 2, 3, 0).numpy() / 2, 0, 1)
    for members in (1, 2):
        result = relighter.relight(replace(request, ensemble=members))
        np.testing.assert_allclose(result.relit, expected, atol=1e-5)
        np.testing.assert_allclose(result.albedo, expected, atol=1e-5)

    # A seam fixed to the token grid (the top half of every 8-px token brighter), whatever the input:
    # one copy shows it; two copies, the second half a token down and right, cancel it wherever both count.
    # The shifted copy's first token row and column hold the strip its roll wrapped across the border next to
    # the scene's edge, so the 4 px at each edge of the frame keep the first copy's result.
    rows = (np.arange(32) % 8 < 4).astype(np.float32) * 0.2 - 0.1
    seam = torch.from_numpy(np.broadcast_to(rows[None, None, :, None], (3, 1, 32, 32)).copy())

    def gridded(x, sigma, **kwargs):
        return _offsets(tok, [seam] * x.shape[0]).to(x)

    one_copy = 0.5 + np.broadcast_to(rows[:, None], (32, 32)) / 2
    for copies in (1, 2):
        relighter = _relighter(shift_average=copies)
        relighter.denoiser = gridded
        relit = relighter.relight(request).relit[0, ..., 0]
        if copies == 1:
            np.testing.assert_allclose(relit, one_copy, atol=1e-5)
            continue
        np.testing.assert_allclose(relit[4:28, 4:28], 0.5, atol=1e-5)                      # seams cancelled
        edges = np.ones((32, 32), bool)
        edges[4:28, 4:28] = False
        np.testing.assert_allclose(relit[edges], one_copy[edges], atol=1e-5)


def test_bad_shift_averages_are_refused_in_one_sentence_and_estimates_count_the_copies():
    relighter = _relighter()
    data = json.loads(json.dumps(relighter.spec.to_json()))
    assert ModelSpec.from_json(data).shift_average == 1
    assert ModelSpec.from_json({**data, "shift_average": 4}).shift_average == 4
    for bad in (0, 3, 8, True, "2", 2.0):
        with pytest.raises(InputError, match="config.json has shift_average .* it takes 1, 2, 4"):
            ModelSpec.from_json({**data, "shift_average": bad})
    four = _relighter(shift_average=4)
    assert four.estimate_seconds(1, 64, 64, steps=2) == pytest.approx(4 * relighter.estimate_seconds(1, 64, 64, steps=2),
                                                                       rel=0.05)
    frames = np.zeros((1, 32, 32, 3), np.float32)
    assert four.relight(RelightRequest(frames=frames, probe=_probe())).info["ensemble"] == 1
