"""Training: the conditioning recipe, lighting dropout, learning, exact resume, export → Relighter."""

import argparse
import json

import numpy as np
import pytest
import torch

from relight_core.data.dataset import write_manifest
from relight_core.dit import CHANNELS, LIGHTING_CHANNELS, pack_lighting
from relight_core.training import add_training_commands
from relight_core.training.autoencoder import TokenizerTrainConfig, train_tokenizer
from relight_core.training.joint import DiTTrainConfig, train_dit, train_step
from relight_core.training.latents import build_latent_set, image_frame_indices
from relight_core.training.loop import load_checkpoint, step_generator
from relight_core.training.recipe import MODES, Recipe, make_example, sample_modes
from tests.factory import FRAMES, SIZE, write_scene

@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    for split, scenes in (("train", 3), ("test", 1)):
        for index in range(scenes):
            write_scene(root, split, index)
        write_manifest(root / split)
    return root


@pytest.fixture(scope="module")
def tokenizer_weights(dataset_root, tmp_path_factory):
    run = tmp_path_factory.mktemp("tok")
    config = TokenizerTrainConfig(data=dataset_root, run=run, preset="tiny", steps=4, clip_batch=2,
                                  image_batch=4, crop=32, log_every=1, val_every=2)
    return train_tokenizer(config, progress=False)


def dit_config(dataset_root, tokenizer_weights, run, **overrides):
    base = dict(data=dataset_root, run=run, tokenizer=tokenizer_weights, tokenizer_preset="tiny", preset="tiny",
                steps=4, video_batch=2, image_batch=4, log_every=1, val_every=2, cache=run.parent / "cache")
    return DiTTrainConfig(**{**base, **overrides})


def fake_latents(b=4, t=2):
    g = torch.Generator().manual_seed(0)
    z = lambda: torch.randn(b, 16, t, 4, 4, generator=g)  # noqa: E731
    return z(), z(), z(), pack_lighting(z(), z(), z())


# --- the conditioning recipe ---------------------------------------------------------------------


def test_mode_frequencies_match_the_recipe():
    recipe = Recipe()
    modes = sample_modes(40000, recipe, torch.Generator().manual_seed(1))
    share = {m: float((modes == i).float().mean()) for i, m in enumerate(MODES)}
    assert share["default"] == pytest.approx(0.70, abs=0.01)
    assert share["albedo_only"] == pytest.approx(0.12, abs=0.01)
    assert share["both"] == pytest.approx(0.18, abs=0.01)
    no_input = sample_modes(100, recipe, torch.Generator().manual_seed(1), has_input=torch.zeros(100, dtype=bool))
    assert (no_input == MODES.index("albedo_only")).all()


def test_each_mode_sets_masks_and_zeros():
    inp, relit, albedo, lighting = fake_latents(b=64)
    recipe = Recipe(p_continue=0.0, p_drop_lighting=0.0)
    ex = make_example(inp, relit, albedo, lighting, recipe, torch.Generator().manual_seed(0))
    t = 2
    assert set(ex.modes.tolist()) == {0, 1, 2}
    for b, mode in enumerate(ex.modes.tolist()):
        mask = ex.condition_mask[b, 0, :, 0, 0]
        assert mask[:t].eq(1).all() and mask[t:2 * t].eq(0).all()          # input given, relit denoised
        assert mask[2 * t:].eq(0 if MODES[mode] == "default" else 1).all()  # albedo given unless default
        expected_input = torch.zeros_like(inp[b]) if MODES[mode] == "albedo_only" else inp[b]
        assert torch.equal(ex.x0[b, :, :t], expected_input)
        assert torch.equal(ex.x0[b, :, t:2 * t], relit[b]) and torch.equal(ex.x0[b, :, 2 * t:], albedo[b])
        assert torch.equal(ex.lighting[b], lighting[b])


def test_lighting_dropout_zeroes_latents_and_masks():
    inp, relit, albedo, lighting = fake_latents(b=2000, t=1)
    ex = make_example(inp, relit, albedo, lighting, Recipe(), torch.Generator().manual_seed(3))
    dropped = ex.lighting_dropped
    assert float(dropped.float().mean()) == pytest.approx(0.10, abs=0.02)
    assert ex.lighting[dropped].abs().sum() == 0                           # latents and the three masks
    assert torch.equal(ex.lighting[~dropped], lighting[~dropped])
    no_probe = make_example(inp[:8], relit[:8], albedo[:8], lighting[:8], Recipe(p_drop_lighting=0.0),
                            torch.Generator(), has_lighting=torch.zeros(8, dtype=bool))
    assert no_probe.lighting.abs().sum() == 0


