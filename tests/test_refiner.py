"""The default model's detail refiner: what it adds in the Relighter, its config and weights, and its
training on a frozen DiT's outputs (relight_core/refiner.py, relight_core/training/refine.py)."""

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from torch.nn import functional as F

from relight_core.checkpoint import ModelSpec, load_model, load_refiner, resolve_model
from relight_core.dit import DiTConfig, JointDiT
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.refiner import LIGHT_FEATURES, REFINER_FILE, RELIT_REFINER_FILE, Refiner, RefinerConfig, light_features
from relight_core.tokenizer import build_tokenizer
from relight_core.training import refine
from relight_core.training.fast import FastConfig, train
from relight_core.training.pack import write_pack
from relight_core.training.recipe import Recipe
from relight_core.upsample import smooth_offset
from tests.factory import write_pack_dataset

SMALL = RefinerConfig(widths=(4, 8), blocks=1)


def residual_model():
    torch.manual_seed(0)
    config = DiTConfig(width=32, depth=1, num_heads=2, patch_spatial=1, patch_temporal=1, out_channels=192,
                       cross_attention=False, adaln_lora_dim=8)
    dit = JointDiT(config)
    torch.nn.init.normal_(dit.final_layer.linear.weight, std=0.05)    # offsets of its own
    spec = ModelSpec(name="r", dit=config, tokenizer={"type": "pixel", "patch": 8}, chunk_frames=1,
                     overlap_frames=0, size=32, steps=1, lighting_size=8, residual=True, offset_filter=(3, 2))
    return spec, dit, build_tokenizer(spec.tokenizer)


def _randomised(refiner: Refiner, std: float) -> Refiner:
    """`refiner` with every weight drawn from N(0, std²) (seeded by the test): one that changes its frames."""
    for parameter in refiner.parameters():
        torch.nn.init.normal_(parameter, std=std)
    return refiner


def test_the_refiner_adds_its_correction_to_the_dit_frames_or_the_filtered_ones_and_stays_out_of_render():
    spec, dit, tok = residual_model()
    frames = np.random.default_rng(1).random((2, 32, 32, 3)).astype(np.float32)
    request = RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32))
    plain = Relighter(replace(spec, offset_filter=(0, 0)), dit, tok).relight(request)
    filtered = Relighter(spec, dit, tok).relight(request)
    # An untrained refiner (its head is zero) changes nothing: the raw frames, or the filtered ones.
    raw_refiner, filtered_refiner = Refiner(SMALL), Refiner(replace(SMALL, base="filtered"))
    np.testing.assert_allclose(Relighter(spec, dit, tok, refiner=raw_refiner).relight(request).relit, plain.relit,
                               atol=1e-5)
    same = Relighter(spec, dit, tok, refiner=filtered_refiner).relight(request)
    np.testing.assert_allclose(same.albedo, filtered.albedo, atol=1e-5)
    np.testing.assert_allclose(same.relit, smooth_offset(frames, plain.relit, 3), atol=1e-5)
    # With a head that adds a constant to the relit frames and another to the albedo, that is what comes out.
    with torch.no_grad():
        filtered_refiner.head.bias.copy_(torch.tensor([0.2, 0.2, 0.2, -0.4, -0.4, -0.4]))
    moved = Relighter(spec, dit, tok, refiner=filtered_refiner).relight(request)
    np.testing.assert_allclose(moved.relit, np.clip(filtered.relit + 0.1, 0, 1), atol=2e-3)  # bf16 where the CPU has it
    np.testing.assert_allclose(moved.albedo, np.clip(filtered.albedo - 0.2, 0, 1), atol=2e-3)
    # A refiner for the albedo alone leaves the relit frames as the offset filter made them.
    albedo_only = Refiner(replace(SMALL, base="filtered", clips=("albedo",)))
    albedo_only.load_state_dict(filtered_refiner.state_dict())
    half = Relighter(spec, dit, tok, refiner=albedo_only).relight(request)
    np.testing.assert_array_equal(half.relit, filtered.relit)
    np.testing.assert_allclose(half.albedo, moved.albedo, atol=1e-6)
    # Render mode (albedo → relit) has no input photo to refine against: the refiner stays out.
    render = replace(request, mode="render", albedo=frames)
    np.testing.assert_array_equal(Relighter(spec, dit, tok, refiner=filtered_refiner).relight(render).relit,
                                  Relighter(spec, dit, tok).relight(render).relit)


def test_the_refiner_takes_frames_of_any_size_and_learns_a_correction():
    refiner = Refiner(RefinerConfig(widths=(4, 8, 8), blocks=1))
    for height, width in ((36, 20), (3, 5), (64, 64)):
        x = torch.rand(1, 3, height, width) * 2 - 1
        relit, albedo = refiner.refine(x, x, x)
        assert relit.shape == albedo.shape == x.shape
    # A few steps of its loss on one item bring its output towards that item's target.
    torch.manual_seed(0)
    inputs = torch.rand(2, 9, 16, 16) * 2 - 1
    target = (inputs[:, 3:6] * 0.5 + 0.3).clamp(-1, 1)
    mask = torch.ones(2, 16, 16, dtype=torch.bool)
    optimizer = torch.optim.Adam(refiner.parameters(), lr=1e-2)
    losses = []
    for _ in range(60):
        delta = refiner(inputs)
        loss = refine.item_loss(inputs[:, 3:6] + delta[:, :3], target, mask)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] - 1.0       # log MSE: the error fell by more than e×


def test_the_refiner_loss_is_the_protocols_psnr_after_the_scale_fit():
    from relight_core.evaluation.metrics import protocol_psnr

    rng = np.random.default_rng(0)
    target = rng.random((1, 8, 8, 3)).astype(np.float32) * 0.8
    pred = np.clip(target * np.array([0.5, 0.7, 0.9], np.float32) + rng.normal(0, 0.02, target.shape), 0, 1)
    mask = np.ones((1, 8, 8), bool)
    signed = [torch.from_numpy(x).permute(0, 3, 1, 2) * 2 - 1 for x in (pred, target)]
    loss = refine.item_loss(*signed, torch.from_numpy(mask))
    plain = float(((pred - target) ** 2).mean())
    fitted = (loss.item() - 0.5 * np.log(plain + 1e-5))
    # −10·log10 of the fitted error is the protocol's PSNR (the scale fit undoes the channel gains).
    assert abs(-10 / np.log(10) * fitted - protocol_psnr(pred[0], target[0], mask[0])) < 0.05


def test_a_refiner_in_config_json_round_trips_and_a_bad_one_or_a_missing_file_is_one_sentence(tmp_path):
    spec, dit, tok = residual_model()
    data = replace(spec, refiner=SMALL.to_dict()).to_json()
    assert ModelSpec.from_json(json.loads(json.dumps(data))).refiner == SMALL.to_dict()
    assert RefinerConfig.from_dict({"clips": ["albedo"]}).clips == ("albedo",)
    for bad in ({"widths": []}, {"widths": [8, -1]}, {"widths": [8], "blocks": 2.5}, {"base": "sharp"}, "wide", {"clips": []}, {"clips": ["shadows"]}, {"clips": [["relit"]]},
                {"widths": [10 ** 6]}, {"relit_gain": -4}, {"relit_gain": 2.5}, {"strength": 3},
                {"light_detail": 16}, {"lighting": True, "light_detail": 64}, {"film_encoder": True},
                {"transport": 8}, {"reshade": True}, {"colour_average": "yes"}, {"grid_shift": -8}, {"grid_shift": 65},
                {"grid_shift": True}, {"grid_shift": 2.5}):
        with pytest.raises(InputError, match='has refiner .*; it takes "widths".*"relit_gain".*"transport".*"reshade".*'
                                             '"colour_average".*"grid_shift".*"strength"'):
            ModelSpec.from_json({**data, "refiner": bad})
    folder = tmp_path / "model"
    folder.mkdir()
    save_file({k: v.contiguous() for k, v in dit.state_dict().items()}, folder / "dit.safetensors")
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=f"missing {REFINER_FILE}"):
        Relighter.load(str(folder))
    save_file({"stem.weight": torch.zeros(1)}, folder / REFINER_FILE)
    with pytest.raises(InputError, match="do not match"):
        load_refiner(*resolve_model(folder))
    save_file(Refiner(SMALL).state_dict(), folder / REFINER_FILE)
    assert isinstance(Relighter.load(str(folder)).refiner, Refiner)
    assert load_refiner(*resolve_model("tiny")) is None


def test_a_flip_averaged_refiner_corrects_a_frame_and_its_mirror_image_alike_and_says_so_in_its_config():
    torch.manual_seed(4)
    plain = _randomised(Refiner(RefinerConfig(widths=(4, 8), blocks=1, base="filtered", clips=("albedo",))), 0.1)
    config = RefinerConfig.from_dict({**plain.config.to_dict(), "flip_average": True})
    assert config.to_dict()["flip_average"] is True and "flip_average" not in plain.config.to_dict()
    averaged = Refiner(config)
    averaged.load_state_dict(plain.state_dict())
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    with torch.no_grad():
        expected = (plain(x) + plain(x.flip(-1)).flip(-1)) / 2
        assert torch.allclose(averaged.correction(x), expected, atol=1e-6)
        assert not torch.allclose(plain.correction(x), expected, atol=1e-3)    # the plain one differs
        # Mirror the frames and the averaged correction mirrors exactly with them.
        assert torch.allclose(averaged.correction(x.flip(-1)), averaged.correction(x).flip(-1), atol=1e-6)
        frames = [x[:, 3 * k:3 * k + 3] for k in range(5)]
        relit, albedo = averaged.refine(*frames[:3], filtered=(frames[3], frames[4]))
    assert torch.equal(relit, frames[3])                                         # albedo-only: relit is the base's
    assert torch.allclose(albedo, (frames[4] + expected[:, 3:]).clamp(-1, 1), atol=1e-6)
    with pytest.raises(ValueError):
        RefinerConfig.from_dict({"flip_average": "yes"})


