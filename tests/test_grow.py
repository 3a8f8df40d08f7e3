"""Growing a trained DiT in depth: same function, new blocks that learn."""

import json

import pytest
import torch

from relight_core.checkpoint import ModelSpec, load_model, save_model
from relight_core.dit import DiTConfig, JointDiT, channel_layout
from relight_core.errors import InputError
from relight_core.tokenizer import PixelTokenizer
from relight_core.training.grow import grow_model, grow_state, grown_order, main

CONFIG = DiTConfig(width=32, depth=4, num_heads=2, adaln_lora_dim=8, patch_spatial=1, out_channels=192)


def trained_like(config: DiTConfig) -> JointDiT:
    """A DiT whose adaLN-zero weights are non-zero, as after training (a fresh one is the identity)."""
    torch.manual_seed(0)
    dit = JointDiT(config)
    with torch.no_grad():
        for p in dit.parameters():
            if not p.abs().sum():
                p.normal_(std=0.05)
    return dit.eval()


def inputs(b=2):
    g = torch.Generator().manual_seed(1)
    channels = channel_layout(CONFIG.out_channels)["padding_mask"].stop  # what the network is fed
    return torch.randn(b, channels, 3, 4, 4, generator=g), torch.tensor([0.3, 2.0])


def test_grown_order_inserts_a_copy_after_every_n_blocks():
    assert grown_order(4, 2) == [(0, False), (1, False), (1, True), (2, False), (3, False), (3, True)]
    assert len(grown_order(8, 2)) == 12 and len(grown_order(8, 1)) == 16 and len(grown_order(3, 4)) == 3
    with pytest.raises(InputError):
        grown_order(4, 0)


def test_grown_network_computes_exactly_what_the_original_did():
    dit = trained_like(CONFIG)
    state, depth = grow_state(dit.state_dict(), CONFIG.depth, every=2)
    assert depth == 6
    grown = JointDiT(DiTConfig(**{**CONFIG.__dict__, "depth": depth})).eval()
    grown.load_state_dict(state)  # strict: every key of the deeper model present, none left over
    x, c_noise = inputs()
    with torch.no_grad():
        expected, got = dit(x, c_noise), grown(x, c_noise)
    assert expected.abs().mean() > 1e-3  # the output is not trivially zero
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)
    # The new block is a copy of its neighbour except for the zeroed residual writes.
    new, old = grown.blocks[2], dit.blocks[1]
    assert torch.equal(new.self_attn.q_proj.weight, old.self_attn.q_proj.weight)
    assert not new.self_attn.out_proj.weight.any() and not new.mlp.fc2.weight.any()


def test_the_new_blocks_learn_from_the_first_step():
    dit = trained_like(CONFIG)
    state, depth = grow_state(dit.state_dict(), CONFIG.depth, every=2)
    grown = JointDiT(DiTConfig(**{**CONFIG.__dict__, "depth": depth}))
    grown.load_state_dict(state)
    x, c_noise = inputs()
    grown(x, c_noise).square().mean().backward()
    for index in (2, 5):  # the two inserted blocks
        block = grown.blocks[index]
        assert block.self_attn.out_proj.weight.grad.abs().sum() > 0
        assert block.mlp.fc2.weight.grad.abs().sum() > 0


def saved(tmp_path, dit):
    spec = ModelSpec(name="t", dit=CONFIG, tokenizer={"type": "pixel", "patch": 8}, chunk_frames=1,
                     overlap_frames=0, size=32, steps=1, notes={"steps": 10})
    return save_model(tmp_path / "src", spec, dit, PixelTokenizer(8))


def test_grow_model_writes_a_loadable_folder(tmp_path):
    dit = trained_like(CONFIG)
    out, depth = grow_model(saved(tmp_path, dit), tmp_path / "grown", every=4)
    config = json.loads((out / "config.json").read_text())
    assert depth == config["dit"]["depth"] == 5 and config["notes"]["previous_notes"] == {"steps": 10}
    _, grown, _ = load_model(out)
    x, c_noise = inputs()
    with torch.no_grad():
        torch.testing.assert_close(grown(x, c_noise), dit(x, c_noise), rtol=0, atol=1e-6)
    with pytest.raises(InputError):
        grow_model("tiny", tmp_path / "nope")


def test_bad_folders_and_counts_get_one_sentence_not_a_traceback(tmp_path, capsys):
    source = saved(tmp_path, trained_like(CONFIG))
    config = json.loads((source / "config.json").read_text())
    config["dit"]["depth"] = 6  # the weights hold 4 blocks
    (source / "config.json").write_text(json.dumps(config))
    with pytest.raises(InputError, match="no block 4"):
        grow_model(source, tmp_path / "a")
    good = saved(tmp_path / "good", trained_like(CONFIG))
    cases = ((["--model", str(good), "--out", str(tmp_path / "b"), "--every", "0"], "--every takes"),
             (["--model", str(source), "--out", str(tmp_path / "c")], "Cannot read"))
    (source / "dit.safetensors").write_bytes(b"not safetensors")
    for argv, sentence in cases:
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {sentence}") and "Traceback" not in err and err.count("\n") == 1
