"""The light's colour temperature: a white balance of the probe, the same for the preview and the model."""

import numpy as np
import pytest
import torch

from relight_core import colour, lighting, preview
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


def test_a_black_body_light_set_to_another_temperature_has_that_black_bodys_colour():
    """The gains are colour-science's CCT → xy → linear sRGB: light of the neutral black body (6500 K)
    white-balanced to `kelvin` has exactly the chromaticity of the Planckian locus at `kelvin`."""
    science = colour.colour_science()
    neutral = colour.xy_to_linear_srgb(lighting.planckian_xy(lighting.NEUTRAL_KELVIN))
    for kelvin in (2000, 3200, 5000, 9000, 20000):
        light = neutral * lighting.light_gains(kelvin).double().numpy()
        xy = science.XYZ_to_xy(science.RGB_to_XYZ(light, "sRGB"))
        np.testing.assert_allclose(xy, lighting.planckian_xy(kelvin), atol=1e-4)


def test_gains_are_vectorised_over_temperatures_and_tints():
    kelvins = [2000.0, 3200.0, 6500.0, 12000.0]
    together = lighting.light_gains(kelvins)
    assert together.shape == (4, 3) and together.dtype == torch.float32
    for row, kelvin in zip(together, kelvins):
        torch.testing.assert_close(row, lighting.light_gains(kelvin))
    assert torch.equal(together[2], torch.ones(3))
    assert lighting.light_gains([6500, 6500]).shape == (2, 3)


def test_tint_turns_the_light_green_or_magenta_at_the_same_brightness():
    luminance = torch.tensor([0.2126, 0.7152, 0.0722])
    green, magenta = lighting.light_gains(6500, 0.01), lighting.light_gains(6500, -0.01)
    assert green[1] > max(green[0], green[2]) and magenta[1] < min(magenta[0], magenta[2])
    for gains in (green, magenta, lighting.light_gains(3200, 0.005)):
        assert float(gains @ luminance) == pytest.approx(1.0, abs=1e-5)
    probe = torch.rand(4, 8, 3)
    torch.testing.assert_close(lighting.adjust_light(probe, 1.0, 5000, 0.01),
                               (probe * lighting.light_gains(5000, 0.01)).clamp(0, lighting.HDR_MAX))
    for tint in (0.05, -1, float("nan"), "green"):
        with pytest.raises(InputError, match="tint"):
            lighting.white_balance(probe, 5000, tint)


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
    of `adjust_light(probe, intensity, temperature, tint)`, at the same rotation."""
    relighter = Relighter.load("tiny", device="cpu")
    probe = torch.rand(32, 64, 3) * 4
    seen = record_encoded_lighting(monkeypatch)
    frames = np.random.default_rng(0).random((1, 32, 48, 3), dtype=np.float32)
    relighter.relight(RelightRequest(frames=frames, probe=probe, rotation=30.0, intensity=2.0, temperature=3200,
                                     tint=0.01, steps=1, sampler="euler"))
    assert seen, "the pipeline encoded no lighting"
    expected = lighting_the_preview_shows(relighter, lighting.adjust_light(probe, 2.0, 3200, 0.01), seen[0], 30.0)
    torch.testing.assert_close(seen[0], expected, rtol=1e-4, atol=1e-5)
    # ...and the colour really reached it: a neutral run, or one without the tint, encodes other light.
    for other in ({}, {"temperature": 3200}):
        seen.clear()
        relighter.relight(RelightRequest(frames=frames, probe=probe, rotation=30.0, intensity=2.0, steps=1,
                                         sampler="euler", **other))
        assert not torch.allclose(seen[0], expected)
    with pytest.raises(InputError, match="tint"):
        relighter.relight(RelightRequest(frames=frames, probe=probe, tint=0.5, steps=1))


def test_preview_balls_follow_the_temperature():
    config = preview.PreviewConfig(ball_size=64, mirror_resolution=48, diffuse_resolution=24)
    probe = torch.ones(16, 32, 3) * 0.5
    neutral = preview.render_preview(probe, 0.0, config=config).astype(float)
    warm = preview.render_preview(probe, 0.0, config=config, temperature=3000).astype(float)
    diffuse = (slice(24, 40), slice(64 + 24, 64 + 40))  # the centre of the matte ball
    assert abs(neutral[diffuse][..., 0].mean() - neutral[diffuse][..., 2].mean()) < 2  # grey light: grey ball
    assert warm[diffuse][..., 0].mean() > warm[diffuse][..., 2].mean() + 40            # warm light: orange ball
    green = preview.render_preview(probe, 0.0, config=config, tint=0.015).astype(float)
    assert green[diffuse][..., 1].mean() > max(green[diffuse][..., 0].mean(), green[diffuse][..., 2].mean()) + 5
