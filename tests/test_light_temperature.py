"""The light's colour temperature: a white balance of the probe, the same for the preview and the model."""

import numpy as np
import pytest
import torch

from relight_core import lighting, preview
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from tests.factory import lighting_the_preview_shows, record_encoded_lighting


def test_planckian_locus_matches_reference_chromaticities():
    # CIE illuminant A is a 2856 K black body: xy (0.44757, 0.40745); 5000 K: (0.3451, 0.3516).
    np.testing.assert_allclose(lighting.planckian_xy(2856), (0.44757, 0.40745), atol=1e-3)
    np.testing.assert_allclose(lighting.planckian_xy(5000), (0.3451, 0.3516), atol=1e-3)


def test_neutral_changes_nothing_and_others_keep_the_brightness():
    probe = torch.rand(8, 16, 3) * 10
    assert torch.equal(lighting.white_balance(probe, lighting.NEUTRAL_KELVIN), probe)
    luminance = torch.tensor([0.2126, 0.7152, 0.0722])
    for kelvin in (2000, 3200, 5000, 8000, 12000):
        gains = lighting.light_gains(kelvin)
        assert float(gains @ luminance) == pytest.approx(1.0, abs=1e-5)
        grey = torch.ones(4, 8, 3)
        assert float((lighting.white_balance(grey, kelvin) @ luminance).mean()) == pytest.approx(1.0, abs=1e-5)


def test_lower_is_warmer_and_higher_is_cooler():
    warm, cool = lighting.light_gains(3200), lighting.light_gains(10000)
    assert warm[0] > warm[1] > warm[2]      # orange: more red than blue
    assert cool[2] > cool[1] > cool[0]      # blue
    # Monotone: the red/blue ratio falls as the temperature rises.
    ratios = [float(g[0] / g[2]) for g in map(lighting.light_gains, (2000, 3000, 4500, 6500, 9000, 15000))]
    assert ratios == sorted(ratios, reverse=True)


@pytest.mark.parametrize("kelvin", [0, 1000, 40000, float("nan"), float("inf"), "warm"])
def test_out_of_range_temperatures_are_one_sentence(kelvin):
    with pytest.raises(InputError, match="colour temperature"):
        lighting.adjust_light(torch.ones(4, 8, 3), 1.0, kelvin)


def test_adjust_light_cleans_scales_then_colours():
    probe = torch.tensor([[[1.0, 2.0, float("nan")], [float("inf"), 0.5, 0.25]]])
    out = lighting.adjust_light(probe, 2.0, 3000)
    expected = lighting.clean_hdr(probe, 2.0) * lighting.light_gains(3000)
    torch.testing.assert_close(out, expected.clamp(0, lighting.HDR_MAX))


def test_the_model_gets_the_light_the_preview_shows(monkeypatch):
    """Pinned like the rotation: the lighting the pipeline encodes is the preview's camera-frame lookup
    of `adjust_light(probe, intensity, temperature)`, at the same rotation."""
    relighter = Relighter.load("tiny", device="cpu")
    probe = torch.rand(32, 64, 3) * 4
    seen = record_encoded_lighting(monkeypatch)
    frames = np.random.default_rng(0).random((1, 32, 48, 3), dtype=np.float32)
    relighter.relight(RelightRequest(frames=frames, probe=probe, rotation=30.0, intensity=2.0, temperature=3200,
                                     steps=1, sampler="euler"))
    assert seen, "the pipeline encoded no lighting"
    expected = lighting_the_preview_shows(relighter, lighting.adjust_light(probe, 2.0, 3200), seen[0], 30.0)
    torch.testing.assert_close(seen[0], expected, rtol=1e-4, atol=1e-5)
    # ...and the colour really reached it: a neutral run encodes other light.
    seen.clear()
    relighter.relight(RelightRequest(frames=frames, probe=probe, rotation=30.0, intensity=2.0, steps=1,
                                     sampler="euler"))
    assert not torch.allclose(seen[0], expected)


def test_preview_balls_follow_the_temperature():
    config = preview.PreviewConfig(ball_size=64, mirror_resolution=48, diffuse_resolution=24)
    probe = torch.ones(16, 32, 3) * 0.5
    neutral = preview.render_preview(probe, 0.0, config=config).astype(float)
    warm = preview.render_preview(probe, 0.0, config=config, temperature=3000).astype(float)
    diffuse = (slice(24, 40), slice(64 + 24, 64 + 40))  # the centre of the matte ball
    assert abs(neutral[diffuse][..., 0].mean() - neutral[diffuse][..., 2].mean()) < 2  # grey light: grey ball
    assert warm[diffuse][..., 0].mean() > warm[diffuse][..., 2].mean() + 40            # warm light: orange ball
