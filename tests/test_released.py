"""Importing the released UniRelight files: renamed weights, safe loading, a runnable folder."""

import numpy as np
import pytest
import torch

from relight_core.checkpoint import load_model
from relight_core.dit import DiTConfig, JointDiT, released_to_ours
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.released import import_released
from tests.test_tokenizer import FakeCosmosDecoder, FakeCosmosEncoder

# The released architecture in miniature: cross-attention on, as in the 7B network.
MINI = DiTConfig(width=64, depth=2, num_heads=2, adaln_lora_dim=16, cross_attention=True, context_dim=32)


def _released_names(depth: int) -> list[str]:
    """Parameter names of a released GeneralDIT (FA-CA-MLP blocks), as stored under `net.`."""
    names = ["x_embedder.proj.1.weight", "view_embeddings.weight", "t_embedder.1.linear_1.weight",
             "t_embedder.1.linear_2.weight", "affline_norm.weight", "final_layer.linear.weight",
             "final_layer.adaLN_modulation.1.weight", "final_layer.adaLN_modulation.2.weight"]
    for i in range(depth):
        for j in range(3):
            names += [f"blocks.block{i}.blocks.{j}.adaLN_modulation.{k}.weight" for k in (1, 2)]
        for j in range(2):
            names += [f"blocks.block{i}.blocks.{j}.block.attn.{p}.weight"
                      for p in ("to_q.0", "to_q.1", "to_k.0", "to_k.1", "to_v.0", "to_out.0")]
        names += [f"blocks.block{i}.blocks.2.block.layer{k}.weight" for k in (1, 2)]
    return names


@pytest.fixture()
def released_files(tmp_path):
    torch.manual_seed(0)
    ours = JointDiT(MINI).state_dict()
    for value in ours.values():
        value.normal_()  # every weight distinct, so a wrong mapping cannot go unnoticed
    state = {"net." + name: ours[released_to_ours(name)].clone() for name in _released_names(MINI.depth)}
    state["net.pos_embedder.seq"] = torch.arange(8.0)
    state["logvar.0.weight"] = torch.zeros(1, 128)
    torch.save({"model": state}, tmp_path / "model.pt")
    tokenizer = tmp_path / "Cosmos-Tokenize1-CV8x8x8-720p"
    tokenizer.mkdir()
    torch.jit.script(FakeCosmosEncoder()).save(str(tokenizer / "encoder.jit"))
    torch.jit.script(FakeCosmosDecoder()).save(str(tokenizer / "decoder.jit"))
    return tmp_path / "model.pt", tokenizer, ours


def test_import_renames_every_weight_and_the_folder_runs(released_files, tmp_path):
    checkpoint, tokenizer, ours = released_files
    folder = import_released(checkpoint, tokenizer, tmp_path / "unirelight", dit_config=MINI)
    spec, dit, _ = load_model(folder)
    assert spec.trained and spec.dit == MINI
    for name, value in dit.state_dict().items():
        assert torch.equal(value, ours[name]), name
    relighter = Relighter.load(folder, device="cpu")
    probe = np.ones((8, 16, 3), np.float32)
    result = relighter.relight(RelightRequest(np.full((1, 16, 32, 3), 0.5, np.float32), probe=probe, steps=1))
    assert result.relit.shape == (1, 16, 32, 3) and np.isfinite(result.relit).all()


def test_architecture_mismatch_is_one_sentence(released_files, tmp_path):
    checkpoint, tokenizer, _ = released_files
    with pytest.raises(InputError, match="does not match the UniRelight 7B architecture"):
        import_released(checkpoint, tokenizer, tmp_path / "out",
                        dit_config=DiTConfig(width=64, depth=3, num_heads=2, adaln_lora_dim=16, cross_attention=True,
                                             context_dim=32))


class _Payload:
    """Any pickled object: loading it would run code, so weights_only loading must refuse it."""


def test_a_pickle_with_objects_is_refused(released_files, tmp_path):
    _, tokenizer, _ = released_files
    torch.save({"model": _Payload()}, tmp_path / "evil.pt")
    with pytest.raises(InputError, match="not a readable PyTorch checkpoint"):
        import_released(tmp_path / "evil.pt", tokenizer, tmp_path / "out", dit_config=MINI)


def test_missing_tokenizer_files(released_files, tmp_path):
    checkpoint, _, _ = released_files
    with pytest.raises(InputError, match="encoder.jit"):
        import_released(checkpoint, tmp_path, tmp_path / "out", dit_config=MINI)
