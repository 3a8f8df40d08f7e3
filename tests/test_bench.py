"""The benchmark's bookkeeping: evaluation counts, FLOP accounting, the 7B parameter count."""

import json

import pytest
import torch

from relight_core import bench
from relight_core.bench import attention_flops, count_evaluations, peak_size, run_bench
from relight_core.errors import InputError
from relight_core.precision import precision_name, resolve_precision


def test_our_sampler_evaluates_the_network_once_per_step_plus_one():
    assert count_evaluations(35, guidance=0.0) == 36
    assert count_evaluations(35, guidance=1.0) == 72


def test_attention_flops_formula():
    # One block, 10 tokens, width 8: Q·Kᵀ and P·V are 2·L²·D each.
    assert attention_flops(1, 8, 10) == 2 * 2 * 10 * 10 * 8


def test_quick_bench_reports_the_numbers(tmp_path, capsys):
    numbers = run_bench(quick=True, out=tmp_path / "bench.json")
    assert json.loads((tmp_path / "bench.json").read_text()) == json.loads(json.dumps(numbers))
    assert abs(numbers["unirelight_7b_params"] - 7e9) / 7e9 < 0.05
    assert numbers["evaluations"] == {"ours": 36, "released": 71}
    waits = numbers["latency"]
    assert waits["model"] == "tiny" and 0 < waits["first_preview_s"] <= waits["relight_s"]
    assert all(waits[k] > 0 for k in ("load_s", "warm_up_s", "estimate_s", "relight_256_s"))
    # Both peaks are measured; the DiT runs in the precision the Relighter would pick here ...
    assert set(numbers["matmul_peak_gflops"]) == {"fp32", "bf16"}
    assert all(value > 0 for value in numbers["matmul_peak_gflops"].values())
    assert numbers["matmul_size"]["fp32"] == 1024 and 256 <= numbers["matmul_size"]["bf16"] <= 1024
    used = precision_name(resolve_precision("auto", "cpu"))
    assert numbers["precision"] == used
    assert [(row["preset"], row["frames"]) for row in numbers["dit"]] == [("tiny", 1), ("tiny", 17)]
    for row in numbers["dit"]:
        assert row["precision"] == used and row["gflops_per_s"] > 0 and row["seconds"] > 0
        # ... and is compared with that precision's peak
        assert row["vs_peak"] == pytest.approx(row["gflops_per_s"] / numbers["matmul_peak_gflops"][used], abs=2e-3)
    out = capsys.readouterr().out
    assert "unirelight-7b preset" in out and f"of {used} peak" in out


def test_bf16_peak_is_sized_down_where_bf16_is_slow(monkeypatch):
    monkeypatch.setattr(bench, "matmul_gflops", lambda *a, **k: 0.9)       # an AVX2 CPU: emulated bf16
    assert peak_size(torch.bfloat16, 2048) == 512                          # 0.3 s a call, not 19 s at 2048²
    monkeypatch.setattr(bench, "matmul_gflops", lambda *a, **k: 0.01)
    assert peak_size(torch.bfloat16, 2048) == 256                          # never below the floor
    monkeypatch.setattr(bench, "matmul_gflops", lambda *a, **k: 600.0)     # AMX
    assert peak_size(torch.bfloat16, 2048) == 2048


def test_bench_refuses_fp16_on_the_cpu():
    with pytest.raises(InputError, match="fp16 runs only on a CUDA GPU"):
        run_bench(quick=True, precision="fp16")