def test_continuation_gives_first_relit_and_albedo_frame_of_videos_only():
    inp, relit, albedo, lighting = fake_latents(b=8, t=2)
    ex = make_example(inp, relit, albedo, lighting, Recipe(p_continue=1.0, p_albedo_only=0, p_both=0),
                      torch.Generator())
    assert ex.condition_mask[:, 0, :, 0, 0].tolist() == [[1, 1, 1, 0, 1, 0]] * 8
    image = make_example(*(x[:, :, :1] for x in (inp, relit, albedo, lighting)),
                         Recipe(p_continue=1.0, p_albedo_only=0, p_both=0), torch.Generator())
    assert image.condition_mask[:, 0, :, 0, 0].tolist() == [[1, 0, 0]] * 8


def test_condition_frames_enter_the_network_nearly_clean():
    """The network sees given clips as x_cond·c_in(0.001) whatever σ, as `ConditionedDenoiser` feeds them."""
    from relight_core.checkpoint import load_model

    _, dit, _ = load_model("tiny")
    seen = {}
    original = dit.forward

    def spy(x, c_noise, context=None):
        seen["x"] = x.detach()
        return original(x, c_noise, context)

    dit.forward = spy
    inp, relit, albedo, lighting = fake_latents(b=2, t=1)
    batch = {"input": inp, "relit": relit, "albedo": albedo, "lighting": lighting,
             "has_input": torch.ones(2, dtype=bool), "has_lighting": torch.ones(2, dtype=bool)}
    recipe = Recipe(p_albedo_only=0, p_both=0, p_continue=0, p_drop_lighting=0)
    train_step(dit, batch, recipe, torch.Generator().manual_seed(0))
    c_in = 1 / (0.001 ** 2 + 0.25) ** 0.5
    noisy = seen["x"][:, CHANNELS["noisy"]]
    torch.testing.assert_close(noisy[:, :, :1].float(), inp * c_in, atol=0.02, rtol=0.02)
    assert seen["x"][:, CHANNELS["condition_mask"]][:, 0, :, 0, 0].tolist() == [[1, 0, 0]] * 2
    assert seen["x"][:, CHANNELS["env_ldr_mask"]][:, 0, :, 0, 0].tolist() == [[0, 1, 0]] * 2


# --- latents, learning, resume, export -----------------------------------------------------------


