"""The benchmark's bookkeeping: evaluation counts, FLOP accounting, the 7B parameter count."""

import json

from relight_core.bench import attention_flops, count_evaluations, run_bench


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
    assert all(row["gflops_per_s"] > 0 and row["seconds"] > 0 for row in numbers["dit"])
    assert "unirelight-7b preset" in capsys.readouterr().out
