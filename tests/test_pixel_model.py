"""The default model's pieces: the lossless pixel tokenizer, the wide token layout, the lighting grid,
image packs and the fast trainer, end to end through a saved model folder and the Relighter."""

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from relight_core import lighting
from relight_core.checkpoint import DIT_FILE, TOKENIZER_FILE, ModelSpec, load_model
from relight_core.colour import colour_science
from relight_core.dit import CHANNELS, DiTConfig, JointDiT, assemble_inputs, channel_layout, pack_lighting
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.tokenizer import PixelTokenizer, build_tokenizer
from relight_core.training.recipe import Recipe
from relight_core.training.fast import FastConfig, light_mix, main, make_batch, merge_shards, train
from relight_core.training.pack import load_pack, load_packs, write_pack
from relight_core.upsample import smooth_offset
from tests.factory import write_pack_dataset


def test_pixel_tokenizer_is_lossless_and_spatially_local():
    tok = build_tokenizer({"type": "pixel", "patch": 8})
    video = torch.rand(2, 3, 3, 32, 48) * 2 - 1
    latents = tok.encode(video)
    assert latents.shape == (2, 192, 3, 4, 6)
    assert torch.equal(tok.decode(latents), video)
    # Latent pixel (i, j) holds exactly the 8×8 block (i, j): changing one block changes one latent pixel.
    changed = video.clone()
    changed[:, :, :, 8:16, 16:24] = 0
    diff = (tok.encode(changed) - latents).abs().sum(dim=(0, 1, 2))
    assert diff[1, 2] > 0 and diff.sum() == diff[1, 2]
    # Channel order (c, dy, dx): channel 0 is the top-left red pixel of each block.
    assert torch.equal(latents[:, 0], video[:, 0, :, ::8, ::8])


def test_pixel_tokenizer_spec_errors_are_one_sentence():
    with pytest.raises(InputError, match="Unknown pixel tokenizer keys"):
        build_tokenizer({"type": "pixel", "channels": 3})
    with pytest.raises(InputError, match="cannot be tokenized: .* multiples of 8"):
        PixelTokenizer(8).encode(torch.zeros(1, 3, 1, 20, 32))


def test_pixel_tokenizer_takes_whole_patches_not_multiples_of_16():
    # A 16:9 frame at the default's 128 px is 128×72: nine 8-px patches high. The learned tokenizers' 16-px rule
    # (8× × a DiT patch of 2) once refused it here, so every 16:9 or 3:2 input failed with the default model.
    video = torch.rand(1, 3, 2, 72, 128) * 2 - 1
    latents = PixelTokenizer(8).encode(video)
    assert latents.shape == (1, 192, 2, 9, 16)
    assert torch.equal(PixelTokenizer(8).decode(latents), video)


def test_channel_layout_generalises_the_released_72():
    assert channel_layout(16) == CHANNELS and CHANNELS["clip_type"].stop == 72
    wide = channel_layout(192)
    assert wide["noisy"] == slice(0, 192) and wide["env_ldr"] == slice(193, 385)
    assert wide["clip_type"] == slice(4 * 192 + 5, 4 * 192 + 8)
    z = torch.randn(1, 192, 1, 2, 2)
    x = assemble_inputs(torch.cat([z, z, z], 2), torch.ones(1, 1, 3, 1, 1), pack_lighting(z, None, z), None)
    assert x.shape[1] == wide["padding_mask"].stop
    assert torch.equal(x[:, wide["env_ldr"], 1], z[:, :, 0]) and bool((x[:, wide["env_log"]] == 0).all())
    assert bool((x[:, wide["env_ldr"], 0] == 0).all())  # lighting only in the relit clip
    dit = JointDiT(DiTConfig(width=32, depth=1, num_heads=2, adaln_lora_dim=8, patch_spatial=1, out_channels=192))
    assert dit(x, torch.zeros(1)).shape == (1, 192, 3, 2, 2)


def test_lowpass_panorama_keeps_energy_and_is_identity_at_full_size():
    pan = torch.zeros(1, 64, 64, 3)
    pan[0, 20, 40] = 1000.0                                  # a one-pixel sun
    small = lighting.downsample_panorama(pan, 16)
    assert small.shape == (1, 16, 16, 3)
    assert torch.allclose(small.mean(), pan.mean()) and small[0, 5, 10, 0] == pytest.approx(1000 / 16)
    low = lighting.lowpass_panorama(pan, 16)
    assert low.shape == pan.shape and low[0, 20, 40, 0] < 1000 and low.mean() == pytest.approx(float(pan.mean()), rel=0.05)
    assert lighting.lowpass_panorama(pan, 64) is pan and lighting.lowpass_panorama(pan, None) is pan


def test_pack_round_trip(tmp_path):
    from relight_core.data.files import read_exr, read_image

    root = write_pack_dataset(tmp_path / "data")
    count = write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    pack = load_pack(tmp_path / "p.npz")
    assert count == 3 and pack["rgb"].shape == (3, 2, 3, 32, 32) and pack["env"].shape == (3, 2, 8, 8, 3)
    scene = root / "train" / "scene_000001"
    original = torch.from_numpy(read_image(scene / "rgb1" / "0000.png")).permute(2, 0, 1) * 255
    assert (pack["rgb"][1, 1].float() - original).abs().mean() < 6          # JPEG, quality 92
    assert torch.equal(pack["mask"][1], torch.from_numpy(read_image(scene / "mask" / "0000.png") > 0.5))
    env = lighting.downsample_panorama(torch.from_numpy(read_exr(scene / "env0" / "0000.exr"))[None], 8)[0]
    assert torch.allclose(pack["env"][1, 0], env, rtol=2e-3, atol=1e-3)     # stored as fp16


