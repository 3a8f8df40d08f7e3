"""Compute precision follows the hardware (precision.py), never the dtype weights are stored in."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from relight_core import precision
from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, MODEL_PRESETS, ModelSpec, load_model, save_model
from relight_core.cli import main
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.precision import resolve_precision
from tests.factory import make_png


@pytest.fixture()
def fresh_cache(tmp_path, monkeypatch):
    """An empty precision cache and no verdicts remembered by this process."""
    monkeypatch.setenv("UNIRELIGHT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(precision, "_verdicts", {})
    monkeypatch.setattr(precision.platform, "machine", lambda: "x86_64")
    return tmp_path / "cache" / precision.CACHE_FILE


def _measured(fp32: float, bf16: float):
    calls = []

    def measure():
        calls.append(1)
        return {"fp32": fp32, "bf16": bf16}
    return measure, calls


def test_explicit_precisions_are_taken_as_asked():
    assert resolve_precision("fp32", "cpu") == torch.float32
    assert resolve_precision("bf16", "cpu") == torch.bfloat16
    assert resolve_precision("fp16", "cuda") == torch.float16


def test_fp16_on_the_cpu_and_unknown_names_are_one_sentence():
    with pytest.raises(InputError, match="fp16 runs only on a CUDA GPU"):
        resolve_precision("fp16", "cpu")
    with pytest.raises(InputError, match="Unknown precision 'half'"):
        resolve_precision("half", "cpu")


def test_auto_on_an_avx2_cpu_is_fp32_without_measuring(fresh_cache, monkeypatch):
    measure, calls = _measured(1.0, 1000.0)
    monkeypatch.setattr(precision, "measure_cpu_matmul", measure)
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX2")
    assert resolve_precision("auto", "cpu") == torch.float32
    assert not calls and not fresh_cache.exists()


def test_auto_picks_fp32_where_bf16_is_measured_slower(fresh_cache, monkeypatch):
    measure, calls = _measured(fp32=70.0, bf16=20.0)   # AVX-512 without native bf16
    monkeypatch.setattr(precision, "measure_cpu_matmul", measure)
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX512")
    assert resolve_precision("auto", "cpu") == torch.float32
    assert len(calls) == 1
    stored = json.loads(fresh_cache.read_text())
    assert stored[precision.cache_key()]["bf16_faster"] is False
    assert "AVX512" in precision.cache_key() and f"torch {torch.__version__}" in precision.cache_key()


def test_auto_picks_bf16_where_measured_faster_and_measures_once_per_machine(fresh_cache, monkeypatch):
    measure, calls = _measured(fp32=200.0, bf16=650.0)  # AMX
    monkeypatch.setattr(precision, "measure_cpu_matmul", measure)
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX512")
    assert resolve_precision("auto", "cpu") == torch.bfloat16
    monkeypatch.setattr(precision, "_verdicts", {})     # as a new process: the file answers
    assert resolve_precision("auto", "cpu") == torch.bfloat16
    assert len(calls) == 1
    # Another thread count is another entry: measured again.
    monkeypatch.setattr(precision, "cache_key", lambda: "same cpu | 7 threads")
    assert resolve_precision("auto", "cpu") == torch.bfloat16
    assert len(calls) == 2 and len(json.loads(fresh_cache.read_text())) == 2


def test_a_burst_of_load_during_one_turn_does_not_decide(monkeypatch):
    # bf16 twice as fast, but other work takes the cores during its first turn (as a render did once)
    rates = {"fp32": iter([100.0, 95.0, 100.0]), "bf16": iter([20.0, 210.0, 205.0])}
    order = []

    def gflops(dtype, **kwargs):
        name = precision.precision_name(dtype)
        order.append(name)
        return next(rates[name])

    monkeypatch.setattr(precision, "matmul_gflops", gflops)
    measured = precision.measure_cpu_matmul(rounds=3)
    assert measured == {"fp32": 100.0, "bf16": 210.0}
    assert order == ["fp32", "bf16"] * 3                  # turns taken in turn, not one dtype's all at once
    assert measured["bf16"] > precision.BF16_MARGIN * measured["fp32"]


def test_bf16_just_a_little_faster_is_not_enough(fresh_cache, monkeypatch):
    monkeypatch.setattr(precision, "measure_cpu_matmul", _measured(fp32=100.0, bf16=105.0)[0])
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX512")
    assert resolve_precision("auto", "cpu") == torch.float32


def test_an_unwritable_cache_only_costs_a_measurement(fresh_cache, monkeypatch):
    fresh_cache.parent.parent.mkdir(parents=True, exist_ok=True)
    fresh_cache.parent.write_text("a file where the cache folder should be")
    monkeypatch.setattr(precision, "measure_cpu_matmul", _measured(fp32=100.0, bf16=400.0)[0])
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX512")
    assert resolve_precision("auto", "cpu") == torch.bfloat16


def test_relighter_computes_in_the_resolved_precision(fresh_cache, monkeypatch):
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX2")
    relighter = Relighter.load("tiny", device="cpu")
    assert relighter.precision == "fp32" and relighter.precision_choice == "auto"
    assert {p.dtype for p in relighter.dit.parameters()} == {torch.float32}
    assert not torch.is_autocast_cpu_enabled()
    with relighter._autocast():
        assert not torch.is_autocast_cpu_enabled()
    frames = np.random.default_rng(0).random((1, 48, 48, 3), dtype=np.float32)
    result = relighter.relight(RelightRequest(frames, mode="albedo", steps=2))
    assert result.info["precision"] == "fp32" and np.isfinite(result.albedo).all()

    forced = Relighter.load("tiny", device="cpu", precision="bf16")
    assert forced.precision == "bf16"
    assert {p.dtype for p in forced.dit.parameters()} == {torch.bfloat16}
    assert {p.dtype for p in forced.tokenizer.parameters()} == {torch.float32}  # autocast lowers it
    with forced._autocast():
        assert torch.is_autocast_cpu_enabled() and torch.get_autocast_dtype("cpu") == torch.bfloat16


def test_bf16_stored_weights_load_as_fp32_when_fp32_computes(tmp_path):
    spec, dit, tokenizer = load_model("tiny")
    save_model(tmp_path, spec, dit.to(torch.bfloat16), tokenizer)   # as training exports: bf16 on disk
    assert {v.dtype for v in load_file(str(tmp_path / DIT_FILE)).values()} == {torch.bfloat16}
    _, loaded, _ = load_model(tmp_path)
    assert {p.dtype for p in loaded.parameters()} == {torch.float32}
    _, loaded16, _ = load_model(tmp_path, dtype=torch.bfloat16)
    assert {p.dtype for p in loaded16.parameters()} == {torch.bfloat16}
    relighter = Relighter.load(str(tmp_path), device="cpu", precision="fp32")
    assert {p.dtype for p in relighter.dit.parameters()} == {torch.float32}


def test_fp32_tokenizer_weights_stay_fp32_when_stored_in_bf16(tmp_path):
    spec, dit, tokenizer = load_model("tiny")
    save_model(tmp_path, spec, dit, tokenizer)
    state = {k: v.to(torch.bfloat16) for k, v in load_file(str(tmp_path / "tokenizer.safetensors")).items()}
    save_file(state, str(tmp_path / "tokenizer.safetensors"))
    _, _, loaded = load_model(tmp_path)
    assert {p.dtype for p in loaded.parameters()} == {torch.float32}


@pytest.mark.parametrize(("stored", "expected"), [(True, "auto"), (False, "fp32")])
def test_old_configs_with_autocast_bf16_still_load(tmp_path, stored, expected):
    spec, dit, tokenizer = load_model("tiny")
    save_model(tmp_path, spec, dit, tokenizer)
    config = json.loads((tmp_path / CONFIG_FILE).read_text())
    del config["precision"]
    config["autocast_bf16"] = stored
    (tmp_path / CONFIG_FILE).write_text(json.dumps(config))
    assert load_model(tmp_path)[0].precision == expected


def test_a_config_with_an_unknown_precision_is_one_sentence(tmp_path):
    spec, dit, tokenizer = load_model("tiny")
    save_model(tmp_path, spec, dit, tokenizer)
    config = json.loads((tmp_path / CONFIG_FILE).read_text())
    config["precision"] = "int4"
    (tmp_path / CONFIG_FILE).write_text(json.dumps(config))
    with pytest.raises(InputError, match="not a valid model config"):
        load_model(tmp_path)


def test_presets_default_to_auto():
    assert all(spec.precision == "auto" for spec in MODEL_PRESETS.values())
    assert ModelSpec.from_json(MODEL_PRESETS["tiny"].to_json()).precision == "auto"


def test_cli_precision_flag(tmp_path, capsys):
    png = make_png(tmp_path / "photo.png")
    fast = ["--model", "tiny", "--steps", "1", "--size", "32"]
    assert main(["albedo", str(png), "--precision", "fp32", "--out", str(tmp_path / "ok"), *fast]) == 0
    assert (tmp_path / "ok" / "albedo.png").is_file()
    capsys.readouterr()
    assert main(["albedo", str(png), "--precision", "fp16", "--device", "cpu", "--out", str(tmp_path / "bad"),
                 *fast]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert [line for line in err if line.startswith("error: ")] == [
        "error: fp16 runs only on a CUDA GPU, not on cpu; use --precision auto, fp32 or bf16 here."]
    assert not (tmp_path / "bad").exists()
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "--precision", "fp8"])
    assert exit_info.value.code == 2
    assert "not a precision; choose one of auto, fp32, bf16, fp16" in capsys.readouterr().err


def test_training_computes_in_the_resolved_precision(fresh_cache, monkeypatch):
    from relight_core.training.joint import DiTTrainConfig, train_step
    from relight_core.training.recipe import Recipe

    assert DiTTrainConfig(data=".", run=".", tokenizer=".").precision == "auto"
    _, dit, _ = load_model("tiny")
    seen = []
    original = dit.forward

    def spy(x, c_noise, context=None):
        seen.append(torch.get_autocast_dtype("cpu") if torch.is_autocast_cpu_enabled() else torch.float32)
        return original(x, c_noise, context)

    dit.forward = spy
    latent = torch.randn(2, 16, 1, 4, 4)
    batch = {"input": latent, "relit": latent, "albedo": latent, "lighting": torch.randn(2, 51, 1, 4, 4),
             "has_input": torch.ones(2, dtype=bool), "has_lighting": torch.ones(2, dtype=bool)}
    monkeypatch.setattr(precision, "cpu_capability", lambda: "AVX2")
    for dtype in (torch.bfloat16, torch.float32, None):
        loss, _ = train_step(dit, batch, Recipe(), torch.Generator().manual_seed(0), dtype)
        assert torch.isfinite(loss)
    assert seen == [torch.bfloat16, torch.float32, torch.float32]   # None: auto, fp32 on an AVX2 CPU
