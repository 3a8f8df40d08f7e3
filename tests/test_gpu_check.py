"""scripts/gpu_check.sh: the memory estimate and its refusal, the table, the no-GPU sentence, and
(on a machine with a CUDA GPU) the real check with the tiny preset and a miniature released folder."""

import dataclasses
import json
import subprocess

import numpy as np
import pytest
import torch

from relight_core import gpu_check, media
from relight_core.checkpoint import MODEL_PRESETS, REPO_ROOT
from relight_core.dit import param_count
from relight_core.gpu_check import (NO_GPU, PAPER_SECONDS, Estimate, Measurement, bundled_workloads, format_table,
                                    measure, memory_estimate, refusal)
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter
from relight_core.released import import_released
from tests.factory import MINI, FakeCosmosDecoder, FakeCosmosEncoder

SCRIPT = REPO_ROOT / "scripts" / "gpu_check.sh"
GIB = 2 ** 30
needs_gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def run_script(*args):
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=540)


def table_rows(report: str) -> list[list[str]]:
    """The body rows of the report's Markdown table, as stripped cells."""
    lines = [line for line in report.splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines[2:]]


@pytest.fixture()
def folder_7b(tmp_path):
    """A model folder of the 7B architecture whose DiT weights are absent: the estimate never loads them."""
    torch.jit.script(FakeCosmosEncoder()).save(str(tmp_path / "encoder.jit"))
    torch.jit.script(FakeCosmosDecoder()).save(str(tmp_path / "decoder.jit"))
    spec = dataclasses.replace(MODEL_PRESETS["unirelight-7b"], trained=True)
    (tmp_path / "config.json").write_text(json.dumps(spec.to_json()))
    return tmp_path


def test_estimate_is_the_weights_plus_the_relighters_own_activation_rule():
    for dtype in (torch.bfloat16, torch.float32):
        estimate = memory_estimate("tiny", dtype)
        assert estimate.weights == param_count(MODEL_PRESETS["tiny"].dit) * dtype.itemsize
    relighter = Relighter.load("tiny", device="cpu", precision="fp32")
    assert estimate.network == relighter.memory_estimate(57, 480, 848)[1]
    assert memory_estimate("tiny", torch.float32, frames=1).network < estimate.network
    assert estimate.total == estimate.weights + estimate.network


def test_a_7b_folder_is_refused_on_a_24_gib_gpu_with_its_estimate_and_fits_an_80_gb_a100(folder_7b):
    estimate = memory_estimate(str(folder_7b), torch.bfloat16)
    assert estimate.weights == pytest.approx(7.236e9 * 2, rel=1e-3)        # 7.236 B parameters in bf16
    sentence = refusal(estimate, 24 * GIB, "GPU NVIDIA GeForce RTX 4090")
    assert sentence.startswith("The GPU NVIDIA GeForce RTX 4090 has 24.0 GiB free but this check needs about ")
    assert gpu_check.gib(estimate.total) in sentence and "13.5 GiB of weights" in sentence
    assert sentence.endswith(".") and sentence.count(". ") == 0 and "\n" not in sentence   # one sentence
    assert refusal(estimate, 79 * GIB, "GPU NVIDIA A100-SXM4-80GB") is None  # the paper's GPU class


def test_without_a_gpu_the_script_says_so_in_one_sentence():
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    done = run_script("tiny")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"error: {NO_GPU}\n"
    assert run_script().returncode == 2                                       # no model: usage


def test_table_has_a_row_per_workload_beside_the_papers_number():
    rows = [Measurement("image objects.png", 1, 480, 848, 35, 36, 7.2, 9.87, 15 * GIB, None),
            Measurement("video orbit.mp4, 57 frames", 57, 480, 848, 35, 36, 180.0, 201.25, 60 * GIB + GIB // 2,
                        PAPER_SECONDS)]
    report = format_table("GPU check: test", rows, Estimate(14 * GIB, 58 * GIB))
    assert report.splitlines()[0] == "GPU check: test"
    header = [line for line in report.splitlines() if line.startswith("|")][0]
    assert [c.strip() for c in header.strip("|").split("|")] == [
        "workload", "frames", "size", "steps", "network calls", "s / call", "total s", "peak GPU memory",
        "paper (A100)"]
    assert table_rows(report) == [
        ["image objects.png", "1", "848×480", "35", "36", "0.200", "9.9", "15.0 GiB", "—"],
        ["video orbit.mp4, 57 frames", "57", "848×480", "35", "36", "5.000", "201.2", "60.5 GiB", "445.5 s"]]
    assert len({len(line) for line in report.splitlines() if line.startswith("|")}) == 1   # aligned columns
    assert "72.0 GiB (14.0 GiB weights + 58.0 GiB activations)" in report


def test_bundled_workloads_are_the_papers_clip_shape():
    image, video = bundled_workloads()
    assert image.frames.shape == (1, 480, 848, 3) and video.frames.shape == (57, 480, 848, 3)
    assert image.paper_seconds is None and video.paper_seconds == PAPER_SECONDS and video.steps == 35
    source = media.load_video(gpu_check.VIDEO).frames                            # 17 frames, played back and forth
    fitted = gpu_check.fit(source, 480, 848)
    np.testing.assert_array_equal(video.frames[16], fitted[16])
    np.testing.assert_array_equal(video.frames[17], fitted[15])
    np.testing.assert_array_equal(video.frames[32], fitted[0])
    np.testing.assert_array_equal(video.frames[33], fitted[1])
    assert float(video.frames.min()) >= 0 and float(video.frames.max()) <= 1


def test_measure_counts_every_network_call_on_the_cpu():
    relighter = Relighter.load("tiny", device="cpu", precision="fp32")
    probe = load_probe(gpu_check.PROBE)
    image, video = bundled_workloads(frames=25, height=32, width=48, steps=2)
    rows = [measure(relighter, workload, probe) for workload in (image, video)]
    chunks = 2                                            # 25 frames in tiny's 17-frame chunks, 9 shared
    assert [r.calls for r in rows] == [3, chunks * 3]     # steps + 1 per chunk
    for row in rows:
        assert 0 < row.network_seconds < row.seconds and row.peak_bytes is None
    assert len(table_rows(format_table("t", rows))) == 2


@needs_gpu
def test_the_check_runs_on_this_gpu_with_the_tiny_preset():
    done = run_script("tiny")
    assert done.returncode == 0, done.stderr
    rows = table_rows(done.stdout)
    assert [r[0] for r in rows] == ["image objects.png", "video orbit.mp4, 57 frames"]
    for row in rows:
        assert row[2] == "848×480" and row[3] == "35" and int(row[4]) >= 36
        assert float(row[5]) > 0 and float(row[6]) > 0 and row[7].endswith("iB")
    assert rows[1][8] == "445.5 s"


@needs_gpu
def test_the_check_runs_a_released_folder_on_this_gpu(released_files, tmp_path):
    """The released path (Cosmos JIT tokenizer on the GPU, 57-frame single chunk) in miniature."""
    checkpoint, tokenizer, _ = released_files
    folder = import_released(checkpoint, tokenizer, tmp_path / "mini", dit_config=MINI)
    done = run_script(folder)
    assert done.returncode == 0, done.stderr
    rows = table_rows(done.stdout)
    assert [int(r[4]) for r in rows] == [36, 36]          # one chunk each: 35 steps + the final x0