def test_colour_permutation_reorders_every_rgb_triple_of_an_item_alike():
    images = torch.rand(3, 15, 4, 5)              # input, relit, albedo and the filtered frames
    order = torch.tensor([[2, 0, 1], [0, 1, 2], [1, 2, 0]])
    out = refine.permute_colours(images, order)
    for item in range(3):
        for frame in range(5):
            for channel in range(3):
                assert torch.equal(out[item, 3 * frame + channel], images[item, 3 * frame + order[item, channel]])


@pytest.mark.parametrize("blocks", [1, 2])
def test_a_refiner_grown_by_a_level_gives_the_same_output_and_then_trains_its_new_level(tmp_path, blocks):
    torch.manual_seed(blocks)
    small = Refiner(RefinerConfig(widths=(4, 8, 12), blocks=blocks, base="filtered"))
    for parameter in small.parameters():          # a trained-looking refiner: every weight counts
        torch.nn.init.normal_(parameter, std=0.2)
    save_file({k: v.contiguous() for k, v in small.state_dict().items()}, tmp_path / "small.safetensors")
    grown = Refiner(RefinerConfig(widths=(4, 8, 12, 16), blocks=blocks, base="filtered"))
    assert refine.initial_weights(grown, tmp_path / "small.safetensors").startswith("grown by a level")
    x = torch.randn(2, 15, 40, 36)                # not a multiple of 8: each level's resize is exercised
    with torch.no_grad():
        assert torch.allclose(grown(x), small(x), atol=1e-5)
    # The new bottom starts out of the way, not dead: the merge's zero weight on it has a gradient, and
    # once one step has moved that weight the new blocks have gradients of their own.
    grown(x).square().mean().backward()
    assert grown.up[2].weight.grad[:, :16].abs().sum() > 0
    assert all(p.grad.abs().sum() == 0 for p in grown.mid.parameters())
    grown.zero_grad()
    with torch.no_grad():
        grown.up[2].weight[:, :16] += 1e-3
    grown(x).square().mean().backward()
    assert all(torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0 for p in grown.mid.parameters())
    # Two levels more, another base, a level and a block more, or fewer blocks is one sentence.
    for config in (RefinerConfig(widths=(4, 8, 12, 16, 16), blocks=blocks, base="filtered"),
                   RefinerConfig(widths=(4, 8, 12, 16), blocks=blocks, base="raw"),
                   RefinerConfig(widths=(4, 8, 12, 16), blocks=blocks + 1, base="filtered"),
                   RefinerConfig(widths=(4, 8, 12), blocks=blocks - 1, base="filtered")):
        with pytest.raises(ValueError, match="nor one with a level fewer or fewer blocks"):
            refine.initial_weights(Refiner(config), tmp_path / "small.safetensors")


@pytest.mark.parametrize("lighting", [False, True])
def test_a_refiner_deepened_by_blocks_gives_the_same_output_and_then_trains_its_new_blocks(tmp_path, lighting):
    torch.manual_seed(3)
    config = dict(widths=(4, 8, 12), base="filtered", lighting=lighting)
    small = Refiner(RefinerConfig(blocks=1, **config))
    for parameter in small.parameters():          # a trained-looking refiner: every weight counts
        torch.nn.init.normal_(parameter, std=0.2)
    save_file({k: v.contiguous() for k, v in small.state_dict().items()}, tmp_path / "small.safetensors")
    deep = Refiner(RefinerConfig(blocks=3, **config))
    assert refine.initial_weights(deep, tmp_path / "small.safetensors").startswith("deepened to 3 residual blocks")
    assert len(deep.enc[0]) == 3 and len(deep.mid) == 6
    x = torch.randn(2, 15, 40, 36)
    light = torch.randn(2, 192) if lighting else None
    with torch.no_grad():
        assert torch.allclose(deep(x, light), small(x, light), atol=1e-5)
    # The trained blocks keep their place and weights; every new block's last convolution has a gradient.
    assert torch.equal(deep.enc[1][0].conv1.weight, small.enc[1][0].conv1.weight)
    assert torch.equal(deep.mid[1].conv2.weight, small.mid[1].conv2.weight)
    deep(x, light).square().mean().backward()
    for new in (deep.enc[0][1], deep.enc[1][2], deep.dec[0][1], deep.mid[2], deep.mid[5]):
        assert new.conv2.weight.abs().sum() == 0 and new.conv2.weight.grad.abs().sum() > 0


