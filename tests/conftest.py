"""Fixtures shared by several test modules (helpers without fixtures live in factory.py)."""

import pytest
import torch

from relight_core.dit import JointDiT
from relight_core.released import released_to_ours
from tests.factory import MINI, FakeCosmosDecoder, FakeCosmosEncoder, released_names


@pytest.fixture()
def released_files(tmp_path):
    torch.manual_seed(0)
    ours = JointDiT(MINI).state_dict()
    for value in ours.values():
        value.normal_()  # every weight distinct, so a wrong mapping cannot go unnoticed
    state = {"net." + name: ours[released_to_ours(name)].clone() for name in released_names(MINI.depth)}
    state["net.pos_embedder.seq"] = torch.arange(8.0)
    state["logvar.0.weight"] = torch.zeros(1, 128)
    torch.save({"model": state}, tmp_path / "model.pt")
    tokenizer = tmp_path / "Cosmos-Tokenize1-CV8x8x8-720p"
    tokenizer.mkdir()
    torch.jit.script(FakeCosmosEncoder()).save(str(tokenizer / "encoder.jit"))
    torch.jit.script(FakeCosmosDecoder()).save(str(tokenizer / "decoder.jit"))
    return tmp_path / "model.pt", tokenizer, ours
