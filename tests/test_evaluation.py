"""Evaluation: the metrics against hand-computed values, the lighting it feeds, the margin, a whole run."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from relight_core import lighting
from relight_core.checkpoint import MODEL_PRESETS
from relight_core.cli import main
from relight_core.data.dataset import RelightDataset, read_stream, write_frame, write_manifest, write_meta
from relight_core.dit import JointDiT, channel_layout
from relight_core.errors import InputError
from relight_core.evaluation import protocol_metrics, psnr, scale_fit, ssim
from relight_core.evaluation.harness import (RunOptions, load_items, measure_item, probe_margin, relight, resized,
                                             sigma_errors)
from relight_core.evaluation.metrics import albedo_metrics, delta_e2000, protocol_psnr, steadiness
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.tokenizer import build_tokenizer
from tests.factory import awake

SIZE = 32


# ---------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------

def test_psnr_is_computed_on_the_mask_only():
    target = np.full((16, 16, 3), 0.6)
    pred = np.full((16, 16, 3), 0.5)                 # off by 0.1 everywhere: MSE 0.01 → 20 dB
    pred[:, 8:] = 0.0                                # far off on the right half...
    mask = np.zeros((16, 16))
    mask[:, :8] = 1.0                                # ...which the mask leaves out
    assert psnr(pred, target, mask) == pytest.approx(20.0)
    unmasked_mse = (0.01 + 0.36) / 2
    assert psnr(pred, target) == pytest.approx(-10 * math.log10(unmasked_mse))
    assert psnr(target, target) == 100.0             # identical: the cap


def test_psnr_averages_frames_and_an_empty_mask_counts_every_pixel():
    target = np.zeros((2, 8, 8, 3))
    pred = np.stack([np.full((8, 8, 3), 0.1), np.full((8, 8, 3), 0.01)])   # 20 dB and 40 dB
    mask = np.zeros((2, 8, 8))
    assert psnr(pred, target, mask) == pytest.approx(30.0)


def test_scale_fit_is_the_per_channel_least_squares_factor_on_the_mask():
    # Channel 0, masked pixels p = (0.1, 0.2), t = (0.2, 0.3): s = (0.02 + 0.06) / (0.01 + 0.04) = 1.6.
    pred = np.zeros((1, 1, 3, 3))
    target = np.zeros((1, 1, 3, 3))
    pred[0, 0, :, 0], target[0, 0, :, 0] = (0.1, 0.2, 0.9), (0.2, 0.3, 0.0)   # the third pixel is masked out
    pred[0, 0, :, 1], target[0, 0, :, 1] = (0.4, 0.2, 0.5), (0.2, 0.1, 0.5)   # exactly half: s = 0.5
    pred[0, 0, :, 2], target[0, 0, :, 2] = (0.3, 0.3, 0.3), (0.3, 0.3, 0.3)   # already right: s = 1
    mask = np.array([[[1.0, 1.0, 0.0]]])
    fitted, scales = scale_fit(pred, target, mask)
    np.testing.assert_allclose(scales, [1.6, 0.5, 1.0])
    np.testing.assert_allclose(fitted[0, 0, :2, 0], [0.16, 0.32])
    # Errors on the mask after the fit: channel 0 (0.04, 0.02), channels 1 and 2 exact.
    expected_mse = (0.04 ** 2 + 0.02 ** 2) / 6
    assert psnr(fitted, target, mask) == pytest.approx(-10 * math.log10(expected_mse))
    assert protocol_metrics(pred, target, mask)["psnr"] == pytest.approx(-10 * math.log10(expected_mse))
    assert protocol_psnr(pred, target, mask) == protocol_metrics(pred, target, mask)["psnr"]


def test_scale_fit_removes_a_colour_cast_and_clips():
    rng = np.random.default_rng(0)
    target = rng.uniform(0.1, 0.5, (2, 16, 16, 3))
    cast = target / np.array([2.0, 0.5, 1.25])         # a tinted, mis-exposed prediction
    assert protocol_metrics(cast, target)["psnr"] == 100.0
    assert psnr(cast, target) < 20
    fitted, _ = scale_fit(np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 3.0))
    assert fitted.max() == 1.0                          # a scaled prediction stays an image


def test_delta_e2000_is_per_frame_on_the_mask_then_averaged():
    target = np.zeros((2, 8, 8, 3))
    pred = np.zeros((2, 8, 8, 3))
    pred[0] = 1.0                                       # frame 0: white for black, ΔE2000 = 100 (L* 100 → 0)
    pred[1, :, :4] = 1.0                                # frame 1: white on the left half only...
    mask = np.zeros((2, 8, 8))
    mask[0, :2] = 1.0
    mask[1, :, 4:] = 1.0                                # ...which its mask leaves out
    assert delta_e2000(pred, target, mask) == pytest.approx(50.0)
    assert delta_e2000(pred, target) == pytest.approx(75.0)
    assert delta_e2000(target, target, mask) == 0.0


def test_albedo_metrics_add_the_colour_difference_after_the_scale_fit():
    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.1, 0.6, (2, 16, 16, 3))
    assert albedo_metrics(albedo * 0.5, albedo)["delta_e2000"] == pytest.approx(0.0, abs=1e-6)   # scale is free
    tinted = albedo.copy()
    tinted[..., 0] = albedo[..., 1]                     # a hue error no per-channel scale removes
    metrics = albedo_metrics(tinted, albedo)
    assert set(metrics) == {"psnr", "ssim", "delta_e2000", "temporal", "flicker"} and metrics["delta_e2000"] > 2
    assert metrics["psnr"] == protocol_metrics(tinted, albedo)["psnr"]


def test_steadiness_of_a_clip_against_values_computed_by_hand():
    truth = np.full((2, 4, 4, 3), 0.5)
    d = 0.1
    pred = np.stack([np.full((4, 4, 3), 0.5 - d), np.full((4, 4, 3), 0.5 + d)])   # brightens against its truth
    s = 0.5 / (0.5 + 2 * d ** 2)                        # the scale fit: Σ p·t / Σ p² over both frames
    metrics = protocol_metrics(pred, truth)
    assert metrics["temporal"] == pytest.approx(2 * d * s) and metrics["flicker"] == pytest.approx(2 * d * s)
    mask = np.ones((2, 4, 4))
    mask[1, :2] = 0                                     # only pixels in the mask of both frames count
    moving = truth.copy()
    moving[1, :2] = 1.0                                 # a change where frame 1's mask is 0: not counted
    steady = steadiness(truth, moving, mask)
    assert steady["temporal"] == pytest.approx(0.0) and steady["flicker"] == pytest.approx(0.0)
    still = protocol_metrics(0.5 * moving, moving)      # a steady clip, off by a scale only
    assert still["temporal"] == pytest.approx(0.0, abs=1e-9) and still["flicker"] == pytest.approx(0.0, abs=1e-9)
    assert "flicker" not in protocol_metrics(pred[0], truth[0])                    # an image has no steadiness


def test_ssim_of_constant_images_and_of_identical_ones():
    a, b = 0.2, 0.6
    c1 = 0.01 ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)  # no variance: the structure term is c2/c2
    assert ssim(np.full((16, 16, 3), a), np.full((16, 16, 3), b)) == pytest.approx(expected)
    image = np.random.default_rng(1).random((20, 24, 3))
    assert ssim(image, image) == pytest.approx(1.0)


def test_ssim_matches_a_window_by_window_computation():
    rng = np.random.default_rng(2)
    a = rng.random((13, 14, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5 ** 2))
    window = np.outer(g, g) / np.outer(g, g).sum()
    values = []
    for c in range(3):
        for i in range(13 - 10):
            for j in range(14 - 10):
                x, y = a[i:i + 11, j:j + 11, c], b[i:i + 11, j:j + 11, c]
                mx, my = (window * x).sum(), (window * y).sum()
                vx, vy = (window * x * x).sum() - mx ** 2, (window * y * y).sum() - my ** 2
                cov = (window * x * y).sum() - mx * my
                values.append((2 * mx * my + 1e-4) * (2 * cov + 9e-4) / ((mx ** 2 + my ** 2 + 1e-4) * (vx + vy + 9e-4)))
    assert ssim(b, a) == pytest.approx(np.mean(values), abs=1e-9)
    assert ssim(b, a) < 0.9


def test_ssim_ignores_what_the_mask_excludes():
    rng = np.random.default_rng(3)
    target = rng.random((32, 32, 3))
    pred = target.copy()
    pred[:, :16] = rng.random((32, 16, 3))              # wrong on the left half only
    mask = np.zeros((32, 32))
    mask[:, 16:] = 1.0
    assert ssim(pred, target, mask) == pytest.approx(1.0)
    assert ssim(pred, target) < 0.75


# ---------------------------------------------------------------------------------------------
# A tiny two-probe dataset written with the data engine's writers
# ---------------------------------------------------------------------------------------------

def _sun_probe(yaw: float) -> torch.Tensor:
    env = torch.full((16, 32, 3), 0.2)
    env[4, int(32 * yaw / 360) % 32] = torch.tensor([400.0, 380.0, 350.0])
    return env


def write_dataset(root, split: str, scenes: int = 2, frames: int = 1, size: int = SIZE, seed: int = 0):
    """Scenes of a textured patch lit from two sides, with camera-frame sun probes, in the dataset format."""
    rng = np.random.default_rng([seed, len(split)])
    yy, xx = np.mgrid[0:size, 0:size] / size
    for s in range(scenes):
        sample = root / split / f"scene_{s:06d}"
        tint = rng.uniform(0.5, 1.0, 3)
        albedo = np.stack([0.3 + 0.5 * ((np.floor(xx * 6) + np.floor(yy * 6)) % 2), 0.3 + 0.4 * xx,
                           0.4 + 0.3 * yy], -1) * tint
        mask = (yy > 0.25).astype(np.float32)
        for light, yaw in enumerate(rng.uniform(0, 360, 2)):
            panorama = lighting.probe_in_camera(_sun_probe(yaw), size, size, rotation=30.0 * s).numpy()
            for t in range(frames):
                shade = 0.25 + 0.75 * np.clip(np.cos(2 * np.pi * (xx - yaw / 360 - 0.05 * t)), 0, 1)
                write_frame(sample, f"rgb{light}", t, np.clip(albedo * shade[..., None], 0, 1))
                write_frame(sample, f"env{light}", t, panorama)
        for t in range(frames):
            write_frame(sample, "albedo", t, albedo)
            write_frame(sample, "mask", t, mask)
        write_meta(sample, {"kind": "synthetic", "frames": frames, "height": size, "width": size, "lights": 2})
    write_manifest(root / split)
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    write_dataset(root, "train", scenes=2)
    write_dataset(root, "test", scenes=2)
    return root


def _tiny(blind: bool = False) -> Relighter:
    """The tiny preset, awake; `blind` zeroes the patch-embedding weights of every lighting channel."""
    spec = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    relighter = awake(Relighter(spec, JointDiT(spec.dit), build_tokenizer(spec.tokenizer), "cpu", precision="fp32"))
    if blind:
        layout = channel_layout(spec.dit.out_channels)
        lit = slice(layout["env_ldr"].start, layout["env_dir_mask"].stop)
        with torch.no_grad():
            weight = relighter.dit.patch_embed.weight                          # (D, C·pt·p·p), (c, pt, p, p) order
            weight.view(weight.shape[0], -1, weight.shape[1] // layout["clip_type"].stop)[:, lit] = 0.0
    return relighter


# ---------------------------------------------------------------------------------------------
# The lighting handed to the model
# ---------------------------------------------------------------------------------------------

def test_the_items_carry_the_datasets_stored_camera_frame_probes(dataset):
    items = load_items(dataset, "test")
    data = RelightDataset(dataset, "test")
    assert [i.name for i in items] == ["scene_000000 0→1", "scene_000000 1→0", "scene_000001 0→1",
                                       "scene_000001 1→0"]
    for index, item in enumerate(items):
        source = data.items[index]
        np.testing.assert_array_equal(item.probe, read_stream(source.sample_dir, f"env{source.target_light}", [0]))
        np.testing.assert_array_equal(item.other_probe, read_stream(source.sample_dir, f"env{source.input_light}", [0]))
        # What training sees for this item is the same panorama's encodings.
        encoded = lighting.encode_lighting(torch.from_numpy(item.probe))
        for key in ("env_ldr", "env_log", "env_dir"):
            torch.testing.assert_close(data[index][key], encoded[key].permute(3, 0, 1, 2), rtol=0, atol=0)
        np.testing.assert_array_equal(item.input, (data[index]["input"].permute(1, 2, 3, 0).numpy() + 1) / 2)
    # `skip` (calibrate --skip) leaves out exactly the items `evaluate --limit` reports on.
    later = load_items(dataset, "test", count=1, spread=True, skip=2)
    assert [i.name for i in later] == ["scene_000001 0→1"]
    np.testing.assert_array_equal(later[0].target, items[2].target)
    with pytest.raises(InputError, match="after its first 4 items"):
        load_items(dataset, "test", skip=4)


def test_calibrate_refuses_a_bad_skip_in_one_sentence(dataset, capsys):
    from relight_core.training import calibrate

    base = ["--model", "default", "--data", str(dataset), "--split", "test"]
    for skip, words in (("-1", "--skip takes a count of items"),
                        ("4", "no scene rendered under two probes after its first 4")):
        with pytest.raises(SystemExit) as stop:
            calibrate.main([*base, "--skip", skip])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and words in err and "Traceback" not in err


def test_a_camera_probe_is_used_as_given_and_equals_the_probe_it_was_made_from():
    relighter = _tiny()
    frames = np.random.default_rng(0).random((1, SIZE, SIZE, 3), dtype=np.float32)
    probe = _sun_probe(90.0)
    panorama = lighting.probe_in_camera(probe, SIZE, SIZE, rotation=40.0)
    # A camera-frame panorama is not a lat-long file: re-gridding it at rotation 0 (identity camera)
    # mirrors it and shifts its rows, so it must not go through `probe` — hence `camera_probe`.
    assert (lighting.probe_in_camera(panorama, SIZE, SIZE, rotation=0.0) - panorama).abs().mean() > 1.0
    via_probe = relighter.relight(RelightRequest(frames, probe=probe, rotation=40.0, steps=2))
    via_panorama = relighter.relight(RelightRequest(frames, camera_probe=panorama.numpy(), steps=2))
    via_bigger = relighter.relight(RelightRequest(
        frames, camera_probe=lighting.probe_in_camera(probe, 2 * SIZE, 2 * SIZE, rotation=40.0)[None], steps=2))
    np.testing.assert_array_equal(via_panorama.relit, via_probe.relit)
    np.testing.assert_array_equal(via_panorama.albedo, via_probe.albedo)
    assert np.abs(via_bigger.relit - via_probe.relit).max() < 0.02        # re-gridded to the frames' size
    elsewhere = relighter.relight(RelightRequest(frames, probe=probe, rotation=220.0, steps=2))
    assert np.abs(elsewhere.relit - via_probe.relit).mean() > 1e-3        # the light does reach the output


def test_resize_panorama_regrids_camera_frame_panoramas():
    d = lighting.texel_directions(64, 128)                  # a smooth sky: low-order terms of the direction
    probe = torch.stack([1 + 0.5 * d[..., 0], 1 + 0.4 * d[..., 1] * d[..., 2], 0.8 + 0.3 * d[..., 2] ** 2], -1)
    big = lighting.probe_in_camera(probe, 64, 64, rotation=25.0)
    small = lighting.probe_in_camera(probe, 32, 32, rotation=25.0)
    assert lighting.resize_panorama(big, 64, 64) is big
    assert (lighting.resize_panorama(big, 32, 32) - small).abs().max() < 0.005
    assert (lighting.resize_panorama(small, 64, 64) - big).abs().mean() < 0.005
    assert (lighting.resize_panorama(big, 32, 32) - lighting.probe_in_camera(probe, 32, 32, rotation=70.0)
            ).abs().mean() > 0.05                         # the check can tell another light apart
    sun = torch.zeros(64, 64, 3)
    sun[20, 33] = 100.0
    kept = float(lighting.resize_panorama(sun, 16, 16).sum()) * 16 / float(sun.sum())
    assert 0.9 < kept < 1.1                              # a small sun is averaged in, never skipped


def test_bad_camera_probe_shapes_are_one_sentence():
    relighter = _tiny()
    frames = np.zeros((2, SIZE, SIZE, 3), np.float32)
    for bad in (np.zeros((SIZE, SIZE)), np.zeros((3, SIZE, SIZE, 3)), np.zeros((SIZE, SIZE, 4))):
        with pytest.raises(InputError, match="camera-frame probe has shape"):
            relighter.relight(RelightRequest(frames, camera_probe=bad, steps=1))


# ---------------------------------------------------------------------------------------------
# The probe-following margin
# ---------------------------------------------------------------------------------------------

def test_the_margin_is_zero_for_a_model_that_ignores_the_probe(dataset):
    item = load_items(dataset, "test", count=1)[0]
    options = RunOptions(steps=2)
    blind = _tiny(blind=True)
    metrics, _ = measure_item(blind, item, options)
    assert metrics["margin"] == pytest.approx(0.0, abs=1e-9)
    # The same network with its lighting weights kept responds to the probe, and the margin moves.
    seeing = _tiny()
    relit_b, _, _ = relight(seeing, item.input, item.probe, options)
    relit_a, _, _ = relight(seeing, item.input, item.other_probe, options)
    assert np.abs(relit_a - relit_b).mean() > 1e-4
    assert abs(probe_margin(relit_b, relit_a, item)) > 1e-6


def test_the_sigma_sweep_measures_the_denoiser_alone_whatever_copies_the_model_averages(dataset):
    from dataclasses import replace

    item = load_items(dataset, "test", count=1)[0]
    options = RunOptions(steps=2)
    plain = _tiny()
    copies = _tiny()
    copies.spec = replace(copies.spec, shift_average=2)          # results are two copies half a token apart
    relit_plain = relight(plain, item.input, item.probe, options)[0]
    assert np.abs(relight(copies, item.input, item.probe, options)[0] - relit_plain).mean() > 1e-5
    rows = sigma_errors(copies, item, options)
    assert rows == sigma_errors(plain, item, options) and len(rows) == 3
    assert copies.spec.shift_average == 2                         # given back after the sweep


def test_the_margin_rewards_following_the_probe(dataset):
    item = load_items(dataset, "test", count=1)[0]
    perfect = probe_margin(item.target, item.input, item)   # each probe's result is that probe's scene
    assert perfect > 10
    assert probe_margin(item.input, item.target, item) == pytest.approx(-perfect)   # the wrong way round


# ---------------------------------------------------------------------------------------------
# A whole run through the CLI
# ---------------------------------------------------------------------------------------------

def test_evaluate_end_to_end_on_the_tiny_preset(dataset, tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["evaluate", "--data", str(dataset), "--model", "tiny", "--steps", "1", "--limit", "2",
                 "--train-items", "1", "--sigma-items", "1", "--sigma-steps", "2", "--steps-list", "1,2",
                 "--eval-size", "96", "--follow-scenes", "1", "--out", str(out)]) == 0
    results = json.loads((out / "metrics.json").read_text())
    test = results["test"]
    assert test["items"] == 2 and results["train"]["items"] == 1
    follow = results["light_follow"]
    assert follow["scenes"] == 1 and follow["size"] == 64 and follow["yaws"] == [0.0, 90.0, 180.0, 270.0]
    assert 0.5 < follow["summary"]["follow_ceiling"] <= 1 and -1 <= follow["summary"]["follow"] <= 1
    assert follow["summary"]["follow"] == pytest.approx(follow["per_scene"][0]["follow"])
    assert results["model"]["steps"] == 1 and results["data"]["measured_size"] == [64, 64]   # tiny works at 64 px
    # The floor is the input scored as the result, computed here independently.
    items = load_items(dataset, "test", count=2)
    floors, albedo_floors = [], []
    for item in items:
        big = [torch.nn.functional.interpolate(torch.from_numpy(x).permute(0, 3, 1, 2), size=(64, 64),
                                               mode="bilinear", antialias=True, align_corners=False)
               .clamp(0, 1).permute(0, 2, 3, 1).numpy() for x in (item.input, item.target, item.albedo)]
        mask = torch.nn.functional.interpolate(torch.from_numpy(item.mask)[:, None], size=(64, 64),
                                               mode="bilinear", antialias=True, align_corners=False)[:, 0] > 0.5
        floors.append(protocol_metrics(big[0], big[1], mask.numpy())["psnr"])
        albedo_floors.append(delta_e2000(scale_fit(big[0], big[2], mask.numpy())[0], big[2], mask.numpy()))
    assert test["floor"]["relit"]["psnr"] == pytest.approx(np.mean(floors), abs=1e-6)
    assert test["floor"]["albedo"]["delta_e2000"] == pytest.approx(np.mean(albedo_floors), abs=1e-6)
    for section in ("model", "floor", "ceiling"):
        for kind in ("relit", "albedo"):
            assert 5 < test[section][kind]["psnr"] <= 100 and -1 <= test[section][kind]["ssim"] <= 1
        assert 0 <= test[section]["albedo"]["delta_e2000"] < 100 and "delta_e2000" not in test[section]["relit"]
    assert test["margin"] is not None and math.isfinite(test["margin"])
    assert [row["steps"] for row in results["steps"]] == [1, 2]
    assert results["steps"][0]["relit"] == pytest.approx(test["model"]["relit"])     # the main run, reused
    sigmas = [row["sigma"] for row in results["sigma"]["test"]["rows"]]
    assert len(sigmas) == 3 and sigmas[0] == pytest.approx(80.0) and sigmas[-1] == pytest.approx(0.002)
    assert results["sigma"]["train"]["items"] == 1
    first = results["sigma"]["test"]["rows"][0]
    assert {"relit_psnr", "relit_psnr_no_light", "albedo_psnr", "relit_latent_mse"} <= set(first)
    full = results["full_resolution"]
    assert full["size"] == 96 and full["items"] == 2
    for source in ("model", "oracle"):
        for method in ("plain", "guided"):
            assert 5 < full[source]["relit"][method]["psnr"] <= 100
    assert full["oracle"]["relit"]["plain"]["psnr"] > full["model"]["relit"]["plain"]["psnr"]   # truth beats noise
    report = (out / "metrics.md").read_text()
    assert "| albedo ΔE2000 |" in report and f"| {test['model']['albedo']['delta_e2000']:.2f} |" in report
    clips = results["data"]["frames"] > 1               # clips are also scored for how steady they are
    assert ("| relit flicker |" in report) == clips == ("flicker" in test["model"]["relit"])
    if clips:
        assert f"| {255 * test['model']['relit']['temporal']:.2f} | {255 * test['model']['relit']['flicker']:.2f} |" \
            in report
    for heading in ("| model |", "floor: input returned unchanged", "ceiling: tokenizer", "Probe-following margin",
                    "Train-set reproduction", "Steps vs quality", "Denoiser error per σ", "Full-resolution output",
                    "Following a turning light"):
        assert heading in report
    from PIL import Image
    grids = sorted(p.name for p in (out / "grids").iterdir())
    assert grids == ["full_000.png", "full_001.png", "test_000.png", "test_001.png", "train_000.png"]
    width, height = Image.open(out / "grids" / "test_000.png").size
    assert width == 5 * 128 and height > 128            # five columns (64 px frames shown at 128)
    assert "relit" in capsys.readouterr().out


def test_measuring_at_another_size_runs_the_model_at_its_own_and_brings_results_back_guided(dataset):
    from relight_core.evaluation.harness import ceiling, model_size, reconstruct
    from relight_core.upsample import guided_ratio_upsample

    relighter = _tiny()                                            # works at 64 px
    big = resized(load_items(dataset, "test", count=1)[0], 128, 8)  # a "photo" twice the model's size
    small = model_size(relighter, big.input)
    assert small.shape == (1, 64, 64, 3)
    options = RunOptions(steps=1)
    relit, albedo, _ = relight(relighter, big.input, big.probe, options)
    assert relit.shape == albedo.shape == big.input.shape
    direct, direct_albedo, _ = relight(relighter, small, big.probe, options)     # at the model's size: as it is
    assert direct.shape == small.shape
    np.testing.assert_allclose(relit, guided_ratio_upsample(big.input, small, direct), atol=1e-6)
    np.testing.assert_allclose(albedo, guided_ratio_upsample(big.input, small, direct_albedo), atol=1e-6)
    # The ceiling is what a perfect model could give through the same path, not a reconstruction at 128 px.
    best = ceiling(relighter, big.target, big.input)
    np.testing.assert_allclose(best, guided_ratio_upsample(big.input, small, reconstruct(
        relighter, model_size(relighter, big.target))), atol=1e-6)
    at_model_size = resized(big, 64, 8)
    np.testing.assert_array_equal(ceiling(relighter, at_model_size.target, at_model_size.input),
                                  reconstruct(relighter, at_model_size.target))


def test_evaluate_scores_how_steady_a_clip_is(tmp_path):
    write_dataset(tmp_path / "clips", "test", scenes=1, frames=3)
    out = tmp_path / "eval-clips"
    assert main(["evaluate", "--data", str(tmp_path / "clips"), "--model", "tiny", "--steps", "1", "--limit", "2",
                 "--train-items", "0", "--sigma-items", "0", "--no-grids", "--out", str(out)]) == 0
    results = json.loads((out / "metrics.json").read_text())
    assert results["data"]["frames"] == 3
    items = [resized(i, results["data"]["measured_size"][0], 8) for i in load_items(tmp_path / "clips", "test")]
    floors = [protocol_metrics(i.input, i.target, i.mask) for i in items]     # the floor, by hand, where measured
    for name in ("temporal", "flicker"):
        assert results["test"]["floor"]["relit"][name] == pytest.approx(np.mean([f[name] for f in floors]), abs=1e-9)
    assert results["test"]["floor"]["relit"]["flicker"] > 0 and "flicker" in results["test"]["model"]["albedo"]
    report = (out / "metrics.md").read_text()
    row = results["test"]["floor"]
    assert (f"| floor: input returned unchanged | {255 * row['relit']['temporal']:.2f} | "
            f"{255 * row['relit']['flicker']:.2f} | {255 * row['albedo']['temporal']:.2f} | "
            f"{255 * row['albedo']['flicker']:.2f} |") in report


def test_evaluate_at_a_larger_size_measures_there(dataset, tmp_path):
    out = tmp_path / "eval96"
    assert main(["evaluate", "--data", str(dataset), "--model", "tiny", "--steps", "1", "--limit", "1",
                 "--train-items", "0", "--sigma-items", "1", "--sigma-steps", "2", "--size", "96", "--no-grids",
                 "--out", str(out)]) == 0
    results = json.loads((out / "metrics.json").read_text())
    assert results["model"]["size"] == 64 and results["data"]["measured_size"] == [96, 96]
    item = resized(load_items(dataset, "test", count=1)[0], 96, 8)
    assert results["test"]["floor"]["relit"]["psnr"] == pytest.approx(
        protocol_metrics(item.input, item.target, item.mask)["psnr"], abs=1e-6)   # the floor at 96 px
    assert math.isfinite(results["test"]["margin"]) and results["sigma"]["test"]["items"] == 1
    assert "model size 64 px, measured at 96×96" in (out / "metrics.md").read_text()


def test_evaluate_without_a_train_split_reports_why_in_one_sentence(dataset, tmp_path):
    # Train-set reproduction asked for where no train split was rendered: the test split is still
    # measured, and the report says why the train table is missing, as one sentence.
    import shutil
    data = tmp_path / "data"
    shutil.copytree(dataset / "test", data / "test")
    out = tmp_path / "eval"
    assert main(["evaluate", "--data", str(data), "--model", "tiny", "--steps", "1", "--limit", "1",
                 "--train-items", "1", "--sigma-items", "0", "--no-margin", "--no-grids", "--out", str(out)]) == 0
    results = json.loads((out / "metrics.json").read_text())
    assert results["test"]["items"] == 1 and results["train"]["items"] == 0
    line = next(x for x in (out / "metrics.md").read_text().splitlines() if x.startswith("Not measured:"))
    assert "manifest" in line and "render-data" in line and line.endswith(".") and not line.endswith("..")


def test_evaluate_bad_input_is_one_sentence_and_exit_2(dataset, tmp_path, capsys):
    assert main(["evaluate", "--data", str(tmp_path / "missing"), "--model", "tiny", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: No dataset manifest") and err.count("\n") == 1
    assert main(["evaluate", "--data", str(dataset), "--model", "tiny", "--eval-size", "64",
                 "--out", str(tmp_path)]) == 2
    assert "must be larger than the model's working size" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", "--data", str(dataset), "--steps-list", "5,x", "--out", str(tmp_path)])
    assert exit_info.value.code == 2


def _shadowed(shadow_x: int, depth: float = 0.25, size: int = 32) -> np.ndarray:
    """Display values of a textured grey ground whose 8-px-wide cast shadow (`depth` of the light) falls at
    column `shadow_x`."""
    from relight_core.colour import linear_to_srgb

    linear = 0.3 + 0.1 * np.random.default_rng(3).random((size, size, 1)) * np.ones(3)
    linear[8:24, shadow_x:shadow_x + 8] *= depth
    return linear_to_srgb(linear)


def test_light_follow_scores_a_moving_shadow_and_an_albedo_that_keeps_the_shading():
    from relight_core.evaluation import light_follow as lf

    truth_a, truth_b, mask = _shadowed(4), _shadowed(20), np.ones((32, 32))
    # A result that changes exactly as the truth does follows it fully, in the detail too, all the way.
    assert lf.change_follow(truth_a, truth_b, truth_a, truth_b, mask) == pytest.approx(1.0)
    assert lf.change_follow(truth_a, truth_b, truth_a, truth_b, mask, sigma=3) == pytest.approx(1.0)
    assert lf.change_reach(truth_a, truth_b, truth_a, truth_b, mask) == pytest.approx(1.0)
    assert lf.shadow_agreement(truth_a, truth_b, truth_a, truth_b, mask) == 1.0
    # A model that ignores the light: no change, nothing followed; the shadow moved the wrong way: all disagree.
    assert lf.change_follow(truth_a, truth_b, truth_a, truth_a, mask) == 0.0
    assert lf.change_reach(truth_a, truth_b, truth_a, truth_a, mask) == pytest.approx(0.0)
    assert lf.shadow_agreement(truth_a, truth_b, truth_b, truth_a, mask) == 0.0
    assert lf.shadow_agreement(truth_a, truth_a, truth_a, truth_b, mask) is None  # the truth does not change
    # Shadows half as deep in log luminance (half the light, not a quarter): reach 0.5, still fully correlated.
    soft_a, soft_b = _shadowed(4, 0.5), _shadowed(20, 0.5)
    assert lf.change_reach(truth_a, truth_b, soft_a, soft_b, mask) == pytest.approx(0.5, abs=0.02)
    assert lf.change_follow(truth_a, truth_b, soft_a, soft_b, mask) == pytest.approx(1.0)
    # A smooth wash where the shadows are: correlated as a whole, barely in the detail (no sharp edge moved).
    blur = lambda x: cv2.GaussianBlur(x.astype(np.float32), (0, 0), 8).astype(np.float64)  # noqa: E731
    wash_a, wash_b = blur(truth_a), blur(truth_b)
    whole = lf.change_follow(truth_a, truth_b, wash_a, wash_b, mask)  # measured 0.61, in the detail 0.22
    assert whole > 0.5 and lf.change_follow(truth_a, truth_b, wash_a, wash_b, mask, sigma=3) < whole / 2
    # The albedo: the input copied keeps all its shading, the true albedo (at any scale) none.
    albedo = 0.6 + 0.1 * np.random.default_rng(4).random((32, 32, 1)) * np.ones(3)
    source = albedo * _shadowed(10)  # the albedo under a light with a shadow in it
    assert lf.albedo_shading(source, albedo, source, mask) == pytest.approx(1.0)
    assert lf.albedo_shading(albedo * 0.7, albedo, source, mask) == pytest.approx(0.0, abs=0.02)
