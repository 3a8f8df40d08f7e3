"""Data-parallel training: torchrun with two gloo processes trains exactly like one process."""

import json
import os
import subprocess
import sys
import time

import pytest
import torch
from safetensors.torch import save_file

from relight_core.checkpoint import MODEL_PRESETS
from relight_core.cli import main
from relight_core.data.dataset import write_manifest
from relight_core.dit import JointDiT, pack_lighting
from relight_core.errors import InputError
from relight_core.tokenizer import TOKENIZER_PRESETS, CausalVideoAutoencoder
from relight_core.training.distributed import check_split, rank_rows
from relight_core.training.joint import train_step, train_step_rows
from relight_core.training.latents import tokenizer_fingerprint
from relight_core.training.loop import load_checkpoint, step_generator
from relight_core.training.recipe import Recipe
from tests.factory import write_scene

STEPS = 3            # steps of the two-process run, then STEPS + 2 after resuming in one process
TOLERANCE = 2e-5     # parameters after a few steps at lr 1e-3: float noise of the gradient reduction


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Three rendered-format training scenes (rank 0 encodes two, rank 1 one), one test scene, and
    untrained tiny tokenizer weights: what `train` reads, made in well under a second."""
    root = tmp_path_factory.mktemp("data")
    for split, scenes in (("train", 3), ("test", 1)):
        for index in range(scenes):
            write_scene(root, split, index)
        write_manifest(root / split)
    torch.manual_seed(0)
    tokenizer = CausalVideoAutoencoder(TOKENIZER_PRESETS["tiny"])
    save_file(tokenizer.state_dict(), root / "tokenizer.safetensors")
    return root, tokenizer_fingerprint(tokenizer)


def train_args(root, run, steps, cache):
    # --run-dir, not --run: torchrun would read --run as its own --run-path
    return ["train", "--data", str(root), "--run-dir", str(run), "--steps", str(steps), "--cache", str(cache),
            "--tokenizer", str(root / "tokenizer.safetensors"), "--tokenizer-preset", "tiny", "--preset", "tiny",
            "--video-batch", "2", "--image-batch", "4", "--lr", "1e-3", "--warmup", "0", "--precision", "fp32",
            "--log-every", "1", "--val-every", "1000"]


def log_records(run):
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def assert_same_parameters(a, b, atol=TOLERANCE):
    for name in ("dit", "ema"):
        assert a["modules"][name].keys() == b["modules"][name].keys()
        for key, value in a["modules"][name].items():
            torch.testing.assert_close(value, b["modules"][name][key], atol=atol, rtol=0, msg=f"{name}.{key}")


def test_rank_rows_split_a_batch_into_contiguous_near_equal_shares():
    assert [rank_rows(4, r, 2) for r in range(2)] == [slice(0, 2), slice(2, 4)]
    assert [rank_rows(5, r, 3) for r in range(3)] == [slice(0, 2), slice(2, 4), slice(4, 5)]
    with pytest.raises(InputError, match="3 processes cannot split a video batch of 2"):
        check_split(3, video_batch=2, image_batch=8)


def test_rank_shares_sum_to_the_single_process_loss_and_gradient():
    """Every random draw is made for the whole batch, so rows computed apart add up to the whole."""
    from relight_core.checkpoint import load_model

    g = torch.Generator().manual_seed(0)
    z = lambda: torch.randn(4, 16, 2, 4, 4, generator=g)  # noqa: E731
    batch = {"input": z(), "relit": z(), "albedo": z(), "lighting": pack_lighting(z(), z(), z()),
             "has_input": torch.ones(4, dtype=bool), "has_lighting": torch.ones(4, dtype=bool)}
    recipe = Recipe(p_sigma_max=0.3)   # every draw of the recipe is taken
    _, dit, _ = load_model("tiny")
    dit.train().requires_grad_(True)

    whole, counts = train_step(dit, batch, recipe, step_generator(0, 7), torch.float32)
    whole.backward()
    grads = [p.grad.clone() for p in dit.parameters()]
    dit.zero_grad()
    every_row, same_counts = train_step_rows(dit, batch, recipe, step_generator(0, 7), slice(0, 4), torch.float32)
    assert torch.equal(every_row, whole) and same_counts == counts     # one rank: the single-process step
    shares = [train_step_rows(dit, batch, recipe, step_generator(0, 7), rows, torch.float32)[0]
              for rows in (slice(0, 1), slice(1, 4))]
    assert all(abs(float(s.detach()) - float(whole.detach())) > 0.01 for s in shares)  # parts, not the whole
    sum(shares).backward()
    torch.testing.assert_close(sum(shares), whole)
    for grad, p in zip(grads, dit.parameters()):
        torch.testing.assert_close(p.grad, grad, atol=1e-6, rtol=1e-5)


def test_two_gloo_processes_give_the_parameters_of_one_process_and_resume_in_one(dataset, tmp_path):
    root, fingerprint = dataset
    cache = tmp_path / "cache"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.getcwd()}
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           "-m", "relight_core", *train_args(root, tmp_path / "two", STEPS, cache)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    print(f"two-process run: {time.monotonic() - started:.1f} s")
    # Both ranks encoded their shard of the scenes: the cache holds all of them, and rank 0 alone
    # printed the summary.
    assert sorted(p.name for p in (cache / fingerprint / "train").iterdir()) == \
        [f"scene_{i:06d}.safetensors" for i in range(3)]
    assert done.stdout.count('"steps": 3') == 1

    assert main(train_args(root, tmp_path / "one", STEPS, cache)) == 0
    two, one = load_checkpoint(tmp_path / "two", ["dit", "ema"]), load_checkpoint(tmp_path / "one", ["dit", "ema"])
    assert two["step"] == one["step"] == STEPS
    assert_same_parameters(two, one)
    # ... and the steps moved the weights far more than the tolerance.
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)                                   # the initialisation `train` starts from
        init = JointDiT(MODEL_PRESETS["tiny"].dit).state_dict()
    moved = max(float((one["modules"]["dit"][k] - v).abs().max()) for k, v in init.items())
    assert moved > 100 * TOLERANCE

    # Rank 0's log is the single process's log: same kinds, modes and (global) losses.
    records_two, records_one = log_records(tmp_path / "two"), log_records(tmp_path / "one")
    assert records_two[0]["processes"] == 2 and "processes" not in records_one[0]
    steps_two = [r for r in records_two if "loss" in r]
    steps_one = [r for r in records_one if "loss" in r]
    assert [r["step"] for r in steps_two] == [r["step"] for r in steps_one] == [1, 2, 3]
    for a, b in zip(steps_two, steps_one):
        assert a["kind"] == b["kind"] and a["n_default"] == b["n_default"] and a["n_no_light"] == b["n_no_light"]
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-4)
        assert a["grad_norm"] == pytest.approx(b["grad_norm"], rel=1e-4)

    # A checkpoint written by two processes resumes in one, and goes on as the one-process run does.
    assert main(train_args(root, tmp_path / "two", STEPS + 2, cache)) == 0
    assert main(train_args(root, tmp_path / "one", STEPS + 2, cache)) == 0
    assert_same_parameters(load_checkpoint(tmp_path / "two", ["dit", "ema"]),
                           load_checkpoint(tmp_path / "one", ["dit", "ema"]))
    assert [r["step"] for r in log_records(tmp_path / "two") if "loss" in r] == [1, 2, 3, 4, 5]
