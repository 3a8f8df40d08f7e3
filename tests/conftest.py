"""Fixtures shared by several test modules (helpers without fixtures live in factory.py)."""

import sys
import tempfile
from types import SimpleNamespace

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


@pytest.fixture(scope="session")
def _client_scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("gradio-client")


@pytest.fixture(autouse=True)
def _gradio_client_downloads_in_pytest_tmp(_client_scratch, monkeypatch):
    """gradio_client (2.x, `Client._download_file`) downloads every output file through a folder it
    makes in the system temp folder and never removes: the suite's API tests left ~1,000 empty
    folders in /tmp a run. Its temp folder is pytest's here; nothing else's temp folder changes."""
    module = sys.modules.get("gradio_client.client")
    if module is not None:
        monkeypatch.setattr(module, "tempfile", SimpleNamespace(
            gettempdir=lambda: str(_client_scratch), TemporaryDirectory=tempfile.TemporaryDirectory))


_shared_ray = []  # [(the connect() context, its address)] while the shared instance runs


@pytest.fixture(scope="module")
def ray_address(request):
    """One local Ray instance (2 CPUs) for every module that uses this fixture (test_batch.py,
    test_data_autolabel.py, test_data_render.py): started by the first, stopped after
    the last, so the session pays Ray's start once and no Ray process idles beside the other modules.
    Runs in this process (batch, render-data, autolabel) reuse its connection."""
    from relight_core.batch import connect

    if not _shared_ray:
        context = connect(num_cpus=2)
        ray = context.__enter__()
        _shared_ray.append((context, ray.get_runtime_context().gcs_address))
    yield _shared_ray[0][1]
    users = [item.module for item in request.session.items if "ray_address" in item.fixturenames]
    if not users or users[-1] is request.module:
        _shared_ray.pop()[0].__exit__(None, None, None)