def test_lossless_pack_holds_the_rendered_pixels(tmp_path):
    from relight_core.data.files import read_image

    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "jpeg.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "png.npz", lighting_size=8, lossless=True)
    jpeg, png = load_pack(tmp_path / "jpeg.npz"), load_pack(tmp_path / "png.npz")
    scene = root / "train" / "scene_000002"
    for stream, got_png, got_jpeg in (("rgb0", png["rgb"][2, 0], jpeg["rgb"][2, 0]),
                                      ("albedo", png["albedo"][2], jpeg["albedo"][2])):
        original = torch.from_numpy(np.round(read_image(scene / stream / "0000.png") * 255)).permute(2, 0, 1)
        assert torch.equal(got_png.float(), original)                        # exactly what was rendered
        assert not torch.equal(got_jpeg.float(), original)                   # which JPEG 92 is not
    assert torch.equal(png["mask"], jpeg["mask"]) and torch.equal(png["env"], jpeg["env"])


def test_a_prefixed_pack_keeps_alike_named_scenes_of_another_split_apart(tmp_path):
    """training.refine leaves out of training every scene its validation pack names; a development pack of the
    test split (scene_000000… like any training pack) packed with a prefix takes none of them away."""
    from relight_core.training.refine import unseen_items

    root = write_pack_dataset(tmp_path / "data", scenes=3)
    write_pack(root, "train", tmp_path / "train.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "plain.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "dev.npz", lighting_size=8, names_prefix="test-s2/")
    names = load_pack(tmp_path / "train.npz")["names"]
    assert load_pack(tmp_path / "dev.npz")["names"] == [f"test-s2/{n}" for n in names]
    assert unseen_items(names, [tmp_path / "plain.npz"], None) == []            # alike names: every scene left out
    assert len(unseen_items(names, [tmp_path / "dev.npz"], None)) == len(unseen_items(names, [], None)) > 0


def test_several_packs_train_as_one_and_must_match(tmp_path, capsys):
    write_pack(write_pack_dataset(tmp_path / "a", scenes=3), "train", tmp_path / "a.npz", lighting_size=8)
    write_pack(write_pack_dataset(tmp_path / "b", scenes=2, seed=1), "train", tmp_path / "b.npz", lighting_size=8)
    a, b = load_pack(tmp_path / "a.npz"), load_pack(tmp_path / "b.npz")
    both = load_packs([tmp_path / "a.npz", tmp_path / "b.npz"])
    assert both["rgb"].shape == (5, 2, 3, 32, 32) and both["lighting_size"] == 8 and len(both["names"]) == 5
    for key in ("rgb", "albedo", "mask", "env"):
        assert torch.equal(both[key][:3], a[key]) and torch.equal(both[key][3:], b[key]), key
    assert not torch.equal(both["rgb"][0], both["rgb"][3])                  # the second pack's own scenes
    single = load_packs(tmp_path / "a.npz")
    assert all(torch.equal(single[k], a[k]) for k in ("rgb", "albedo", "mask", "env"))
    write_pack(write_pack_dataset(tmp_path / "c", scenes=2, size=16), "train", tmp_path / "c.npz", lighting_size=8)
    with pytest.raises(ValueError, match="c.npz holds \\(16, 16\\) px images"):
        load_packs([tmp_path / "a.npz", tmp_path / "c.npz"])
    # The trainer's --pack takes several: a run on both sees all five scenes.
    main(["--pack", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--out", str(tmp_path / "run"),
          "--minutes", "0.01", "--device", "cpu", "--batch", "2", "--width", "32", "--depth", "1",
          "--num-heads", "2", "--eval-items", "1", "--eval-steps", "1", "--warmup", "1"])
    start = json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[0])
    assert start["event"] == "start" and start["items"] == 5
    assert start["config"]["pack"] == f"{tmp_path / 'a.npz'} {tmp_path / 'b.npz'}"
    capsys.readouterr()
    # From the command line a mismatch or a missing pack is one sentence (exit 2), not a traceback.
    for packs, sentence in (([tmp_path / "a.npz", tmp_path / "c.npz"], "c.npz holds (16, 16) px images"),
                            ([tmp_path / "a.npz", tmp_path / "gone.npz"], "no pack at")):
        with pytest.raises(SystemExit) as exit_info:
            main(["--pack", *map(str, packs), "--out", str(tmp_path / "run2"), "--minutes", "0.01",
                  "--device", "cpu", "--width", "32", "--depth", "1", "--num-heads", "2"])
        assert exit_info.value.code == 2 and sentence in capsys.readouterr().err