def test_refine_trains_on_unseen_scenes_resumes_and_writes_a_model_the_relighter_runs(tmp_path, capsys):
    root = write_pack_dataset(tmp_path / "data", scenes=4)
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "seen.npz", lighting_size=8, limit=1)
    write_pack(root, "train", tmp_path / "val.npz", lighting_size=8, limit=2)    # scenes 0 and 1
    base = dict(pack=tmp_path / "p.npz", device="cpu", batch=2, width=32, depth=1, num_heads=2, log_every=1,
                eval_items=2, eval_steps=1, warmup=1, checkpoint_every_minutes=0.0)
    train(FastConfig(out=tmp_path / "dit", minutes=0.01, recipe=Recipe(residual=True), **base))
    model = tmp_path / "dit" / "model"
    config = json.loads((model / "config.json").read_text())
    config["offset_filter"] = [2, 1]
    (model / "config.json").write_text(json.dumps(config))
    args = ["--model", str(model), "--pack", str(tmp_path / "p.npz"), "--seen", str(tmp_path / "seen.npz"),
            "--val-pack", str(tmp_path / "val.npz"), "--out", str(tmp_path / "run"), "--widths", "4", "8",
            "--batch", "2", "--minutes", "0.03", "--val-every-minutes", "0.01", "--warmup", "2",
            "--model-dir", str(tmp_path / "refined"), "--scenes", "1"]
    assert refine.main(args) == 0
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    # It trains on the first scene neither the DiT (--seen) nor the validation saw, both directions.
    assert best["train_items"] == 2 and best["val_items"] == 4
    first = dict(np.load(tmp_path / "run" / "outputs-train.npz"))
    assert list(first["names"]) == ["scene_000002"] * 2 and first["relit"].shape == (2, 3, 32, 32)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert json.loads((tmp_path / "refined" / "config.json").read_text())["refiner"]["clips"] == ["relit", "albedo"]
    # Run again with more minutes and scenes: it resumes at the step it stopped, computes the DiT's
    # outputs for the new scene only (the cached ones are kept as they were) and goes on, here for the
    # albedo alone, which the model folder it writes then says.
    args[args.index("--minutes") + 1] = "0.06"
    args[args.index("--scenes") + 1] = "2"
    args += ["--clips", "albedo", "--permute-colours", "--flip-average"]
    capsys.readouterr()
    assert refine.main(args) == 0
    out = capsys.readouterr().out
    assert f"resumed at step {log[-1]['step']}" in out
    assert "holds 2 of these 4 items; computing the other 2" in out and "DiT outputs: 2 of 2 items" in out
    cached = np.load(tmp_path / "run" / "outputs-train.npz")
    assert list(cached["names"]) == ["scene_000002"] * 2 + ["scene_000003"] * 2
    assert list(cached["targets"]) == [0, 1, 0, 1]
    assert np.array_equal(cached["relit"][:2], first["relit"]) and np.array_equal(cached["albedo"][:2], first["albedo"])
    assert json.loads((tmp_path / "run" / "best.json").read_text())["train_items"] == 4
    more = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert more[-1]["step"] > log[-1]["step"]
    # Validated as the Relighter uses it: correcting the albedo alone, its relit frames are the filter's.
    start = json.loads((tmp_path / "run" / "best.json").read_text())["start"]["filtered"]["relit"]
    assert more[-1]["val"]["relit"] == pytest.approx(start, abs=1e-3)
    # A new run folder can start from that refiner (--init): at lr 0 its best is those very weights.
    init = ["--init", str(tmp_path / "run" / "refiner.safetensors")]
    fresh = [*args[:args.index("--out") + 1], str(tmp_path / "run2"), *args[args.index("--out") + 2:], *init]
    fresh[fresh.index("--model-dir") + 1] = str(tmp_path / "refined2")
    assert refine.main([*fresh, "--lr", "0", "--minutes", "0.02"]) == 0
    assert "starting from the refiner in" in capsys.readouterr().out
    trained, again = (load_file(tmp_path / r / "refiner.safetensors") for r in ("run", "run2"))
    assert all(torch.equal(trained[k], again[k]) for k in trained)
    # The starting refiner is scored first, so what the run has to beat is on record.
    best2 = json.loads((tmp_path / "run2" / "best.json").read_text())
    assert best2["start"]["init"]["albedo"] == pytest.approx(best2["val"]["albedo"], abs=1e-3)
    with pytest.raises(SystemExit):
        refine.main([*fresh[:fresh.index("--widths")], "--widths", "4", "8", "8", "8", "--out", str(tmp_path / "run3"),
                     "--minutes", "0.02", *init])
    assert "is not a refiner of this shape nor one with a level fewer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        refine.main([*fresh[:fresh.index("--init")], "--init", str(tmp_path / "nowhere.safetensors")])
    assert "no refiner weights at --init" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        refine.main([*fresh, "--alike-weight", "0"])
    assert "--alike-weight takes a number above 0" in capsys.readouterr().err
    relighter = Relighter.load(str(tmp_path / "refined"))
    assert relighter.refiner is not None and relighter.refiner.config.base == "filtered"
    assert relighter.refiner.config.clips == ("albedo",) and relighter.refiner.config.flip_average
    frames = np.random.default_rng(3).random((1, 32, 32, 3)).astype(np.float32)
    result = relighter.relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    assert result.relit.shape == frames.shape and np.isfinite(result.albedo).all()
    # A relit refiner that sees the light, beside that albedo one: from the albedo refiner's weights with its
    # relit correction set to zero (so it starts at the filtered frames), the light's FiLM new, and its relit
    # correction a smooth gain (--relit-gain, as shipped).
    lit = [*fresh[:fresh.index("--out")], "--out", str(tmp_path / "run4"), "--widths", "4", "8", "--batch", "2",
           "--minutes", "0.03", "--val-every-minutes", "0.01", "--warmup", "2", "--scenes", "2",
           "--model", str(tmp_path / "refined"), "--model-dir", str(tmp_path / "refined3"), "--flip-average",
           "--permute-colours", "--clips", "relit", "--lighting", "--zero-head", "--slot", "relit_refiner",
           "--same-scenes", "1", "--relit-gain", "4", "--alike-weight", "2", "--alike-db", "0", *init]
    assert refine.main(lit) == 0
    out = capsys.readouterr().out
    assert "with the light's FiLM new; the corrected clips' head set to zero" in out
    assert "4 of 5 items have a floor of 0.0 dB or more; drawn 2.0× as often" in out     # the same-light one is not
    best4 = json.loads((tmp_path / "run4" / "best.json").read_text())
    assert best4["refiner"]["lighting"] and best4["refiner"]["clips"] == ["relit"] and best4["refiner"]["relit_gain"] == 4
    # --same-scenes: one training scene and every validation scene also relit to its own light, scored apart.
    assert best4["train_items"] == 5 and best4["val_items"] == 6 and "same" in best4["val"]
    kinds = np.load(tmp_path / "run4" / "outputs-train.npz")
    assert list(kinds["same"]) == [0, 0, 0, 0, 1] and list(kinds["names"][-1:]) == ["scene_000002"]
    assert list(kinds["targets"][-1:]) == [0]                                  # light scene % 2
    pack = refine.load_packs([tmp_path / "p.npz"])
    data = refine.item_tensors(pack, [(2, 0, 1), (2, 0, 0)], {k: kinds[k][[4, 0]] for k in ("relit", "albedo")},
                               load_model(tmp_path / "refined")[0], "raw")
    assert torch.equal(data["input"][0], data["target"][0]) and torch.equal(data["input"][1], pack["rgb"][2, 1])
    assert best4["start"]["init"]["relit"] == pytest.approx(best4["start"]["filtered"]["relit"], abs=1e-3)
    config3 = json.loads((tmp_path / "refined3" / "config.json").read_text())
    assert config3["refiner"] == json.loads((tmp_path / "refined" / "config.json").read_text())["refiner"]
    assert config3["relit_refiner"]["lighting"] and "relit_refiner" in config3["notes"]
    both = Relighter.load(str(tmp_path / "refined3"))
    assert both.refiner.config.clips == ("albedo",) and both.relit_refiner.config.lighting
    assert both.relit_refiner.config.relit_gain == 4 and both.refiner.config.relit_gain == 0
    twice = both.relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    np.testing.assert_allclose(twice.albedo, result.albedo, atol=2e-3)     # the albedo refiner is the one copied
    # calibrate --strengths --write fits both refiners' strengths on items and stores them (1: no key).
    from relight_core.training import calibrate

    assert calibrate.main(["--model", str(tmp_path / "refined3"), "--data", str(root), "--split", "train",
                           "--items", "2", "--strengths", "--write"]) == 0
    fitted = json.loads((tmp_path / "refined3" / "config.json").read_text())
    table = fitted["notes"]["strength_calibration"]["table"]
    assert set(table) == {str(s) for s in calibrate.STRENGTHS}
    assert fitted["notes"]["strength_calibration"]["owners"] == {"relit_refiner": ["relit"], "refiner": ["albedo"]}
    for slot, clip in (("relit_refiner", "relit"), ("refiner", "albedo")):
        chosen = fitted[slot].get("strength", 1.0)
        assert chosen in calibrate.STRENGTHS and (chosen != 1.0) == ("strength" in fitted[slot])
        assert table[str(chosen)][clip] >= table["1.0"][clip]
        assert getattr(Relighter.load(str(tmp_path / "refined3")), slot).config.strength == chosen
    # A second shape on the same run folder is refused in one sentence, as is a model that is not a pixel model.
    with pytest.raises(SystemExit):
        refine.main([*args[:args.index("--widths")], "--widths", "4", "8", "8", "--minutes", "0.1"])
    assert "another shape" in capsys.readouterr().err
    spec, _, _ = load_model(model)
    assert spec.residual
    with pytest.raises(SystemExit):
        refine.main([*args[:1], str(tmp_path), *args[2:]])
    assert f"--model {tmp_path} holds no dit.safetensors" in capsys.readouterr().err
    # Two renders' packs name their scenes alike (scene_000000, ...); the DiT's outputs are kept by name, so
    # training on both at once is refused in one sentence rather than reading one scene's outputs for another.
    with pytest.raises(SystemExit):
        refine.main([*args[:3], str(tmp_path / "p.npz"), *args[3:]])
    assert "the --pack files hold scenes of the same name" in capsys.readouterr().err
    # --device: the items stay in host memory and each batch goes to the device, flipped alike; a GPU asked
    # for where there is none is one sentence.
    flip = torch.tensor([True, False])
    on_host = refine.model_inputs(data, [0, 1], "raw", flip)
    moved = refine.model_inputs(data, [0, 1], "raw", flip, torch.device("cpu"))
    for a, b in zip((*on_host[:3], on_host[3]("env"), on_host[3]("mask")), (*moved[:3], moved[3]("env"), moved[3]("mask"))):
        assert torch.equal(a, b)
    assert torch.equal(on_host[3]("env")[0], data["env"][0].flip(1)) and torch.equal(on_host[3]("env")[1], data["env"][1])
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit):
            refine.main([*args, "--device", "cuda"])
        assert "no usable CUDA GPU" in capsys.readouterr().err


def test_light_features_keep_the_lights_shape_and_colour_not_its_scale():
    pano = torch.rand(2, 32, 32, 3) + 0.1
    features = light_features(pano)
    assert features.shape == (2, LIGHT_FEATURES)
    assert torch.allclose(light_features(pano * 7.5), features, atol=1e-5)       # the protocol fits the scale
    sun = pano.clone()
    sun[:, 4:8, 20:24] += 50.0                                                    # a sun in one place ...
    moved = pano.clone()
    moved[:, 4:8, 4:8] += 50.0                                                    # ... or another
    assert (light_features(sun) - light_features(moved)).abs().max() > 1.0
    # A frame-sized panorama and its area average to the lighting grid give the same features.
    assert torch.allclose(light_features(pano.repeat_interleave(4, 1).repeat_interleave(4, 2)), features, atol=1e-5)
    with pytest.raises(ValueError, match="panoramas"):
        light_features(torch.rand(32, 32, 3))


def test_a_refiner_that_sees_the_light_starts_as_one_that_does_not_and_mirrors_with_its_light():
    torch.manual_seed(5)
    config = RefinerConfig(widths=(4, 8), blocks=1, base="filtered", clips=("relit",), flip_average=True)
    blind = _randomised(Refiner(config), 0.1)
    lit_config = RefinerConfig.from_dict({**config.to_dict(), "lighting": True})
    assert lit_config.to_dict()["lighting"] is True and lit_config.shape != config.shape
    lit = Refiner(lit_config)
    missing = lit.load_state_dict(blind.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("film.") for k in missing)
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    light = torch.rand(2, 32, 32, 3)
    light[0, 8:12, 2:6] += 40.0                                                  # a sun on the left ...
    light[1, 8:12, 26:30] += 40.0                                                # ... and on the right
    with torch.no_grad():
        # Its FiLM starts at zero: the same corrections as the refiner without the light, whatever the light.
        assert torch.allclose(lit.correction(x, light), blind.correction(x), atol=1e-6)
        torch.nn.init.normal_(lit.film[-1].weight, std=0.1)
        one, other = lit.correction(x, light), lit.correction(x, light.flip(0))
        assert (one - other).abs().max() > 1e-3                                   # now the light counts
        # Mirror the frames and the light, and the correction mirrors with them.
        assert torch.allclose(lit.correction(x.flip(-1), light.flip(2)), one.flip(-1), atol=1e-5)
        relit, albedo = lit.refine(*[x[:, 3 * k:3 * k + 3] for k in range(3)],
                                   filtered=(x[:, 9:12], x[:, 12:15]), panoramas=light)
    assert torch.equal(albedo, x[:, 12:15])                                      # relit-only: albedo is the base's
    with pytest.raises(ValueError, match="sees the light"):
        lit.correction(x)
    with pytest.raises(ValueError, match="takes the light's features"):
        blind(x, light_features(light))
    with pytest.raises(ValueError):
        RefinerConfig.from_dict({"lighting": 1})


