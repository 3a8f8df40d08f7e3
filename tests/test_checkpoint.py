"""Model folders: save/load round trips, presets, and one-sentence errors on broken folders."""

import json

import pytest
import torch
from safetensors.torch import load_file, save_file

from relight_core.checkpoint import (CONFIG_FILE, DIT_FILE, MODEL_PRESETS, ModelSpec, load_model, resolve_model,
                                     save_model)
from relight_core.errors import InputError


@pytest.fixture()
def saved_tiny(tmp_path):
    torch.manual_seed(0)
    spec, dit, tokenizer = load_model("tiny")
    save_model(tmp_path, spec, dit, tokenizer)
    return tmp_path, spec, dit, tokenizer


def test_spec_json_round_trip():
    for spec in MODEL_PRESETS.values():
        assert ModelSpec.from_json(json.loads(json.dumps(spec.to_json()))) == spec


def test_offset_filter_round_trips_and_a_bad_one_is_one_sentence():
    data = MODEL_PRESETS["tiny"].to_json()
    data["offset_filter"] = [16, 8]
    assert ModelSpec.from_json(json.loads(json.dumps(data))).offset_filter == (16, 8)
    for bad in ([16], [-1, 2], [2.5, 2], "8", [True, 0]):
        data["offset_filter"] = bad
        with pytest.raises(InputError, match="offset_filter .* two whole numbers"):
            ModelSpec.from_json(data)


def test_save_then_load_gives_identical_weights(saved_tiny):
    directory, spec, dit, tokenizer = saved_tiny
    spec2, dit2, tokenizer2 = load_model(directory)
    assert spec2 == spec
    for (k, v), (k2, v2) in zip(dit.state_dict().items(), dit2.state_dict().items()):
        assert k == k2 and torch.equal(v, v2)
    for (k, v), (k2, v2) in zip(tokenizer.state_dict().items(), tokenizer2.state_dict().items()):
        assert k == k2 and torch.equal(v, v2)


def test_missing_weights_file_is_named(saved_tiny):
    directory = saved_tiny[0]
    (directory / DIT_FILE).unlink()
    with pytest.raises(InputError, match="missing dit.safetensors"):
        load_model(directory)


def test_missing_config_is_named(saved_tiny):
    directory = saved_tiny[0]
    (directory / CONFIG_FILE).unlink()
    with pytest.raises(InputError, match="no config.json"):
        load_model(directory)


def test_shape_mismatch_is_reported(saved_tiny):
    directory = saved_tiny[0]
    state = load_file(str(directory / DIT_FILE))
    name = next(k for k, v in state.items() if v.ndim == 2)
    state[name] = torch.zeros(state[name].shape[0] + 1, state[name].shape[1])
    save_file(state, str(directory / DIT_FILE))
    with pytest.raises(InputError, match="wrong shape"):
        load_model(directory)


def test_corrupt_weights_file(saved_tiny):
    directory = saved_tiny[0]
    (directory / DIT_FILE).write_bytes(b"not a safetensors file")
    with pytest.raises(InputError, match="not a readable safetensors"):
        load_model(directory)


def test_unknown_model_name(tmp_path):
    with pytest.raises(InputError, match="neither a model directory nor a preset"):
        resolve_model(tmp_path / "nowhere")


def test_default_falls_back_to_an_untrained_preset_when_nothing_ships(monkeypatch, tmp_path):
    import relight_core.checkpoint as checkpoint
    monkeypatch.setattr(checkpoint, "DEFAULT_MODEL_DIR", tmp_path / "absent")
    spec, directory = resolve_model("default")
    assert directory is None and not spec.trained
