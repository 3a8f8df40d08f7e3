"""Importing the released UniRelight files: renamed weights, safe loading, a runnable folder."""

import numpy as np
import pytest
import torch

from relight_core.checkpoint import load_model
from relight_core.dit import DiTConfig
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.released import import_released
from tests.factory import MINI

# The released architecture in miniature: cross-attention on, as in the 7B network.
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
