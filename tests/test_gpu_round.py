"""scripts/gpu_round.sh end to end, on the CPU with tiny settings: pieces of a pack → one run per
learning rate from the shipped weights, each keeping its best EMA on the validation pack → the pick,
as shards + config.json + pick.json and the runs' logs in $OUT (what a GPU machine hands back)."""

import json
import os
import subprocess
import sys

from relight_core.checkpoint import REPO_ROOT, load_model
from relight_core.training.fast import merge_shards
from relight_core.training.pack import write_pack
from relight_core.training.pieces import cut_pack
from tests.factory import write_pack_dataset


def test_a_gpu_round_runs_its_learning_rates_and_hands_back_the_pick(tmp_path):
    root = write_pack_dataset(tmp_path / "data", scenes=5)
    write_pack(root, "train", tmp_path / "all.npz", lighting_size=8)
    counts = cut_pack(tmp_path / "all.npz", tmp_path / "pieces", [1.0, 1.0], val=2)
    assert counts["val"] == 2 and counts["p1"] == 3
    out = tmp_path / "out"
    env = dict(os.environ, PACKS=str(tmp_path / "pieces" / "p*.npz"), VAL=str(tmp_path / "pieces" / "val.npz"),
               TEST=str(tmp_path / "pieces" / "val.npz"), INIT=str(REPO_ROOT / "models" / "default"),
               OUT=str(out), RUNS_DIR=str(tmp_path / "runs"), DEVICE="cpu", BATCH="2", LRS="1e-4 0",
               PYTHON=sys.executable, OMP_NUM_THREADS="1")
    done = subprocess.run(["bash", str(REPO_ROOT / "scripts" / "gpu_round.sh"), "0.02"], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert {p.name for p in out.iterdir()} >= {"config.json", "pick.json", "dit-shard-0.safetensors",
                                               "log-lr-1e-4.txt", "log-lr-0.txt"}
    assert len(list(out.iterdir())) <= 8                                      # a device hands back ≤ 8 files
    for lr in ("1e-4", "0"):
        records = [json.loads(line) for line in (out / f"log-lr-{lr}.txt").read_text().splitlines()
                   if line.startswith('{"event": "val"')]
        assert records[0]["step"] == 0 and len(records) >= 2                  # scored at step 0 and the end
    picked = json.loads((out / "pick.json").read_text())
    runs = [str(tmp_path / "runs" / f"lr-{lr}" / "model") for lr in ("1e-4", "0")]
    assert set(picked["scores"]) == {*runs, "mean", "mean with init", "init"} and picked["best"] in picked["scores"]
    spec, dit, _ = load_model(merge_shards(out, out / "config.json", tmp_path / "picked"))
    assert spec.residual and spec.notes["picked"]["from"] == picked["best"]