def test_batches_flip_image_and_probe_together(tmp_path):
    write_pack(write_pack_dataset(tmp_path / "data"), "train", tmp_path / "p.npz", lighting_size=8)
    pack = load_pack(tmp_path / "p.npz")
    tok = PixelTokenizer(8)
    idx, target = torch.tensor([0, 2]), torch.tensor([1, 0])
    plain = make_batch(pack, tok, idx, target, torch.tensor([False, False]))
    flipped = make_batch(pack, tok, idx, target, torch.tensor([True, False]))
    assert torch.equal(tok.decode(flipped["relit"])[0], tok.decode(plain["relit"])[0].flip(-1))
    assert torch.equal(flipped["relit"][1], plain["relit"][1])
    # Input is the other light's image; the lighting is the target light's probe.
    assert torch.equal(tok.decode(plain["input"])[0, :, 0], pack["rgb"][0, 0].float() / 127.5 - 1)
    ldr = lighting.encode_lighting(lighting.upsample_panorama(pack["env"][2, 0][None], 32, 32))["env_ldr"]
    assert torch.allclose(tok.decode(plain["lighting"][1:2, :192])[0, :, 0], ldr[0].permute(2, 0, 1), atol=1e-6)
    # The flipped probe: radiance mirrored, directions unchanged.
    dir_plain, dir_flipped = plain["lighting"][0, 2 * 193:3 * 193 - 1], flipped["lighting"][0, 2 * 193:3 * 193 - 1]
    assert torch.equal(dir_plain, dir_flipped)


def test_batches_reorder_the_colours_of_frames_and_probe_alike(tmp_path):
    """An item with its colours reordered is the item of a pack whose frames and probes were reordered by hand."""
    write_pack(write_pack_dataset(tmp_path / "data"), "train", tmp_path / "p.npz", lighting_size=8)
    pack = load_pack(tmp_path / "p.npz")
    tok = PixelTokenizer(8)
    idx, target, flip = torch.tensor([0, 2, 1]), torch.tensor([1, 0, 1]), torch.tensor([False, True, False])
    colours = torch.tensor([[1, 2, 0], [0, 1, 2], [2, 1, 0]])           # the second unchanged
    got = make_batch(pack, tok, idx, target, flip, colours=colours)
    plain = make_batch(pack, tok, idx, target, flip)
    for i, order in enumerate(([1, 2, 0], [0, 1, 2], [2, 1, 0])):
        by_hand = {"rgb": pack["rgb"][idx[i]:idx[i] + 1][:, :, order], "albedo": pack["albedo"][idx[i]:idx[i] + 1][:, order],
                   "env": pack["env"][idx[i]:idx[i] + 1][..., order], "names": [pack["names"][idx[i]]],
                   "lighting_size": pack["lighting_size"]}
        want = make_batch(by_hand, tok, torch.tensor([0]), target[i:i + 1], flip[i:i + 1])
        for key in ("input", "relit", "albedo", "lighting"):
            assert torch.allclose(got[key][i:i + 1], want[key], atol=1e-6), (i, key)
    assert torch.equal(got["relit"][1], plain["relit"][1])             # the identity order leaves the item as it was
    assert not torch.allclose(got["relit"][0], plain["relit"][0])      # another one does not
    assert not torch.allclose(got["lighting"][2], plain["lighting"][2])


def test_batches_relight_between_mixtures_of_the_two_probes_in_linear_light(tmp_path):
    write_pack(write_pack_dataset(tmp_path / "data"), "train", tmp_path / "p.npz", lighting_size=8)
    pack = load_pack(tmp_path / "p.npz")
    tok = PixelTokenizer(8)
    idx, target, no_flip = torch.tensor([0, 2]), torch.tensor([1, 0]), torch.tensor([False, False])
    plain = make_batch(pack, tok, idx, target, no_flip)
    unmixed = make_batch(pack, tok, idx, target, no_flip, torch.tensor([[1.0, 0.0], [1.0, 0.0]]))
    for key in ("input", "relit", "albedo", "lighting"):
        assert torch.allclose(unmixed[key], plain[key], atol=1e-5), key
    w, v = 0.7, 0.2
    mixed = make_batch(pack, tok, idx, target, no_flip, torch.tensor([[w, v], [1.0, 0.0]]))
    # Scene 0, target light 1: the relit frame is sRGB(w·lin(rgb1) + (1−w)·lin(rgb0)), the input
    # sRGB(v·lin(rgb1) + (1−v)·lin(rgb0)), by colour-science's curve; the albedo does not change.
    science = colour_science().models
    on, off = (science.eotf_sRGB(pack["rgb"][0, k].double().numpy() / 255) for k in (1, 0))
    relit = science.eotf_inverse_sRGB(w * on + (1 - w) * off) * 2 - 1
    source = science.eotf_inverse_sRGB(v * on + (1 - v) * off) * 2 - 1
    np.testing.assert_allclose(tok.decode(mixed["relit"])[0, :, 0].numpy(), relit, atol=2e-5)
    np.testing.assert_allclose(tok.decode(mixed["input"])[0, :, 0].numpy(), source, atol=2e-5)
    assert not np.allclose(relit, tok.decode(plain["relit"])[0, :, 0].numpy(), atol=1e-2)
    assert torch.equal(mixed["albedo"], plain["albedo"]) and torch.allclose(mixed["relit"][1], plain["relit"][1], atol=1e-5)
    # The lighting is the same mixture of the two linear probes, then encoded.
    probe = w * pack["env"][0, 1] + (1 - w) * pack["env"][0, 0]
    ldr = lighting.encode_lighting(lighting.upsample_panorama(probe[None], 32, 32))["env_ldr"]
    assert torch.allclose(tok.decode(mixed["lighting"][0:1, :192])[0, :, 0], ldr[0].permute(2, 0, 1), atol=1e-5)