def test_a_refiner_that_sees_more_of_the_light_starts_from_one_that_sees_less_and_tells_finer_suns_apart(tmp_path):
    torch.manual_seed(7)
    config = RefinerConfig(widths=(4, 8, 8), blocks=1, base="filtered", clips=("relit",), flip_average=True,
                           lighting=True, relit_gain=4)
    coarse = _randomised(Refiner(config), 0.1)
    save_file(coarse.state_dict(), str(tmp_path / "coarse.safetensors"))
    fine_config = RefinerConfig.from_dict({**config.to_dict(), "light_detail": 16, "film_encoder": True})
    assert fine_config.to_dict()["light_detail"] == 16 and fine_config.to_dict()["film_encoder"] is True
    assert fine_config.shape != config.shape and fine_config.light_features == LIGHT_FEATURES + 3 * 16 * 16
    fine = Refiner(fine_config)
    assert "more of the light new" in refine.initial_weights(fine, tmp_path / "coarse.safetensors")
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    light = torch.rand(2, 32, 32, 3) + 0.1
    light[:, 8:10, 8:10] += 60.0                                                # a sun ...
    shifted = light.clone()
    shifted[:, 8:10, 8:10] -= 60.0
    shifted[:, 10:12, 10:12] += 60.0                                            # ... moved within one 8×8 cell
    assert torch.allclose(light_features(light), light_features(shifted), atol=1e-5)
    with torch.no_grad():
        # The same output as the refiner it starts from, whatever the light: the new weights are at zero.
        assert torch.allclose(fine.correction(x, light), coarse.correction(x, light), atol=1e-6)
        assert torch.allclose(fine.correction(x, shifted), coarse.correction(x, shifted), atol=1e-6)
        # Once they have weight, the finer grid tells the two suns apart (the 8×8 one cannot) ...
        torch.nn.init.normal_(fine.film[0].weight, std=0.1)
        assert (fine.correction(x, light) - fine.correction(x, shifted)).abs().max() > 1e-4
        # ... the encoder's FiLM counts, and the mirror symmetry still holds.
        before = fine.correction(x, light)
        fine.film[-1].weight[-2 * sum(config.widths[:-1]):] += 0.2
        assert (fine.correction(x, light) - before).abs().max() > 1e-4
        assert torch.allclose(fine.correction(x.flip(-1), light.flip(2)), fine.correction(x, light).flip(-1), atol=1e-5)
    # A refiner that sees the probe on another fine grid is not one that sees less of it: refused, not misread.
    save_file({k: v.contiguous() for k, v in fine.state_dict().items()}, str(tmp_path / "fine.safetensors"))
    with pytest.raises(ValueError, match="not a refiner of this shape"):
        refine.initial_weights(Refiner(replace(fine_config, light_detail=12)), tmp_path / "fine.safetensors")
    for bad in ({"light_detail": 16}, {"film_encoder": True}, {"lighting": True, "light_detail": 1},
                {"lighting": True, "light_detail": 40}, {"lighting": True, "film_encoder": 1}):
        with pytest.raises(ValueError, match="light_detail"):
            RefinerConfig.from_dict(bad)


def test_a_transport_refiner_starts_as_one_without_its_term_a_weighted_mean_of_the_probes_cells_that_learns_the_light(tmp_path):
    torch.manual_seed(8)
    config = RefinerConfig(widths=(4, 8, 8), blocks=1, base="filtered", clips=("relit",), lighting=True, relit_gain=4)
    plain = _randomised(Refiner(config), 0.1)
    save_file(plain.state_dict(), str(tmp_path / "plain.safetensors"))
    transport_config = RefinerConfig.from_dict({**config.to_dict(), "transport": 4})
    assert transport_config.to_dict()["transport"] == 4 and transport_config.shape != config.shape
    lit = Refiner(transport_config)
    assert "transport term new" in refine.initial_weights(lit, tmp_path / "plain.safetensors")
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    light = torch.rand(2, 32, 32, 3) + 0.1
    light[0, 4:8, 20:24] += torch.tensor([60.0, 30.0, 5.0])                       # a warm sun in one of 4×4 cells
    with torch.no_grad():
        before = plain.correction(x, light)
        # The same output as the refiner it starts from: uniform weights, a shading of exactly 1.
        assert torch.allclose(lit.correction(x, light), before, atol=1e-6)
        # Every pixel weighting one cell alone: the log gain gains that cell's light over the probe's mean, per
        # channel (the sun's cell for the first item: warm, bright), and nothing else changes.
        lit.transport_head.bias[0 * 4 + 2] = 60.0          # row 0, column 2: the sun's
        cells = F.adaptive_avg_pool2d(light.permute(0, 3, 1, 2), 4).flatten(2)
        expected = torch.log(cells[:, :, 0 * 4 + 2] / cells.mean(2))                 # [B,3]
        added = lit.correction(x, light) - before
        assert torch.allclose(added[:, :3], expected[:, :, None, None].expand(-1, -1, 16, 20), atol=1e-4)
        assert expected[0, 0] > 1.5 and expected[0, 0] > expected[0, 2] + 1 and added[:, 3:].abs().max() == 0
        # With weights learnt from the frames, the term shades places apart, and the mirror symmetry holds.
        lit.transport_head.bias.zero_()
        torch.nn.init.normal_(lit.transport_head.weight, std=1.0)
        added = lit.correction(x, light)[:, :3] - before[:, :3]
        assert added.std((2, 3)).min() > 1e-3
        mirrored = Refiner(replace(transport_config, flip_average=True))
        mirrored.load_state_dict(lit.state_dict())
        assert torch.allclose(mirrored.correction(x.flip(-1), light.flip(2)), mirrored.correction(x, light).flip(-1),
                              atol=1e-5)
    # Reshading: the gated term swaps the base's own shading (relit ÷ albedo, per cell) for the transport one.
    reshading = Refiner(replace(transport_config, reshade=True))
    assert "transport term new" in refine.initial_weights(reshading, tmp_path / "plain.safetensors")
    with torch.no_grad():
        assert torch.allclose(reshading.correction(x, light), before, atol=1e-6)   # the gate starts at zero
        reshading.transport_gate.bias.fill_(1.0)
        reshading.transport_head.bias[0 * 4 + 2] = 60.0
        own = F.avg_pool2d(torch.log((x[:, 9:12] + 1.04) / (x[:, 12:15] + 1.04)), 2)   # its level: 1/2 size here
        swapped = F.interpolate(expected[:, :, None, None] - own, size=(16, 20), mode="bilinear", align_corners=False)
        assert torch.allclose(reshading.correction(x, light)[:, :3] - before[:, :3], swapped, atol=1e-4)
    # Trained alone (training's optimiser: its own group at --transport-lr; the rest frozen here at scale 0) where
    # each half of the frame is lit from its own cell of the probe, under new random suns every step, it learns
    # to follow the light: only a shading linear in the probe can fit that.
    torch.manual_seed(9)
    learner = Refiner(transport_config)
    optimiser = refine.refiner_optimizer(learner, 1e-2, head_lr=0.0, transport_lr=10.0)
    rest, head, transport = optimiser.param_groups
    assert [id(p) for p in transport["params"]] == [id(learner.transport_head.weight), id(learner.transport_head.bias)]
    rest["scale"] = 0.0
    for group in optimiser.param_groups:
        group["lr"] = 1e-2 * group["scale"]
    frozen = learner.stem.weight.clone()
    right = torch.zeros(4, 1, 16, 16)
    right[..., 8:] = 1.0
    inputs = (right * 1.6 - 0.8).expand(4, 3, 16, 16)                            # the input tells the halves apart
    base = torch.zeros(4, 3, 16, 16)
    x, r, a = refine.network_input("filtered", inputs, base, base, (base, base))

    def lit_halves():
        probe = torch.rand(4, 32, 32, 3) + 0.1
        probe[:, 0:8, 16:24] += torch.rand(4, 1, 1, 3) * 40                         # cell 2 lights the left half,
        probe[:, 8:16, 8:16] += torch.rand(4, 1, 1, 3) * 40                         # cell 5 the right one
        cells = F.adaptive_avg_pool2d(probe.permute(0, 3, 1, 2), 4).flatten(2)
        shading = cells / cells.mean(2, keepdim=True)
        field = torch.where(right.bool(), shading[:, :, 5, None, None], shading[:, :, 2, None, None])
        return probe, (base + 1.04) * field - 1.04                                # the base under that gain

    def loss_of(probe, target):
        relit, _ = learner.corrected(learner(x, learner.light(probe)), r, a, clamp=False)
        return refine.item_loss(relit, target, torch.ones(4, 16, 16))

    held = [lit_halves() for _ in range(4)]
    with torch.no_grad():
        before = sum(loss_of(*item) for item in held) / 4
    for _ in range(200):
        loss = loss_of(*lit_halves())
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        after = sum(loss_of(*item) for item in held) / 4
    assert after < before - 1.5 and torch.equal(learner.stem.weight, frozen)        # log MSE, on suns it never saw
    for bad in ({"lighting": True, "relit_gain": 4, "transport": 1}, {"relit_gain": 4, "transport": 8},
                {"lighting": True, "transport": 8}, {"lighting": True, "relit_gain": 4, "clips": ["albedo"], "transport": 8},
                {"lighting": True, "relit_gain": 4, "reshade": True}):
        with pytest.raises(ValueError, match="transport"):
            RefinerConfig.from_dict(bad)


