"""Colour maths through colour-science: the one sRGB curve, light colour from a temperature, CIEDE2000."""

import numpy as np
import pytest
import torch

from relight_core import colour, lighting, media


def test_the_srgb_curve_is_colour_sciences_for_arrays_and_tensors():
    science = colour.colour_science()
    x = np.linspace(-0.05, 3.0, 4001)
    expected = science.models.eotf_inverse_sRGB(x)
    np.testing.assert_allclose(colour.linear_to_srgb(x), expected, rtol=0, atol=1e-12)
    # Tensors (the lighting encodings, on the model's device) get the same curve, in float32.
    encoded = colour.linear_to_srgb(torch.from_numpy(x).float())
    assert isinstance(encoded, torch.Tensor) and encoded.dtype == torch.float32
    np.testing.assert_allclose(encoded.numpy(), expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(colour.srgb_to_linear(expected), x, rtol=0, atol=1e-12)
    # And back (the trainer mixes lights in linear light on its device): a tensor in, a tensor out.
    decoded = colour.srgb_to_linear(torch.from_numpy(expected).float())
    assert isinstance(decoded, torch.Tensor) and decoded.dtype == torch.float32
    np.testing.assert_allclose(decoded.numpy(), science.models.eotf_sRGB(expected), rtol=2e-6, atol=1e-6)
    # IEC 61966-2-1 values: the knee, and 18 % grey.
    assert colour.linear_to_srgb(np.float64(0.0031308)) == pytest.approx(0.04045, abs=1e-6)
    assert colour.linear_to_srgb(np.float64(0.18)) == pytest.approx(0.4613561, abs=1e-7)
    assert colour.linear_to_srgb(np.float32([0.5])).dtype == np.float32


def test_every_srgb_user_goes_through_the_one_curve():
    assert media.linear_to_srgb is colour.linear_to_srgb and media.srgb_to_linear is colour.srgb_to_linear
    x = torch.linspace(0, 50, 101)[:, None].expand(101, 3)
    expected = colour.linear_to_srgb(lighting.reinhard(x).numpy().clip(0, 1))  # through colour-science
    np.testing.assert_allclose(lighting.env_ldr(x).numpy(), expected, atol=1e-6)


def test_temperature_chromaticities_are_the_planckian_locus():
    # CIE illuminant A is a 2856 K black body: xy (0.44757, 0.40745); 5000 K: (0.3451, 0.3516).
    np.testing.assert_allclose(colour.temperature_xy(2856), (0.44757, 0.40745), atol=1e-4)
    np.testing.assert_allclose(colour.temperature_xy([2856, 5000]), [(0.44757, 0.40745), (0.3451, 0.3516)], atol=2e-4)
    # A tint leaves the locus: positive Δuv towards green (larger y), negative towards magenta.
    on, green, magenta = colour.temperature_xy(5000, [0.0, 0.01, -0.01])
    assert green[1] > on[1] > magenta[1]


def test_white_is_white_and_luminance_is_rec709():
    rgb = colour.xy_to_linear_srgb(np.array([0.3127, 0.3290]))    # D65, the sRGB white
    np.testing.assert_allclose(rgb, 1.0, atol=5e-4)
    np.testing.assert_allclose(colour.luminance(np.eye(3, dtype=np.float32)), (0.2126, 0.7152, 0.0722))
    assert colour.luminance(np.ones((4, 3), np.float32)).dtype == np.float32


def test_delta_e_2000_values_and_shapes(monkeypatch):
    white, black = np.ones(3), np.zeros(3)
    assert colour.delta_e_2000(white, black) == pytest.approx(100.0, abs=1e-6)   # L* 100 → 0, S_L = 1
    rng = np.random.default_rng(0)
    a, b = rng.random((5, 7, 3)), rng.random((5, 7, 3))
    d = colour.delta_e_2000(a, b)
    assert d.shape == (5, 7) and (d > 0).all()
    np.testing.assert_allclose(colour.delta_e_2000(b, a), d)                     # symmetric
    np.testing.assert_array_equal(colour.delta_e_2000(a, a), 0.0)
    science = colour.colour_science()
    white_point = science.RGB_COLOURSPACES["sRGB"].whitepoint
    lab = [science.XYZ_to_Lab(science.sRGB_to_XYZ(x), white_point) for x in (a[2, 3], b[2, 3])]
    assert d[2, 3] == pytest.approx(float(science.delta_E(*lab, method="CIE 2000")), rel=1e-9)
    monkeypatch.setattr(colour, "DELTA_E_BLOCK", 4)                             # blocks give the same numbers
    np.testing.assert_array_equal(colour.delta_e_2000(a, b), d)