def test_light_mixes_keep_each_item_mostly_one_probe():
    generator = torch.Generator().manual_seed(0)
    assert torch.equal(light_mix(64, 0.0, generator, torch.device("cpu")), torch.tensor([[1.0, 0.0]]).expand(64, 2))
    mixes = light_mix(4000, 0.5, generator, torch.device("cpu"))
    mixed = (mixes != torch.tensor([1.0, 0.0])).any(1)
    assert 0.45 < mixed.float().mean() < 0.55
    target, source = mixes[mixed].unbind(1)
    assert target.min() >= 0.5 and target.max() <= 1 and source.min() >= 0 and source.max() <= 0.5
    assert target.std() > 0.1 and source.std() > 0.1


def test_mix_and_crop_shares_outside_their_range_are_refused_before_anything_loads(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--pack", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "run"), "--mix-lights", "1.5"])
    assert exit_info.value.code == 2
    assert "--mix-lights is a share of items, from 0 to 1; got 1.5" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
    for flags, message in ((["--crop", "0.5", "--crop-min", "0"], "--crop-min a fraction of the frame in (0, 1]"),
                           (["--crop", "0.5"], "--crop zooms into the packs' full-size images, so it needs a smaller "
                                              "--train-size")):
        with pytest.raises(SystemExit) as exit_info:
            main(["--pack", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "run"), *flags])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_fast_training_on_a_device_this_machine_lacks_says_so_in_one_sentence(tmp_path, capsys):
    # no machine has 64 GPUs; one without any says so, one with some names how many it has
    write_pack(write_pack_dataset(tmp_path / "data"), "train", tmp_path / "p.npz", lighting_size=8)
    with pytest.raises(SystemExit) as exit_info:
        main(["--pack", str(tmp_path / "p.npz"), "--out", str(tmp_path / "run"), "--device", "cuda:64"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    if torch.cuda.is_available():
        assert "There is no GPU cuda:64: this machine has" in err
    else:
        assert "The device 'cuda:64' was asked for, but this machine has no usable CUDA GPU" in err
    assert not (tmp_path / "run").exists()


def test_fast_training_exports_a_model_the_relighter_runs(tmp_path):
    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    config = FastConfig(pack=tmp_path / "p.npz", out=tmp_path / "run", minutes=0.02, device="cpu", batch=2,
                        width=32, depth=1, num_heads=2, log_every=1, eval_items=2, eval_steps=2, warmup=1)
    summary = train(config)
    assert summary["steps"] >= 1 and set(summary["sampled_psnr"]["train"]) == {"relit", "albedo", "floor", "margin"}
    model = tmp_path / "run" / "model"
    assert (model / DIT_FILE).is_file() and not (model / TOKENIZER_FILE).exists()
    merged = merge_shards(tmp_path / "run", tmp_path / "run" / "config.json", tmp_path / "merged")
    from safetensors.torch import load_file
    a, b = load_file(str(model / DIT_FILE)), load_file(str(merged / DIT_FILE))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    spec = json.loads((model / "config.json").read_text())
    assert spec["tokenizer"] == {"type": "pixel", "patch": 8} and spec["lighting_size"] == 8
    spec, dit, tok = load_model(model)
    assert isinstance(tok, PixelTokenizer) and spec.chunk_frames == 1
    relighter = Relighter(spec, dit, tok)
    frames = np.random.default_rng(1).random((3, 32, 32, 3)).astype(np.float32)
    result = relighter.relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32), steps=2))
    assert result.relit.shape == frames.shape and result.info["chunks"] == 3
    assert np.isfinite(result.albedo).all()


def test_accumulate_steps_once_on_the_mean_gradient_of_its_micro_batches(tmp_path, monkeypatch):
    """--accumulate k: each optimizer step draws k micro-batches and uses the mean of their gradients."""
    import relight_core.training.fast as fast
    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    micro, steps = [], []                      # per micro-batch: (items, grad of the head); per step: its grad
    original_loss, original_clip = fast.denoising_loss, torch.nn.utils.clip_grad_norm_

    def loss_spy(net, example, recipe, generator):
        loss, sigma = original_loss(net, example, recipe, generator)
        head = net.final_layer.linear.weight
        micro.append((example.x0.shape[0], torch.autograd.grad(loss, head, retain_graph=True)[0].clone()))
        return loss, sigma

    def clip_spy(parameters, max_norm, *args, **kwargs):
        parameters = list(parameters)
        head = next(p for p in parameters if p.shape[0] == 192 and p.dim() == 2 and p.shape[1] == 32)
        steps.append(head.grad.clone())
        return original_clip(parameters, max_norm, *args, **kwargs)

    monkeypatch.setattr(fast, "denoising_loss", loss_spy)
    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", clip_spy)
    summary = train(FastConfig(pack=tmp_path / "p.npz", out=tmp_path / "run", minutes=0.03, device="cpu", batch=2,
                               accumulate=3, width=32, depth=1, num_heads=2, log_every=1, eval_items=2,
                               eval_steps=1, warmup=1))
    assert summary["steps"] >= 1 and len(steps) == summary["steps"] and len(micro) == 3 * summary["steps"]
    assert summary["samples_seen"] == 6 * summary["steps"] and {n for n, _ in micro} == {2}
    for i, grad in enumerate(steps):
        parts = [g for _, g in micro[3 * i:3 * i + 3]]
        assert not torch.allclose(parts[0], parts[1])          # each micro-batch draws its own items and noise
        mean = sum(parts) / 3                                   # to bf16's rounding where autocast runs
        assert (grad - mean).norm() <= 1e-2 * mean.norm() and (grad - parts[0]).norm() > 0.1 * mean.norm()
    assert json.loads((tmp_path / "run" / "model" / "config.json").read_text())["notes"]["batch"] == 6
    with pytest.raises(SystemExit):
        main(["--pack", str(tmp_path / "p.npz"), "--out", str(tmp_path / "bad"), "--accumulate", "0"])