def test_a_grid_shifted_refiner_averages_its_correction_with_the_one_for_the_padded_frames_cropped_back():
    """`grid_shift` s: the mean of the correction for the frames and for the frames reflected s px out on every
    side, cropped back, so the U-Net's coarse grid falls elsewhere on the scene in the second pass."""
    torch.manual_seed(11)
    config = RefinerConfig(widths=(4, 8, 8), blocks=1, base="filtered", clips=("relit",), lighting=True,
                           flip_average=True, relit_gain=4)
    plain = _randomised(Refiner(config), 0.2)
    shifted = Refiner(RefinerConfig.from_dict({**config.to_dict(), "grid_shift": 2}))
    assert shifted.config.to_dict()["grid_shift"] == 2 and shifted.config.shape == config.shape
    assert "grid_shift" not in config.to_dict()                      # 0: configs before it read alike
    shifted.load_state_dict(plain.state_dict())
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    light = torch.rand(2, 32, 32, 3) + 0.1
    with torch.no_grad():
        out = shifted.correction(x, light)
        padded = plain.correction(F.pad(x, (2, 2, 2, 2), mode="reflect"), light)
        assert padded.shape[-2:] == (20, 24)
        torch.testing.assert_close(out, (plain.correction(x, light) + padded[..., 2:18, 2:22]) / 2)
        # the grid two pixels off changes the correction: the second pass is not the first again
        assert (padded[..., 2:18, 2:22] - plain.correction(x, light)).abs().max() > 1e-2
        # a frame smaller than the shift is padded with its edge and keeps its size; an untrained one adds nothing
        tiny = torch.rand(1, 15, 2, 3) * 2 - 1
        assert shifted.correction(tiny, light[:1]).shape == (1, 6, 2, 3)
        untrained = Refiner(shifted.config)
        base = torch.rand(1, 3, 16, 20) * 1.6 - 0.8
        relit, _ = untrained.refine(base, base, base, (base, base), light[:1])
        torch.testing.assert_close(relit, base)


