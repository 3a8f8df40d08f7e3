"""Full-resolution output: guided ratio upsampling, and the CLI writing results at the input's size."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from relight_core import media
from relight_core.cli import main
from relight_core.errors import InputError
from relight_core.upsample import guided_ratio_upsample, plain_upsample, smooth_offset
from tests.factory import make_sun_probe


def _photo(t=1, h=75, w=100, seed=0) -> np.ndarray:
    """A detailed picture: a fine checkerboard over smooth colour, in (0.05, 1)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    checker = ((yy // 3 + xx // 3) % 2)[..., None] * 0.3
    base = np.stack([xx / w, yy / h, 0.5 + 0.3 * np.sin(xx / 7)], -1) * 0.6 + 0.05
    frames = [np.clip(base + checker + 0.02 * rng.standard_normal((h, w, 3)), 0.05, 1) for _ in range(t)]
    return np.stack(frames).astype(np.float32)


def _small(frames: np.ndarray, long_side: int = 32) -> np.ndarray:
    return media.resize_frames(frames, long_side, multiple=16)


@pytest.mark.parametrize("t", [1, 3])
def test_returns_the_full_inputs_size(t):
    full = _photo(t)
    small = _small(full)
    assert small.shape == (t, 32, 32, 3)
    out = guided_ratio_upsample(full, small, np.clip(small * 0.7, 0, 1))
    assert out.shape == full.shape and out.dtype == np.float32
    assert 0.0 <= out.min() and out.max() <= 1.0
    assert guided_ratio_upsample(full[0], small[0], small[0]).shape == full.shape[1:]   # a single image


def test_a_constant_ratio_relighting_is_reproduced_exactly():
    full = _photo(2)
    small = _small(full)
    gain = np.array([0.5, 1.3, 0.8], np.float32)        # a colour cast; the green channel clips
    out = guided_ratio_upsample(full, small, small * gain)
    np.testing.assert_allclose(out, np.clip(full * gain, 0, 1), rtol=0, atol=1e-6)   # float32 rounding only
    assert (out[..., 1] == 1.0).any()


def test_the_ratio_follows_the_inputs_edges_better_than_resizing():
    """A shadow whose edge is a sharp edge of the input: the guided ratio keeps it, resizing blurs it."""
    full = _photo(1, 96, 128)
    h, w = full.shape[1:3]
    shade = np.ones((1, h, w, 1), np.float32)
    shade[:, :, : w // 2 + 5] = 0.35                    # not on the model grid's pixel boundaries
    full = full.copy()
    full[:, :, w // 2 + 5:] = np.clip(full[:, :, w // 2 + 5:] + 0.25, 0, 1)   # the input has that edge too
    truth = np.clip(full * shade, 0, 1)
    small = _small(full)
    small_truth = _small(truth)                         # a perfect model at its own size
    guided = guided_ratio_upsample(full, small, small_truth)
    plain = plain_upsample(small_truth, h, w)
    assert np.abs(guided - truth).mean() < 0.5 * np.abs(plain - truth).mean()


def test_same_size_returns_the_output_and_bad_shapes_are_one_sentence():
    small = _photo(1, 32, 32)
    out = small * 0.5
    np.testing.assert_array_equal(guided_ratio_upsample(small, small, out), out)
    with pytest.raises(InputError, match="matching frame counts"):
        guided_ratio_upsample(_photo(2), _small(_photo(1)), _small(_photo(1)))
    with pytest.raises(InputError, match="matching frame counts"):
        guided_ratio_upsample(_photo(1), _small(_photo(1)), _small(_photo(1))[..., :2])


def test_cli_writes_the_inputs_resolution_unless_raw(tmp_path):
    photo = tmp_path / "photo.png"
    media.save_image(photo, _photo(1, 64, 96)[0])
    probe = make_sun_probe(tmp_path / "sun.exr")
    fast = ["--model", "tiny", "--steps", "1", "--size", "48"]
    assert main(["relight", str(photo), "--probe", str(probe), "--out", str(tmp_path / "full"), *fast]) == 0
    assert main(["relight", str(photo), "--probe", str(probe), "--out", str(tmp_path / "raw"), "--raw", *fast]) == 0
    for name in ("relit.png", "albedo.png"):
        assert Image.open(tmp_path / "full" / name).size == (96, 64)
        assert Image.open(tmp_path / "raw" / name).size == (48, 32)
    assert main(["albedo", str(photo), "--out", str(tmp_path / "albedo"), *fast]) == 0
    assert Image.open(tmp_path / "albedo" / "albedo.png").size == (96, 64)


def test_offset_smoothing_keeps_a_constant_offset_and_averages_blotches_away():
    guide = _photo(t=2, h=48, w=64) * 0.8
    shifted = guide + 0.1                                        # a constant offset: kept exactly
    np.testing.assert_allclose(smooth_offset(guide, shifted, 4), np.clip(shifted, 0, 1), atol=1e-5)
    assert smooth_offset(guide, shifted, 0) is shifted          # radius 0: the output as it is
    # A shading change that is smooth inside the picture, plus the blotches a short-trained model
    # adds: the filter brings the result closer to the clean change, and keeps the input's checkerboard.
    yy, xx = np.mgrid[0:48, 0:64]
    shading = (0.15 * np.sin(xx / 20.0) * np.cos(yy / 25.0))[None, ..., None].astype(np.float32)
    clean = guide + shading
    blotchy = clean + 0.05 * np.random.default_rng(3).standard_normal(clean.shape).astype(np.float32)
    smoothed = smooth_offset(guide, blotchy, 4)
    assert np.abs(smoothed - clean).mean() < 0.5 * np.abs(blotchy - clean).mean()
    checker = (((yy // 3 + xx // 3) % 2) == 1)
    assert smoothed[0][checker].mean() - smoothed[0][~checker].mean() > 0.2
    with pytest.raises(InputError, match="one size"):
        smooth_offset(guide, guide[:, :32], 2)


def test_the_torch_guided_filter_is_opencv_contribs_and_stands_in_where_opencv_has_no_ximgproc(monkeypatch):
    import cv2

    from relight_core import upsample

    rng = np.random.default_rng(1)
    # sizes, radii (one past the image: the mirrored border repeats) and sources of one and three channels
    for h, w, radius, channels in ((128, 128, 12, 3), (37, 53, 4, 3), (16, 16, 20, 3), (20, 30, 3, 1)):
        guide = rng.random((h, w, 3)).astype(np.float32)
        source = (rng.random((h, w, channels) if channels > 1 else (h, w)).astype(np.float32) - 0.5)
        expected = cv2.ximgproc.guidedFilter(guide, source, radius, 0.01)
        got = upsample.guided_filter_torch(guide, source, radius, 0.01)
        assert got.shape == expected.shape and got.dtype == np.float32
        np.testing.assert_allclose(got, expected, atol=1e-6)
        assert np.abs(got - source).max() > 0.1                          # it did filter
    # Frames in batches of any shape, at once, and on a given torch device: each as OpenCV filters it alone.
    guides = rng.random((2, 3, 24, 20, 3)).astype(np.float32)
    sources = rng.random((2, 3, 24, 20)).astype(np.float32)
    batched = upsample.guided_filter_torch(guides, sources, 5, 0.01, device="cpu")
    assert batched.shape == sources.shape
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(batched[i, j], cv2.ximgproc.guidedFilter(guides[i, j], sources[i, j], 5, 0.01),
                                       atol=1e-6)
    # A plain OpenCV (a GPU machine's image) has no ximgproc: the offset filter and the ratio transfer give the same.
    guide = rng.random((2, 32, 32, 3)).astype(np.float32)
    output = np.clip(guide + 0.2 * rng.random((2, 32, 32, 3)).astype(np.float32), 0, 1)
    small = guide[:, ::2, ::2]
    with_contrib = (upsample.smooth_offset(guide, output, 4), upsample.guided_ratio_upsample(guide, small, output[:, ::2, ::2]))
    monkeypatch.delattr(cv2, "ximgproc")
    without = (upsample.smooth_offset(guide, output, 4), upsample.guided_ratio_upsample(guide, small, output[:, ::2, ::2]))
    for a, b in zip(with_contrib, without):
        np.testing.assert_allclose(a, b, atol=1e-6)