def test_a_residual_models_offset_filter_smooths_what_it_changed_and_scales_with_the_size():
    torch.manual_seed(0)
    config = DiTConfig(width=32, depth=1, num_heads=2, patch_spatial=1, patch_temporal=1, out_channels=192,
                       cross_attention=False, adaln_lora_dim=8)
    dit = JointDiT(config)
    torch.nn.init.normal_(dit.final_layer.linear.weight, std=0.05)    # a model whose offsets are blotchy
    tok = build_tokenizer({"type": "pixel", "patch": 8})
    spec = ModelSpec(name="r", dit=config, tokenizer={"type": "pixel", "patch": 8}, chunk_frames=1,
                     overlap_frames=0, size=32, steps=1, lighting_size=8, residual=True)
    frames = np.random.default_rng(1).random((1, 32, 32, 3)).astype(np.float32)
    request = RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32))
    raw = Relighter(spec, dit, tok).relight(request)
    filtered = Relighter(replace(spec, offset_filter=(3, 2)), dit, tok).relight(request)
    np.testing.assert_allclose(filtered.relit, smooth_offset(frames, raw.relit, 3), atol=1e-5)
    np.testing.assert_allclose(filtered.albedo, smooth_offset(frames, raw.albedo, 2), atol=1e-5)
    assert np.abs(filtered.relit - raw.relit).mean() > 1e-3             # it did something
    # Frames at twice the model's size get twice the radius.
    big = np.random.default_rng(2).random((1, 64, 64, 3)).astype(np.float32)
    big_request = replace(request, frames=big)
    raw_big = Relighter(spec, dit, tok).relight(big_request)
    filtered_big = Relighter(replace(spec, offset_filter=(3, 0)), dit, tok).relight(big_request)
    np.testing.assert_allclose(filtered_big.relit, smooth_offset(big, raw_big.relit, 6), atol=1e-5)
    np.testing.assert_allclose(filtered_big.albedo, raw_big.albedo, atol=1e-6)
    # Render mode (albedo → relit) has no input to take an offset from: the filter stays out of it.
    render = replace(request, mode="render", albedo=frames)
    np.testing.assert_array_equal(Relighter(replace(spec, offset_filter=(3, 2)), dit, tok).relight(render).relit,
                                  Relighter(spec, dit, tok).relight(render).relit)