def test_latent_cache_has_every_stream_and_is_reused(dataset_root, tokenizer_weights, tmp_path):
    from relight_core.data.dataset import RelightDataset
    from relight_core.tokenizer import build_tokenizer

    tokenizer = build_tokenizer({"type": "causal-ae", "preset": "tiny", "weights": str(tokenizer_weights)})
    dataset = RelightDataset(dataset_root, "train")
    latents = build_latent_set(dataset, tokenizer, tmp_path, progress=False)
    assert len(latents) == len(dataset) == 6
    scene = latents.scenes[0]
    for name in ("rgb0", "rgb1", "albedo", "env0_ldr", "env1_log", "env1_dir"):
        assert scene[f"{name}/video"].shape == (16, 2, SIZE // 8, SIZE // 8)
        assert scene[f"{name}/image"].shape == (len(image_frame_indices(FRAMES)), 16, 1, SIZE // 8, SIZE // 8)
    # Causal tokenizer: the first frame alone encodes to the clip's first latent frame.
    torch.testing.assert_close(scene["rgb0/image"][0, :, 0].float(), scene["rgb0/video"][:, 0].float(),
                               atol=2e-2, rtol=2e-2)
    again = build_latent_set(dataset, tokenizer, tmp_path, progress=False)
    assert all(torch.equal(again.scenes[0][k], v) for k, v in scene.items())
    batch = latents.batch([0, 1])
    # Item 0 is light 0 → 1 and item 1 is 1 → 0 of the same scene: input and target swap.
    assert torch.equal(batch["input"][0], batch["relit"][1]) and torch.equal(batch["relit"][0], batch["input"][1])
    assert batch["lighting"].shape == (2, LIGHTING_CHANNELS, 2, SIZE // 8, SIZE // 8)


def test_loss_decreases_on_a_fixed_batch(dataset_root, tokenizer_weights, tmp_path):
    from relight_core.checkpoint import load_model
    from relight_core.data.dataset import RelightDataset
    from relight_core.tokenizer import build_tokenizer
    from relight_core.training.loop import make_optimizer

    tokenizer = build_tokenizer({"type": "causal-ae", "preset": "tiny", "weights": str(tokenizer_weights)})
    latents = build_latent_set(RelightDataset(dataset_root, "train"), tokenizer, tmp_path, progress=False)
    batch = latents.batch([0, 1, 2, 3])
    torch.manual_seed(0)
    _, dit, _ = load_model("tiny")
    dit.train().requires_grad_(True)
    optimizer = make_optimizer(dit, 3e-3, (0.9, 0.99), 0.0)
    recipe = Recipe(p_albedo_only=0, p_both=0, p_continue=0, p_drop_lighting=0)
    losses = []
    for _ in range(25):
        loss, _ = train_step(dit, batch, recipe, torch.Generator().manual_seed(0))   # same σ and noise
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_resume_continues_exactly(dataset_root, tokenizer_weights, tmp_path):
    straight = dit_config(dataset_root, tokenizer_weights, tmp_path / "straight", steps=4, log_every=1)
    train_dit(straight, progress=False)
    split = dit_config(dataset_root, tokenizer_weights, tmp_path / "split", steps=2, log_every=1)
    train_dit(split, progress=False)
    train_dit(dit_config(dataset_root, tokenizer_weights, tmp_path / "split", steps=4, log_every=1), progress=False)

    def losses(run):
        lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
        return [(r["step"], r["loss"]) for r in lines if "loss" in r]

    assert losses(tmp_path / "straight") == losses(tmp_path / "split")
    assert [s for s, _ in losses(tmp_path / "split")] == [1, 2, 3, 4]
    a = load_checkpoint(tmp_path / "straight", ["dit", "ema"])
    b = load_checkpoint(tmp_path / "split", ["dit", "ema"])
    assert a["step"] == b["step"] == 4
    for name in ("dit", "ema"):
        for key, value in a["modules"][name].items():
            assert torch.equal(value, b["modules"][name][key]), (name, key)


def test_step_generator_depends_only_on_seed_and_step():
    assert torch.equal(torch.rand(3, generator=step_generator(0, 5)), torch.rand(3, generator=step_generator(0, 5)))
    assert not torch.equal(torch.rand(3, generator=step_generator(0, 5)), torch.rand(3, generator=step_generator(0, 6)))


def test_tokenizer_run_logs_and_resumes(dataset_root, tokenizer_weights):
    run = tokenizer_weights.parent.parent
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if "l1" in r] == [1, 2, 3, 4]
    assert {r["kind"] for r in records if "l1" in r} == {"video", "image"}
    assert any("val_l1" in r for r in records)
    assert load_checkpoint(run, ["model"])["step"] == 4


def test_export_loads_in_the_relighter_and_runs(dataset_root, tokenizer_weights, tmp_path):
    from relight_core.pipeline import Relighter, RelightRequest

    out = tmp_path / "model"
    summary = train_dit(dit_config(dataset_root, tokenizer_weights, tmp_path / "run", steps=2, export=out),
                        progress=False)
    assert summary["steps"] == 2 and "val_loss" in summary
    config = json.loads((out / "config.json").read_text())
    assert config["trained"] and config["size"] == SIZE and config["chunk_frames"] == FRAMES
    assert config["notes"]["steps"] == 2
    relighter = Relighter.load(str(out), device="cpu")
    frames = np.random.default_rng(0).random((1, SIZE, SIZE, 3), dtype=np.float32)
    probe = torch.full((8, 16, 3), 0.5)
    result = relighter.relight(RelightRequest(frames=frames, probe=probe, steps=2))
    assert result.relit.shape == frames.shape and np.isfinite(result.relit).all()
    assert result.info["trained"]


def test_cli_registers_both_commands(tmp_path):
    parser = argparse.ArgumentParser()
    add_training_commands(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["train", "--data", str(tmp_path), "--run", str(tmp_path / "r"),
                              "--tokenizer", "t.safetensors", "--minutes", "1.5"])
    assert args.minutes == 1.5 and args.preset == "small" and callable(args.func)
    args = parser.parse_args(["train-tokenizer", "--data", str(tmp_path), "--run", str(tmp_path / "r")])
    assert args.crop == 64 and callable(args.func)
    from relight_core.errors import InputError
    with pytest.raises(InputError, match="no train/ split"):
        args.func(args)