@pytest.mark.parametrize("input_mix", [False, True])
def test_a_colour_averaged_refiner_treats_every_order_of_the_colour_channels_alike(input_mix):
    torch.manual_seed(10)
    config = RefinerConfig(widths=(4, 8, 8), blocks=1, base="filtered", clips=("relit", "albedo"), lighting=True,
                           flip_average=True, relit_gain=4 if input_mix else 0, input_mix=input_mix)
    plain = _randomised(Refiner(config), 0.2)
    averaged = Refiner(RefinerConfig.from_dict({**config.to_dict(), "colour_average": True}))
    assert averaged.config.to_dict()["colour_average"] is True and averaged.config.shape == config.shape
    averaged.load_state_dict(plain.state_dict())
    x = torch.rand(2, 15, 16, 20) * 2 - 1
    light = torch.rand(2, 32, 32, 3) + 0.1
    light[:, 4:8, 20:24, 0] += 50.0                                                  # a red sun

    def channels(count, order):       # every RGB triple's channel j from its channel order[j]; a lone last one stays
        return [3 * t + o for t in range(count // 3) for o in order] + list(range(3 * (count // 3), count))

    order = [2, 0, 1]
    with torch.no_grad():
        out, out_swapped = averaged.correction(x, light), averaged.correction(x[:, channels(15, order)], light[..., order])
        assert out.shape[1] == (10 if input_mix else 6)
        # the colours swapped in, the correction's colours come out swapped alike (the mix logit as it was) ...
        assert torch.allclose(out_swapped, out[:, channels(out.shape[1], order)], atol=1e-5)
        # ... which the refiner itself does not do: the average is of six different corrections, each put back
        alone = plain.correction(x[:, channels(15, order)], light[..., order])
        assert (alone - plain.correction(x, light)[:, channels(out.shape[1], order)]).abs().max() > 1e-2
        expected = sum(plain.correction(x[:, channels(15, p)], light[..., list(p)])[:, np.argsort(channels(out.shape[1], p))]
                       for p in itertools.permutations(range(3))) / 6
        assert torch.allclose(out, expected, atol=1e-5)


def test_a_relit_refiner_beside_the_albedo_one_corrects_the_relit_frames_with_the_target_light(tmp_path):
    spec, dit, tok = residual_model()
    frames = np.random.default_rng(1).random((2, 32, 32, 3)).astype(np.float32)
    probe = np.ones((16, 32, 3), np.float32)
    probe[2:5, 6:10] = 60.0                                                      # a sun
    request = RelightRequest(frames=frames, probe=probe)
    filtered = Relighter(spec, dit, tok).relight(request)
    albedo_refiner = Refiner(replace(SMALL, base="filtered", clips=("albedo",)))
    relit_refiner = Refiner(replace(SMALL, base="filtered", clips=("relit",), lighting=True))
    torch.manual_seed(2)
    with torch.no_grad():
        albedo_refiner.head.bias.copy_(torch.tensor([0.3, 0.3, 0.3, -0.4, -0.4, -0.4]))  # its relit head is unused
        torch.nn.init.normal_(relit_refiner.head.weight, std=0.05)
        torch.nn.init.normal_(relit_refiner.film[-1].weight, std=0.5)
    both = Relighter(spec, dit, tok, refiner=albedo_refiner, relit_refiner=relit_refiner)
    assert both.clip_refiners() == {"relit": "relit_refiner", "albedo": "refiner"}
    assert both.clip_refiners(lit=False) == {"albedo": "refiner"}    # it sees the light: none, it stays out
    result = both.relight(request)
    np.testing.assert_allclose(result.albedo, np.clip(filtered.albedo - 0.2, 0, 1), atol=2e-3)
    assert np.abs(result.relit - filtered.relit).max() > 1e-3                     # the relit refiner's
    # It sees the target light: the probe turned, its correction differs (the DiT's part is taken out).
    turned = replace(request, rotation=request.rotation + 90.0)
    base_turned = Relighter(spec, dit, tok).relight(turned).relit
    assert np.abs((both.relight(turned).relit - base_turned) - (result.relit - filtered.relit)).max() > 1e-3
    # Without a probe (a random light) it has no light to see and stays out; the albedo one still runs.
    random = replace(request, probe=None, mode="random")
    unlit = both.relight(random)
    plain_random = Relighter(spec, dit, tok).relight(random)
    np.testing.assert_array_equal(unlit.relit, plain_random.relit)
    np.testing.assert_allclose(unlit.albedo, np.clip(plain_random.albedo - 0.2, 0, 1), atol=2e-3)
    # A model folder holds both (config.json "refiner" and "relit_refiner"); Relighter.load runs them.
    folder = tmp_path / "model"
    folder.mkdir()
    save_file({k: v.contiguous() for k, v in dit.state_dict().items()}, folder / "dit.safetensors")
    data = replace(spec, refiner=albedo_refiner.config.to_dict(), relit_refiner=relit_refiner.config.to_dict()).to_json()
    (folder / "config.json").write_text(json.dumps(data))
    save_file(albedo_refiner.state_dict(), folder / REFINER_FILE)
    with pytest.raises(InputError, match=f"missing {RELIT_REFINER_FILE}"):
        Relighter.load(str(folder))
    save_file(relit_refiner.state_dict(), folder / RELIT_REFINER_FILE)
    loaded = Relighter.load(str(folder))
    assert loaded.relit_refiner.config.lighting and loaded.refiner.config.clips == ("albedo",)
    again = loaded.relight(request)
    np.testing.assert_allclose(again.relit, result.relit, atol=2e-3)
    np.testing.assert_allclose(again.albedo, result.albedo, atol=2e-3)
    with pytest.raises(InputError, match='has relit_refiner .*; it takes "widths"'):
        ModelSpec.from_json({**data, "relit_refiner": {"lighting": "yes"}})


def test_a_relit_gain_refiner_multiplies_its_base_by_a_smooth_field_and_draws_no_edge_of_its_own():
    torch.manual_seed(6)
    config = RefinerConfig(widths=(4, 8), blocks=1, base="filtered", clips=("relit",), relit_gain=8)
    assert RefinerConfig.from_dict(config.to_dict()) == config and config.to_dict()["relit_gain"] == 8
    for bad in (-1, 2.5, True, 65):
        with pytest.raises(ValueError, match="relit_gain"):
            RefinerConfig.from_dict({**config.to_dict(), "relit_gain": bad})
    refiner = Refiner(config)
    base = torch.full((1, 3, 32, 32), -0.2)
    base[..., 16:] = 0.6                                             # one vertical edge
    albedo = torch.zeros_like(base)
    # a correction that is the same over each 8×8 cell: the base times its exponential, exactly
    cells = torch.randn(1, 6, 4, 4) * 0.5
    delta = cells.repeat_interleave(8, -2).repeat_interleave(8, -1)
    relit, same_albedo = refiner.corrected(delta, base, albedo, clamp=False)
    assert torch.equal(same_albedo, albedo)                          # it corrects the relit frames alone
    inside = (slice(None), slice(None), slice(4, 28), slice(4, 28))  # cell centres and between: bilinear
    expected = F.interpolate(cells[:, :3], size=(32, 32), mode="bilinear", align_corners=False)
    eps = 2 * 0.02
    torch.testing.assert_close(relit, (base + 1 + eps) * torch.exp(expected) - eps - 1, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(relit[inside], base[inside] + delta[:, :3][inside], atol=1e-2)   # not added
    # Pixel noise as the correction: added, it would draw edges everywhere; as a gain it is averaged
    # away within each cell, so the result's steps outside the base's own edge stay small.
    noise = torch.randn(1, 6, 32, 32)
    gained, _ = refiner.corrected(noise, base, albedo)
    added, _ = Refiner(replace(config, relit_gain=0)).corrected(noise, base, albedo)
    steps = lambda x: (x[..., 1:] - x[..., :-1]).abs()[..., [c for c in range(31) if c != 15]]  # noqa: E731
    assert steps(gained).max() < 0.25 * steps(added).max()
    # A black base stays black under a gain near one; a constant base stays constant under a constant gain.
    black = torch.full_like(base, -1.0)
    near_one, _ = refiner.corrected(torch.full_like(delta, 0.05), black, albedo)
    assert (near_one + 1).max() < 0.005
    flat, _ = refiner.corrected(torch.full_like(delta, 0.3), torch.full_like(base, 0.1), albedo)
    torch.testing.assert_close(flat, torch.full_like(base, (1.1 + 0.04) * float(np.exp(0.3)) - 0.04 - 1))
    # The training loss sees the same correction unclamped; Relighter's result is clamped to [-1, 1].
    bright, _ = refiner.corrected(torch.full_like(delta, 2.0), base, albedo)
    assert bright.max() == 1.0



def test_an_input_mix_refiner_mixes_the_gained_input_into_the_relit_frames_cell_by_cell_and_learns_when_to(tmp_path):
    torch.manual_seed(9)
    config = RefinerConfig(widths=(4, 8), blocks=1, base="filtered", clips=("relit",), relit_gain=8, input_mix=True)
    assert RefinerConfig.from_dict(config.to_dict()) == config and config.to_dict()["input_mix"] is True
    plain = replace(config, input_mix=False)
    assert "input_mix" not in plain.to_dict() and plain.shape != config.shape       # its head has 4 more channels
    for bad in ({"input_mix": 1}, {"input_mix": True, "relit_gain": 0}, {"input_mix": True, "clips": ["albedo"]}):
        with pytest.raises(ValueError, match="input_mix"):
            RefinerConfig.from_dict({**config.to_dict(), **bad})
    refiner = Refiner(config)
    assert refiner.head.out_channels == 10
    base, albedo = torch.rand(1, 3, 32, 32) * 1.6 - 0.8, torch.rand(1, 3, 32, 32) * 1.6 - 0.8
    inputs = torch.rand(1, 3, 32, 32) * 1.6 - 0.8
    eps = 2 * 0.02

    def constant(relit_gain: float, input_gain: float, logit: float) -> torch.Tensor:
        delta = torch.zeros(1, 10, 32, 32)
        delta[:, :3], delta[:, 6:9], delta[:, 9] = relit_gain, input_gain, logit
        return delta

    gained_base = (base + 1 + eps) * np.exp(0.2) - eps - 1
    gained_input = (inputs + 1 + eps) * np.exp(-0.3) - eps - 1
    # the logit far up: the input under its own gain; far down: the base under its gain; at the offset, halfway
    up, same_albedo = refiner.corrected(constant(0.2, -0.3, 40.0), base, albedo, clamp=False, inputs=inputs)
    torch.testing.assert_close(up, gained_input)
    assert torch.equal(same_albedo, albedo)
    down, _ = refiner.corrected(constant(0.2, -0.3, -40.0), base, albedo, clamp=False, inputs=inputs)
    torch.testing.assert_close(down, gained_base)
    half, _ = refiner.corrected(constant(0.2, -0.3, 5.0 / 8), base, albedo, clamp=False, inputs=inputs)
    torch.testing.assert_close(half, (gained_base + gained_input) / 2)
    # each cell mixes on its own: the left half takes the input, the right half the base (bilinear between)
    split = constant(0.0, 0.0, -40.0)
    split[:, 9, :, :16] = 40.0
    mixed, _ = refiner.corrected(split, base, albedo, clamp=False, inputs=inputs)
    torch.testing.assert_close(mixed[..., :4], inputs[..., :4])
    torch.testing.assert_close(mixed[..., 28:], base[..., 28:])
    with pytest.raises(ValueError, match="pass the input"):
        refiner.corrected(split, base, albedo)
    # Started from a refiner without the mix (--init): the same weights, the mix's channels at zero — the
    # input's weight sigmoid(−5), so the output moves by under 1% of the input's difference from it.
    old = _randomised(Refiner(plain), 0.1)
    save_file({k: v.contiguous() for k, v in old.state_dict().items()}, tmp_path / "old.safetensors")
    assert "input mix new" in refine.initial_weights(refiner, tmp_path / "old.safetensors")
    with torch.no_grad():
        before, _ = old.refine(inputs, base, albedo, (base * 0.9, albedo * 0.9))
        after, _ = refiner.refine(inputs, base, albedo, (base * 0.9, albedo * 0.9))
    assert 0 < (after - before).abs().max() <= 2 * torch.sigmoid(torch.tensor(-5.0))   # frames span [-1, 1]
    # Trained where the input is the answer (the relit base a blur of it), the mix learns to take the input
    # (training's optimiser: the last layer, where the mix starts, may learn faster than the rest: --head-lr).
    sharp = (torch.rand(4, 3, 32, 32) > 0.5).float() * 1.6 - 0.8
    blurred = F.avg_pool2d(sharp, 5, 1, 2)
    refiner = Refiner(config)
    optimiser = refine.refiner_optimizer(refiner, 1e-2, head_lr=2.0)
    rest, head = optimiser.param_groups
    assert [id(p) for p in head["params"]] == [id(refiner.head.weight), id(refiner.head.bias)]
    assert (rest["scale"], head["scale"]) == (1.0, 2.0) and len(rest["params"]) == len(list(refiner.parameters())) - 2
    for group in optimiser.param_groups:
        group["lr"] = 1e-2 * group["scale"]
    mask = torch.ones(4, 32, 32)
    losses = []
    for _ in range(60):
        x, r, _ = refine.network_input("filtered", sharp, blurred, blurred, (blurred, blurred))
        relit, _ = refiner.corrected(refiner(x), r, blurred, clamp=False, inputs=sharp)
        loss = refine.item_loss(relit, sharp, mask)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] - 2.0                     # log MSE: far closer to the sharp input
    # A run resumes its optimiser with the scales it had; one saved before the head had a group of its own
    # (one group, no scale) resumes as that one group at scale 1.
    again = refine.refiner_optimizer(refiner, 1e-2, head_lr=7.0, saved=optimiser.state_dict())
    assert [g["scale"] for g in again.param_groups] == [1.0, 2.0]
    assert torch.equal(again.state[refiner.head.bias]["exp_avg"], optimiser.state[refiner.head.bias]["exp_avg"])
    old_style = torch.optim.AdamW(refiner.parameters(), lr=1e-2)
    refiner(x).sum().backward()
    old_style.step()
    resumed = refine.refiner_optimizer(refiner, 1e-2, head_lr=7.0, saved=old_style.state_dict())
    assert len(resumed.param_groups) == 1 and resumed.param_groups[0]["scale"] == 1.0
    assert torch.equal(resumed.state[refiner.head.weight]["exp_avg_sq"], old_style.state[refiner.head.weight]["exp_avg_sq"])


def test_input_floors_are_the_protocols_psnr_of_the_input_against_the_target():
    """What --alike-weight draws more often: items whose input is already close to the target."""
    from relight_core.evaluation.metrics import protocol_psnr

    g = torch.Generator().manual_seed(0)
    target = torch.randint(0, 256, (3, 3, 16, 16), dtype=torch.uint8, generator=g)
    tint = torch.tensor([0.5, 0.8, 1.2]).view(1, 3, 1, 1)                # scaled by the fit, clipped after it
    noise = torch.tensor([2.0, 8.0, 30.0]).view(3, 1, 1, 1) * torch.randn(3, 3, 16, 16, generator=g)
    inputs = (target.float() * tint + noise).clamp(0, 255).to(torch.uint8)
    mask = torch.rand(3, 16, 16, generator=g) > 0.3
    floors = refine.input_floors({"input": inputs, "target": target, "mask": mask})
    hwc = lambda x: x.permute(1, 2, 0).numpy()[None] / 255.0              # noqa: E731
    expected = [protocol_psnr(hwc(inputs[k]), hwc(target[k]), mask[k].numpy()[None]) for k in range(3)]
    np.testing.assert_allclose(floors.numpy(), expected, atol=1e-3)
    assert floors[0] > floors[1] > floors[2]                              # less noise, a higher floor


def test_cached_outputs_reuses_the_items_a_file_holds_by_name_direction_and_same(tmp_path):
    """The DiT's outputs are kept by (scene name, target light, same): a file written for other items gives
    back the frames of those it holds, in the new order, and names the rows it lacks."""
    frames = np.arange(4 * 3 * 2 * 2, dtype=np.uint8).reshape(4, 3, 2, 2)
    path = tmp_path / "outputs.npz"
    np.savez(path, names=np.array(["a", "a", "b", "b"]), targets=np.array([0, 1, 0, 0]),
             same=np.array([0, 0, 0, 1], dtype=np.int64), relit=frames, albedo=frames + 100)
    pack = {"names": np.array(["b", "a", "c"])}
    items = [(0, 0, 1), (1, 1, 0), (2, 0, 0), (0, 0, 0)]    # b same, a→1, c (not held), b→0
    rows = refine.held_rows(path, *refine.item_keys(pack, items))
    assert rows == [3, 1, None, 2]
    out = refine.held_frames(path, rows)
    np.testing.assert_array_equal(out["relit"][[0, 1, 3]], frames[[3, 1, 2]])
    np.testing.assert_array_equal(out["albedo"][[0, 1, 3]], frames[[3, 1, 2]] + 100)
    assert refine.held_frames(path, [None, None]) is None
    # Every item held, in another order: nothing is computed (there is no model), the file is rewritten in
    # the items' order and the next call reads it back as it is.
    held = [(1, 0, 0), (0, 0, 1)]
    first = refine.cached_outputs(path, tmp_path / "no-model", pack, held, log=lambda m: None, copies=1)
    np.testing.assert_array_equal(first["relit"], frames[[0, 3]])
    again = refine.cached_outputs(path, tmp_path / "no-model", pack, held, log=lambda m: pytest.fail(m), copies=1)
    np.testing.assert_array_equal(again["albedo"], frames[[0, 3]] + 100)


def test_a_refiners_strength_scales_its_correction_and_calibrate_picks_it_per_refiner_by_the_clips_it_supplies():
    torch.manual_seed(8)
    config = RefinerConfig(widths=(4, 8), blocks=1, base="filtered", clips=("relit", "albedo"), relit_gain=8)
    assert "strength" not in config.to_dict()                        # 1, as trained: configs before it read alike
    half = replace(config, strength=0.5)
    assert RefinerConfig.from_dict(half.to_dict()) == half and half.to_dict()["strength"] == 0.5
    assert half.shape == config.shape                                # the same weights, used more gently
    for bad in (-0.1, 2.5, True, "1"):
        with pytest.raises(ValueError, match="strength"):
            RefinerConfig.from_dict({**config.to_dict(), "strength": bad})
    base, albedo = torch.rand(1, 3, 32, 32) * 1.6 - 0.8, torch.rand(1, 3, 32, 32) * 1.6 - 0.8
    delta = torch.randn(1, 6, 4, 4).repeat_interleave(8, -2).repeat_interleave(8, -1) * 0.3
    full_relit, full_albedo = Refiner(config).corrected(delta, base, albedo, clamp=False)
    half_relit, half_albedo = Refiner(half).corrected(delta, base, albedo, clamp=False)
    # the relit gain raised to the strength (the log gain scaled), the added albedo correction scaled
    eps = 2 * 0.02
    torch.testing.assert_close((half_relit + 1 + eps) ** 2, (full_relit + 1 + eps) * (base + 1 + eps))
    torch.testing.assert_close(half_albedo, albedo + 0.5 * (full_albedo - albedo))
    off_relit, off_albedo = Refiner(replace(config, strength=0.0)).corrected(delta, base, albedo)
    torch.testing.assert_close(off_relit, base)
    torch.testing.assert_close(off_albedo, albedo)
    # calibrate: each refiner is scored on the clips whose result it supplies (the relit refiner's relit
    # wins where both correct it) and keeps strength 1 unless another gains STRENGTH_MIN_GAIN over it.
    from relight_core.training import calibrate

    spec, dit, tok = residual_model()
    both = Relighter(spec, dit, tok, refiner=Refiner(config), relit_refiner=Refiner(replace(config, clips=("relit",))))
    assert both.clip_refiners() == {"relit": "relit_refiner", "albedo": "refiner"}     # the relit refiner's relit wins
    assert calibrate.refiner_owners(both) == {"relit_refiner": ["relit"], "refiner": ["albedo"]}
    assert calibrate.refiner_owners(Relighter(spec, dit, tok, refiner=Refiner(config))) == {"refiner": ["relit", "albedo"]}
    table = {0.5: {"relit": 21.0, "albedo": 20.0}, 0.8: {"relit": 22.0, "albedo": 20.01}, 1.0: {"relit": 21.5, "albedo": 20.0}}
    assert calibrate.best_strengths(table, {"relit_refiner": ["relit"], "refiner": ["albedo"]}) == \
        {"relit_refiner": 0.8, "refiner": 1.0}                        # albedo's +0.01 dB is noise: stays 1
    assert calibrate.best_strengths(table, {"refiner": ["relit", "albedo"]}) == {"refiner": 0.8}
    # measured through the Relighter: strength 0 gives the model without that refiner, and the
    # refiners' own configs come back as they were
    frames = np.random.default_rng(3).random((2, 32, 32, 3)).astype(np.float32)
    probe = np.ones((16, 32, 3), np.float32)
    item = type("Item", (), {"input": frames, "probe": probe, "target": frames[::-1].copy(),
                             "albedo": frames * 0.5, "mask": np.ones((2, 32, 32), bool)})()
    with torch.no_grad():
        torch.nn.init.normal_(both.refiner.head.weight, std=0.1)
        torch.nn.init.normal_(both.relit_refiner.head.weight, std=0.1)
    measured = calibrate.measure_strengths(both, [item], grid=(0.0, 1.0))
    plain = calibrate.measure_strengths(Relighter(spec, dit, tok), [item], grid=(1.0,))[1.0]
    assert measured[0.0] == pytest.approx(plain, abs=1e-4) and measured[1.0] != pytest.approx(plain, abs=1e-3)
    assert both.refiner.config.strength == both.relit_refiner.config.strength == 1.0


def test_the_dits_outputs_for_training_average_the_models_shifted_copies_as_the_relighter_does(tmp_path):
    """`refine.dit_outputs` gives the refiner what `Relighter` feeds it: with `shift_average` 2 the mean of
    the copy on the input and the copy on the input rolled by half a token (4 px; the same noise), rolled back; the strip
    the roll wrapped across the border (the first token row and column of the rolled copy) is the first
    copy's alone. The outputs file records the count and one made with another is refused."""
    from relight_core.checkpoint import save_model
    from relight_core.pipeline import copies_mean

    root = write_pack_dataset(tmp_path / "data", scenes=2)
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    pack = refine.load_packs([tmp_path / "p.npz"])
    items = [(0, 0, 0), (0, 1, 0), (1, 1, 0)]
    spec, dit, tok = residual_model()
    one = save_model(tmp_path / "one", spec, dit, tok)
    two = save_model(tmp_path / "two", replace(spec, shift_average=2), dit, tok)
    single = refine.dit_outputs(one, pack, items, log=lambda m: None)
    both = refine.dit_outputs(two, pack, items, log=lambda m: None)
    assert single["relit"].shape == both["relit"].shape == (3, 3, 32, 32)
    for key in ("relit", "albedo"):
        moved = (both[key].astype(int) - single[key]).__abs__()
        assert moved[..., 4:-4, 4:-4].mean() > 1                      # the copies changed the frames inside ...
        assert moved[..., :4, :].max() <= 1 and moved[..., :, -4:].max() <= 1  # ... not the first copy's strip
    # Built by hand: the DiT's frames on the rolled input, rolled back, averaged without the wrapped strip.
    rolled = refine.dit_outputs(one, {**pack, "rgb": pack["rgb"].roll((4, 4), dims=(-2, -1)),
                                      "albedo": pack["albedo"].roll((4, 4), dims=(-2, -1))}, items, log=lambda m: None)
    for key in ("relit", "albedo"):
        entries = np.stack([single[key], rolled[key]]).astype(np.float32).transpose(0, 1, 3, 4, 2)
        by_hand = copies_mean(entries, [(False, (0, 0)), (False, (4, 4))], 8).transpose(0, 3, 1, 2)
        assert np.abs(by_hand - both[key]).max() <= 1                 # rounding to uint8 once or twice
    # A DiT that proposes no change gives back its input through the copies, every pixel in its place.
    with torch.no_grad():
        dit.final_layer.linear.weight.zero_()
    still = refine.dit_outputs(save_model(tmp_path / "still", replace(spec, shift_average=2), dit, tok), pack, items,
                               log=lambda m: None)
    sources = pack["rgb"][[0, 0, 1], [1, 0, 0]].numpy()
    assert np.abs(still["relit"].astype(int) - sources).max() <= 3    # what σ 80's skip lets through of the noise
    # The cache: the count is recorded, the same file serves the same count and refuses another.
    path = tmp_path / "outputs.npz"
    refine.cached_outputs(path, two, pack, items, log=lambda m: None)
    assert int(np.load(path)["copies"]) == 2
    again = refine.cached_outputs(path, two, pack, items, log=lambda m: pytest.fail(m))
    np.testing.assert_array_equal(again["albedo"], both["albedo"])
    with pytest.raises(ValueError, match="averaged over 2 shifted copies and this model runs 1 .*new --out"):
        refine.cached_outputs(path, one, pack, items[:1], log=lambda m: None)


def test_the_dits_outputs_for_training_take_the_residual_gain_as_often_as_the_relighter_does(tmp_path):
    """A one-step run applies the albedo gain at each network call: once where the schedule ends at 0
    (`final_denoise` false, the shipped model), twice with the clean-up call at σ_min; `dit_outputs` too, so
    that a refiner trains on the frames it is given in use."""
    from relight_core.checkpoint import save_model

    root = write_pack_dataset(tmp_path / "data", scenes=1)
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    pack = refine.load_packs([tmp_path / "p.npz"])
    items = [(0, 0, 0), (0, 1, 0)]
    spec, dit, tok = residual_model()
    with torch.no_grad():
        dit.final_layer.linear.weight.normal_(std=0.2)    # a clear albedo offset for the gain to scale
    source = pack["rgb"][[0, 0], [1, 0]].numpy().astype(float)
    offsets = {}
    for final in (False, True):
        for gain in (1.0, 0.5):
            model = save_model(tmp_path / f"m-{final}-{gain}", replace(spec, final_denoise=final,
                                                                       residual_gain=(1.0, gain)), dit, tok)
            out = refine.dit_outputs(model, pack, items, log=lambda m: None)
            offsets[final, gain] = out["albedo"].astype(float) - source
    for final, power in ((False, 1), (True, 2)):
        full, scaled = offsets[final, 1.0], offsets[final, 0.5]
        inside = (np.abs(full) > 20) & (np.abs(full) < 230)   # not clipped at 0 or 255 either way
        assert inside.mean() > 0.2
        np.testing.assert_allclose(scaled[inside], 0.5 ** power * full[inside], atol=1.5)


def test_a_model_folder_from_a_refiner_run_keeps_how_the_model_ran_that_slot_not_its_strength(tmp_path):
    model, run = tmp_path / "model", tmp_path / "run"
    model.mkdir()
    run.mkdir()
    config = {"name": "m", "refiner": {**SMALL.to_dict(), "grid_shift": 8, "strength": 0.5}}
    (model / "config.json").write_text(json.dumps(config))
    for path in (model / "dit.safetensors", model / REFINER_FILE, run / REFINER_FILE):
        save_file({"w": torch.zeros(1)}, path)
    best = {"refiner": SMALL.to_dict(), "step": 3, "val": {}, "start": {}, "train_items": 2, "val_items": 1}
    written = json.loads((refine.write_model(model, run, tmp_path / "out", best) / "config.json").read_text())
    assert written["refiner"] == {**SMALL.to_dict(), "grid_shift": 8}
    # a model without it in that slot writes the run's config as it is
    config["refiner"].pop("grid_shift")
    (model / "config.json").write_text(json.dumps(config))
    written = json.loads((refine.write_model(model, run, tmp_path / "out2", best) / "config.json").read_text())
    assert written["refiner"] == SMALL.to_dict()


def _model_folder(folder, relit_strength=0.85):
    """A residual pixel model folder with both refiners (the relit one at a strength, as shipped)."""
    spec, dit, _ = residual_model()
    folder.mkdir()
    save_file({k: v.contiguous() for k, v in dit.state_dict().items()}, folder / "dit.safetensors")
    albedo_refiner = _randomised(Refiner(replace(SMALL, base="filtered", clips=("albedo",))), 0.05)
    relit_refiner = _randomised(Refiner(replace(SMALL, base="filtered", clips=("relit",), lighting=True,
                                                relit_gain=4, strength=relit_strength)), 0.05)
    data = replace(spec, refiner=albedo_refiner.config.to_dict(), relit_refiner=relit_refiner.config.to_dict(),
                   shift_average=2).to_json()
    (folder / "config.json").write_text(json.dumps(data))
    save_file(albedo_refiner.state_dict(), folder / REFINER_FILE)
    save_file(relit_refiner.state_dict(), folder / RELIT_REFINER_FILE)
    return dit


def test_assemble_swaps_a_gpu_rounds_dit_or_a_refiner_into_a_model_that_keeps_how_it_runs(tmp_path, capsys):
    from relight_core.training import assemble
    from relight_core.training.fast import write_shards

    like = tmp_path / "like"
    _model_folder(like)
    # A GPU round hands back shards + the DiT's own config (no refiners, no copies, its notes).
    torch.manual_seed(5)
    new = JointDiT(resolve_model(like)[0].dit)
    round_dir = tmp_path / "round"
    round_dir.mkdir()
    assert write_shards({k: v.to(torch.bfloat16) for k, v in new.state_dict().items()}, round_dir) >= 1
    config = json.loads((like / "config.json").read_text())
    bare = {k: config[k] for k in ("name", "dit", "tokenizer", "size", "residual")}
    (round_dir / "config.json").write_text(json.dumps({**bare, "notes": {"picked": {"from": "mean"}}}))
    retrained = _randomised(Refiner(RefinerConfig.from_dict(config["relit_refiner"])), 0.02)
    save_file(retrained.state_dict(), tmp_path / "relit.safetensors")
    assert assemble.main(["--like", str(like), "--dit", str(round_dir), "--relit-refiner", str(tmp_path / "relit.safetensors"),
                          "--bf16", "--out", str(tmp_path / "new")]) == 0
    made = json.loads((tmp_path / "new" / "config.json").read_text())
    assert made["refiner"] == config["refiner"] and made["relit_refiner"] == config["relit_refiner"]   # strength too
    assert made["shift_average"] == 2 and made["notes"]["dit_round"] == {"picked": {"from": "mean"}}
    stored = load_file(tmp_path / "new" / "dit.safetensors")
    assert all(v.dtype == torch.bfloat16 and torch.equal(v, new.state_dict()[k].to(torch.bfloat16)) for k, v in stored.items())
    spec, directory = resolve_model(tmp_path / "new")
    relit = load_refiner(spec, directory, slot="relit_refiner")
    assert torch.equal(relit.head.weight, retrained.head.weight.to(torch.bfloat16).float())
    albedo = load_refiner(spec, directory)                                   # the slot not given: like's, in bf16
    assert torch.equal(albedo.head.weight, load_file(like / REFINER_FILE)["head.weight"].to(torch.bfloat16).float())
    assert Relighter.load(str(tmp_path / "new")).relit_refiner.config.strength == 0.85
    # Another network, weights that do not fit the slot, a slot the model lacks: one sentence each.
    (round_dir / "config.json").write_text(json.dumps({**bare, "dit": {**bare["dit"], "width": 64}}))
    with pytest.raises(SystemExit):
        assemble.main(["--like", str(like), "--dit", str(round_dir), "--out", str(tmp_path / "x")])
    assert "is another network than" in capsys.readouterr().err
    save_file(Refiner(replace(SMALL, widths=(4, 8, 8))).state_dict(), tmp_path / "wide.safetensors")
    with pytest.raises(SystemExit):
        assemble.main(["--like", str(like), "--refiner", str(tmp_path / "wide.safetensors"), "--out", str(tmp_path / "y")])
    assert "does not load" in capsys.readouterr().err
    (tmp_path / "torn.safetensors").write_bytes(b"\x10\x00\x00\x00not a header")
    with pytest.raises(SystemExit):
        assemble.main(["--like", str(like), "--refiner", str(tmp_path / "torn.safetensors"), "--out", str(tmp_path / "t")])
    assert "is not a readable safetensors file" in capsys.readouterr().err
    del config["relit_refiner"]
    (like / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit):
        assemble.main(["--like", str(like), "--relit-refiner", str(tmp_path / "relit.safetensors"), "--out", str(tmp_path / "z")])
    assert "has no \"relit_refiner\"" in capsys.readouterr().err


def test_refit_fits_a_models_own_refiner_again_from_its_config_and_weights(tmp_path, capsys):
    model = tmp_path / "model"
    _model_folder(model)
    root = write_pack_dataset(tmp_path / "data", scenes=3)
    write_pack(root, "train", tmp_path / "p.npz", lighting_size=8)
    write_pack(root, "train", tmp_path / "val.npz", lighting_size=8, limit=1)
    args = ["--model", str(model), "--pack", str(tmp_path / "p.npz"), "--val-pack", str(tmp_path / "val.npz"),
            "--refit", "--slot", "relit_refiner", "--batch", "2", "--minutes", "0.02", "--val-every-minutes", "0.01",
            "--lr", "0", "--out", str(tmp_path / "run")]
    assert refine.main(args) == 0
    assert "starting from the refiner in" in capsys.readouterr().out
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    shipped = json.loads((model / "config.json").read_text())["relit_refiner"]
    assert best["refiner"] == {k: v for k, v in shipped.items() if k != "strength"}   # its shape; training uses 1
    # At lr 0 nothing beats the start, and the start is what is kept (step 0), not the first validation's.
    assert best["step"] == 0 and best["val"]["relit"] == best["start"]["init"]["relit"]
    kept, start = load_file(tmp_path / "run" / "refiner.safetensors"), load_file(model / RELIT_REFINER_FILE)
    assert all(torch.equal(kept[k], start[k]) for k in start)
    config = json.loads((model / "config.json").read_text())
    del config["relit_refiner"]
    (model / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit):
        refine.main([*args[:-1], str(tmp_path / "run2")])
    assert "names no refiner in \"relit_refiner\"" in capsys.readouterr().err