def test_a_zero_head_residual_model_returns_its_input_and_training_resumes(tmp_path, capsys):
    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    base = dict(pack=tmp_path / "p.npz", device="cpu", batch=2, width=32, depth=1, num_heads=2, log_every=1,
                eval_items=2, eval_steps=1, warmup=1, checkpoint_every_minutes=0.0)
    first = train(FastConfig(out=tmp_path / "first", minutes=0.02, **base))
    # Continue it as a residual model with its output layer zeroed, and a learning rate of 0: the
    # model then is exactly "return the input" (relit and albedo), whatever its other weights.
    residual = FastConfig(out=tmp_path / "res", minutes=0.01, init=tmp_path / "first" / "model", zero_head=True,
                          lr=0.0, recipe=Recipe(residual=True, p_sigma_max=0.75), **base)
    train(residual)
    spec, dit, tok = load_model(tmp_path / "res" / "model")
    assert spec.residual and spec.steps == 1
    frames = np.random.default_rng(2).random((1, 32, 32, 3)).astype(np.float32)
    result = Relighter(spec, dit, tok).relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    np.testing.assert_allclose(result.relit, frames, atol=0.02)
    np.testing.assert_allclose(result.albedo, frames, atol=0.02)
    plain, _, _ = load_model(tmp_path / "first" / "model")
    assert not plain.residual
    # Calibration (training.calibrate) measures the offset gains on items and writes the best into
    # config.json, which Relighter then applies; a gain of 0 returns the input exactly.
    from relight_core.training import calibrate

    data = tmp_path / "data"
    model = tmp_path / "res" / "model"
    assert calibrate.main(["--model", str(model), "--data", str(data), "--split", "train", "--items", "2",
                           "--write"]) == 0
    written = json.loads((model / "config.json").read_text())
    assert len(written["residual_gain"]) == 2 and set(written["notes"]["calibration"]["table"]) == {
        str(g) for g in calibrate.GRID}
    assert load_model(model)[0].residual_gain == tuple(written["residual_gain"])
    zero = Relighter(replace(spec, residual_gain=(0.0, 0.0)), dit, tok)
    result = zero.relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    np.testing.assert_allclose(result.relit, frames, atol=1e-5)
    assert set(written["notes"]["calibration"]["table"]["0.5"]) == {str(r) for r in calibrate.RADII}
    assert tuple(written["offset_filter"]) == load_model(model)[0].offset_filter
    with pytest.raises(SystemExit):       # no refiner: no strength to fit, said in one sentence
        calibrate.main(["--model", str(model), "--data", str(data), "--split", "train", "--items", "2", "--strengths"])
    assert "has no refiner; --strengths fits refiners' strengths" in capsys.readouterr().err
    assert calibrate.best_gains({(0.5, 0): {"relit": 20.0, "albedo": 18.0}, (1.0, 0): {"relit": 19.0, "albedo": 19.0},
                                 (0.5, 4): {"relit": 20.5, "albedo": 17.0}, (1.0, 4): {"relit": 20.5, "albedo": 19.0}}) \
        == ((0.5, 4), (1.0, 0))   # best each; a tie goes to the smaller gain, then the smaller radius
    # The first run left a checkpoint (weights, EMA, optimizer, generator, step, time used): started
    # again on the same folder it resumes there and, its time spent, stops without a new step.
    again = train(FastConfig(out=tmp_path / "first", minutes=0.02, **base))
    log = [json.loads(line) for line in (tmp_path / "first" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if r.get("event") == "resume"] == [first["steps"]]
    assert again["steps"] == first["steps"]


def test_a_validation_pack_exports_the_best_ema_not_the_last(tmp_path):
    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    base = dict(pack=tmp_path / "p.npz", device="cpu", batch=2, width=32, depth=1, num_heads=2, log_every=1000,
                eval_items=2, eval_steps=1, warmup=1)
    train(FastConfig(out=tmp_path / "first", minutes=0.01, **base))
    # From a zero-head residual init ("return the input") at a learning rate that wrecks the weights
    # within a step: the EMA scored at step 0 stays the best, and that is what is exported.
    summary = train(FastConfig(out=tmp_path / "wild", minutes=0.03, init=tmp_path / "first" / "model",
                               zero_head=True, lr=50.0, ema_decay=0.0, val_pack=tmp_path / "p.npz",
                               val_every_minutes=0.0, val_items=2, recipe=Recipe(residual=True), **base))
    log = [json.loads(line) for line in (tmp_path / "wild" / "log.jsonl").read_text().splitlines()]
    vals = [r for r in log if r.get("event") == "val"]
    assert vals[0]["step"] == 0 and vals[0]["best"] and vals[-1]["step"] == summary["steps"] >= 1
    assert not any(r["best"] for r in vals[1:]) and summary["selected"]["step"] == 0
    spec, dit, tok = load_model(tmp_path / "wild" / "model")
    assert spec.notes["selected"]["step"] == 0 and spec.notes["selected"]["val"]["relit"] == vals[0]["relit"]
    frames = np.random.default_rng(2).random((1, 32, 32, 3)).astype(np.float32)
    result = Relighter(spec, dit, tok).relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    np.testing.assert_allclose(result.relit, frames, atol=0.02)
    np.testing.assert_allclose(result.albedo, frames, atol=0.02)
    # Started again on the same folder it resumes from its checkpoint, best EMA included: its time
    # spent, it takes no step and still exports the step-0 weights.
    again = train(FastConfig(out=tmp_path / "wild", minutes=0.03, init=tmp_path / "first" / "model",
                             zero_head=True, lr=50.0, ema_decay=0.0, val_pack=tmp_path / "p.npz",
                             val_every_minutes=0.0, val_items=2, recipe=Recipe(residual=True), **base))
    assert again["steps"] == summary["steps"] and again["selected"]["step"] == 0
    # Without the validation pack the same run exports its last EMA, which has moved off the input.
    train(FastConfig(out=tmp_path / "last", minutes=0.01, init=tmp_path / "first" / "model", zero_head=True,
                     lr=50.0, ema_decay=0.0, recipe=Recipe(residual=True), **base))
    spec, dit, tok = load_model(tmp_path / "last" / "model")
    moved = Relighter(spec, dit, tok).relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    assert "selected" not in spec.notes and not np.allclose(moved.relit, frames, atol=0.02)


def test_pieces_keep_the_newest_unseen_scenes_for_validation_and_each_fits_its_size(tmp_path, capsys):
    from relight_core.training.pieces import cut_pack
    from relight_core.training.pieces import main as pieces_main

    root = write_pack_dataset(tmp_path / "data", scenes=6)
    write_pack(root, "train", tmp_path / "all.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "seen.npz", lighting_size=8, limit=2)      # scenes 0 and 1 trained on
    whole = load_pack(tmp_path / "all.npz")
    counts = cut_pack(tmp_path / "all.npz", tmp_path / "out", [100.0, 100.0], seen=tmp_path / "seen.npz", val=1)
    assert counts == {"val": 1, "p1": 5, "p2": 0, "left": 0} and not (tmp_path / "out" / "p2.npz").exists()
    val, piece = load_pack(tmp_path / "out" / "val.npz"), load_pack(tmp_path / "out" / "p1.npz")
    assert val["names"] == [whole["names"][5]]                                    # the newest unseen scene
    order = (2, 3, 4, 0, 1)                                                       # unseen first, then seen
    assert piece["names"] == [whole["names"][i] for i in order]
    for key in ("rgb", "albedo", "mask", "env"):                                  # the scenes themselves, unchanged
        assert torch.equal(piece[key], whole[key][list(order)]) and torch.equal(val[key], whole[key][[5]])
    # Pieces of about two scenes' size each: every piece fits, and what does not fit is counted.
    small = 2.5 * (tmp_path / "all.npz").stat().st_size / 1e6 / 6
    counts = cut_pack(tmp_path / "all.npz", tmp_path / "tight", [small, small])
    sizes = [(tmp_path / "tight" / f"p{i}.npz").stat().st_size / 1e6 for i in (1, 2)]
    assert max(sizes) <= small and counts["p1"] >= 1 and counts["p1"] + counts["p2"] + counts["left"] == 6
    assert load_packs([tmp_path / "tight" / "p1.npz", tmp_path / "tight" / "p2.npz"])["names"] == \
        whole["names"][:counts["p1"] + counts["p2"]]
    # Several --seen packs: their scenes together count as trained on.
    write_pack(root, "train", tmp_path / "first4.npz", lighting_size=8, limit=4)
    pieces_main(["--pack", str(tmp_path / "all.npz"), "--out", str(tmp_path / "two"), "--pieces", "50",
                 "--seen", str(tmp_path / "seen.npz"), str(tmp_path / "first4.npz"), "--val", "1"])
    assert capsys.readouterr().out.split() == ["val", "1", "p1", "5", "left", "0"]
    assert load_pack(tmp_path / "two" / "val.npz")["names"] == [whole["names"][5]]
    assert load_pack(tmp_path / "two" / "p1.npz")["names"] == [whole["names"][i] for i in (4, 0, 1, 2, 3)]
    with pytest.raises(SystemExit):
        pieces_main(["--pack", str(tmp_path / "all.npz"), "--out", str(tmp_path / "x"), "--pieces", "50",
                     "--val", "7"])
    assert "--val 7 asks for more scenes than the 6" in capsys.readouterr().err


def test_pick_keeps_the_best_of_runs_their_mean_and_the_start_on_the_validation_pack(tmp_path, capsys):
    from safetensors.torch import load_file

    from relight_core.training.pick import pick

    root = write_pack_dataset(tmp_path / "data")
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    base = dict(pack=tmp_path / "p.npz", device="cpu", batch=2, width=32, depth=1, num_heads=2, log_every=1000,
                eval_items=2, eval_steps=1, warmup=1, minutes=0.01, recipe=Recipe(residual=True))
    train(FastConfig(out=tmp_path / "start", zero_head=True, lr=0.0, **base))   # "return the input"
    start = tmp_path / "start" / "model"
    for name, seed in (("a", 1), ("b", 2)):
        train(FastConfig(out=tmp_path / name, init=start, lr=1e-2, seed=seed, **base))
    runs = [tmp_path / "a" / "model", tmp_path / "b" / "model"]
    result = pick(runs, tmp_path / "p.npz", tmp_path / "out", init=start, items=3, device="cpu",
                  model_dir=tmp_path / "picked")
    scores = result["scores"]
    assert set(scores) == {str(runs[0]), str(runs[1]), "mean", "mean with init", "init"}
    # The best score wins (a run too short to move its EMA ties with the start, and a tie keeps the start).
    total = {n: scores[n]["relit"] + scores[n]["albedo"] for n in scores}
    assert total[result["best"]] == max(total.values())
    merged = merge_shards(tmp_path / "out", tmp_path / "out" / "config.json", tmp_path / "merged")
    picked = load_file(str(tmp_path / "picked" / DIT_FILE))
    assert all(torch.equal(v, picked[k]) for k, v in load_file(str(merged / DIT_FILE)).items())
    if result["best"] == str(runs[0]):  # the shards hold the winner's weights
        assert all(torch.equal(v, picked[k]) for k, v in load_file(str(runs[0] / DIT_FILE)).items())
    spec = json.loads((tmp_path / "out" / "config.json").read_text())
    assert spec["notes"]["picked"]["from"] == result["best"] and spec["residual"]
    assert json.loads((tmp_path / "out" / "pick.json").read_text())["best"] == result["best"]
    # A run that changed nothing ties with its start: the start is kept.
    same = pick([start], tmp_path / "p.npz", tmp_path / "same", init=start, items=3, device="cpu")
    assert same["best"] == "init" and len(set(map(str, same["scores"].values()))) == 1
    # Its command line refuses a start folder without weights in one sentence, before loading anything.
    from relight_core.training.pick import main as pick_main

    with pytest.raises(SystemExit):
        pick_main([str(runs[0]), "--val", str(tmp_path / "p.npz"), "--out", str(tmp_path / "no"),
                   "--init", str(tmp_path / "nowhere")])
    assert f"--init {tmp_path / 'nowhere'} holds no {DIT_FILE}" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_training_at_a_smaller_size_shrinks_the_packs_as_the_pipeline_shrinks_frames(tmp_path):
    from relight_core import media
    from relight_core.evaluation.harness import load_items, resized
    from relight_core.evaluation.metrics import protocol_psnr
    from relight_core.training import calibrate
    from relight_core.training.fast import shrink_pack

    root = write_pack_dataset(tmp_path / "data", size=32)
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    pack = load_pack(tmp_path / "p.npz")
    small = shrink_pack(pack, 16)
    assert small["rgb"].shape == (3, 2, 3, 16, 16) and small["rgb"].dtype == torch.uint8
    assert small["albedo"].shape == (3, 3, 16, 16) and small["mask"].shape == (3, 16, 16)
    assert small["mask"].dtype == torch.bool and torch.equal(small["env"], pack["env"])   # probes stay
    # The images shrink as Relighter's callers shrink frames (antialiased bilinear), to within rounding.
    image = pack["rgb"][1, 0].permute(1, 2, 0)[None].float().numpy() / 255
    expected = media.resize_frames(image, 16, multiple=8)[0] * 255
    assert np.abs(small["rgb"][1, 0].permute(1, 2, 0).float().numpy() - expected).max() <= 0.51
    assert shrink_pack(pack, 32) is pack
    for bad in (12, 64):
        with pytest.raises(ValueError, match="--train-size"):
            shrink_pack(pack, bad)
    # A run with --train-size (here every item a zoomed crop of the 32-px images) exports a model that
    # works at that size ...
    train(FastConfig(pack=tmp_path / "p.npz", out=tmp_path / "run", device="cpu", batch=2, width=32, depth=1,
                     num_heads=2, log_every=1, eval_items=2, eval_steps=1, warmup=1, minutes=0.01, train_size=16,
                     crop=1.0, recipe=Recipe(residual=True)))
    spec, dit, tok = load_model(tmp_path / "run" / "model")
    assert spec.size == 16 and spec.residual and spec.notes["crop"] == {"share": 1.0, "smallest": 0.5}
    # ... and calibrating it at its data's size scores the results brought back there: at gain 0 (the
    # input unchanged at 16 px, ratio 1) the score is the input-copy floor at 32 px exactly.
    relighter = Relighter(spec, dit, tok)
    items = [resized(item, 32, 8) for item in load_items(root, "train", 2)]
    table = calibrate.measure_gains(relighter, items, grid=(0.0, 1.0), radii=(0, 2))
    floor = np.mean([protocol_psnr(item.input, item.target, item.mask) for item in items])
    assert table[0.0, 0]["relit"] == pytest.approx(floor, abs=1e-4)
    assert table[0.0, 2]["relit"] == pytest.approx(floor, abs=1e-4)
    assert set(table) == {(0.0, 0), (0.0, 2), (1.0, 0), (1.0, 2)}
    # Unless asked for another, the filter's eps is the one Relighter uses.
    from relight_core.upsample import GUIDE_EPS
    assert calibrate.measure_gains(relighter, items, grid=(1.0,), radii=(2,), eps=GUIDE_EPS) == \
        {key: table[key] for key in [(1.0, 2)]}
    # Several regularisations from one sampling pass: each the same as measured alone, and they differ.
    filters = calibrate.measure_filters(relighter, items, (1.0,), (2,), (GUIDE_EPS, 1.0))
    assert set(filters) == {(1.0, 2, GUIDE_EPS), (1.0, 2, 1.0)} and filters[1.0, 2, GUIDE_EPS] == table[1.0, 2]
    assert filters[1.0, 2, 1.0] == calibrate.measure_gains(relighter, items, grid=(1.0,), radii=(2,), eps=1.0)[1.0, 2]
    assert filters[1.0, 2, 1.0] != filters[1.0, 2, GUIDE_EPS]
    # At the model's own size the same calibration scores the 16-px floor, another number.
    small_items = [resized(item, 16, 8) for item in load_items(root, "train", 2)]
    small_floor = np.mean([protocol_psnr(item.input, item.target, item.mask) for item in small_items])
    assert calibrate.measure_gains(relighter, small_items, grid=(0.0,), radii=(0,))[0.0, 0]["relit"] == \
        pytest.approx(small_floor, abs=1e-4)
    assert abs(small_floor - floor) > 1e-2


def test_crops_zoom_into_the_full_size_images_and_keep_the_probes(tmp_path):
    from relight_core.training.fast import crop_draws, crop_items, shrink_pack

    write_pack(write_pack_dataset(tmp_path / "data", size=32), "train", tmp_path / "p.npz", lighting_size=8)
    full = load_pack(tmp_path / "p.npz")
    small = shrink_pack(full, 16)
    idx = torch.tensor([2, 0, 2])
    # Side 1 is the shrunk item; side ½ at the right, top corner is the full image's 16×16 there,
    # pixel for pixel (nothing to shrink); side ¾ is a 24-px crop shrunk to 16.
    items = crop_items(full, small, idx, torch.tensor([[1.0, 0.3, 0.9], [0.5, 1.0, 0.0], [0.75, 0.0, 1.0]]))
    assert torch.equal(items["rgb"][0], small["rgb"][2]) and torch.equal(items["albedo"][0], small["albedo"][2])
    assert torch.equal(items["rgb"][1], full["rgb"][0][..., :16, 16:])
    assert torch.equal(items["albedo"][1], full["albedo"][0][..., :16, 16:])
    crop = full["rgb"][2][..., 8:, :24].reshape(6, 24, 24)[None].float()
    shrunk = torch.nn.functional.interpolate(crop, size=(16, 16), mode="bilinear", antialias=True, align_corners=False)
    assert torch.equal(items["rgb"][2], shrunk[0].round().to(torch.uint8).reshape(2, 3, 16, 16))
    assert not torch.equal(items["rgb"][2], small["rgb"][2])
    assert torch.equal(items["env"], full["env"][idx])    # the camera-frame probes stay
    # make_batch takes the items as a pack of their own.
    batch = make_batch(items, PixelTokenizer(8), torch.arange(3), torch.tensor([0, 1, 0]), torch.zeros(3, dtype=torch.bool))
    assert torch.equal(PixelTokenizer(8).decode(batch["relit"])[1, :, 0], full["rgb"][0, 1][..., :16, 16:].float() / 127.5 - 1)
    # The draws: a share of items cropped, their sides within [smallest, 1).
    draws = crop_draws(4000, 0.25, 0.5, torch.Generator().manual_seed(0), torch.device("cpu"))
    cropped = draws[:, 0] < 1
    assert 0.22 < cropped.float().mean() < 0.28 and draws[cropped, 0].min() >= 0.5
    assert ((draws[:, 1:] >= 0) & (draws[:, 1:] < 1)).all()
    assert torch.equal(crop_draws(8, 0.0, 0.5, torch.Generator(), torch.device("cpu"))[:, 0], torch.ones(8))
