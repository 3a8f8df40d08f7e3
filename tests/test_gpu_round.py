"""scripts/gpu_round.sh end to end, on the CPU with tiny settings: pieces of a pack → one run per
learning rate from the shipped weights, each keeping its best EMA on the validation pack → the pick,
as shards + config.json + pick.json and the runs' logs in $OUT (what a GPU machine hands back)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

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
               OUT=str(out), RUNS_DIR=str(tmp_path / "runs"), DEVICE="cpu", BATCH="2", LRS="1e-4 0:permute fast",
               PYTHON=sys.executable, OMP_NUM_THREADS="1")
    done = subprocess.run(["bash", str(REPO_ROOT / "scripts" / "gpu_round.sh"), "0.02"], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert {p.name for p in out.iterdir()} >= {"config.json", "pick.json", "dit-shard-0.safetensors",
                                               "log-lr-1e-4.txt", "log-lr-0-permute.txt", "failures.txt"}
    # a run that dies (here a learning rate that is not a number) is named as failed, and the others are picked from
    failed = (out / "failures.txt").read_text().splitlines()
    assert len(failed) == 1 and "lr-fast failed (exit status 2)" in failed[0] and "log-lr-fast.txt" in failed[0]
    assert len([p for p in out.iterdir() if "fast" not in p.name and p.name != "failures.txt"]) <= 8   # ≤ 8 files
    for lr in ("1e-4", "0-permute"):
        records = [json.loads(line) for line in (out / f"log-lr-{lr}.txt").read_text().splitlines()
                   if line.startswith('{"event": "val"')]
        assert records[0]["step"] == 0 and len(records) >= 2                  # scored at step 0 and the end
    notes = {lr: json.loads((tmp_path / "runs" / f"lr-{lr}" / "model" / "config.json").read_text())["notes"]
             for lr in ("1e-4", "0-permute")}
    assert notes["0-permute"]["permute_colours"] is True and "permute_colours" not in notes["1e-4"]
    picked = json.loads((out / "pick.json").read_text())
    runs = [str(tmp_path / "runs" / f"lr-{lr}" / "model") for lr in ("1e-4", "0-permute")]
    assert set(picked["scores"]) == {*runs, "mean", "mean with init", "init"} and picked["best"] in picked["scores"]
    spec, dit, _ = load_model(merge_shards(out, out / "config.json", tmp_path / "picked"))
    assert spec.residual and spec.notes["picked"]["from"] == picked["best"]


def test_a_whole_round_is_planned_into_calls_carried_and_hands_back_a_model_with_its_refiners_fitted_again(tmp_path,
                                                                                                         capsys):
    """training.calls cuts the files into calls within a size; copied in turn into the machine's folder, the last
    runs scripts/gpu_whole_round.sh: the DiT's round, then both refiners fitted again to the picked DiT (here at
    lr 0, so the start is kept), all in ≤ 8 files; here the parts make a model folder that runs."""
    from relight_core.pipeline import Relighter, RelightRequest
    from relight_core.training import calls
    from relight_core.training.assemble import assemble

    root = write_pack_dataset(tmp_path / "data", scenes=9)
    write_pack(root, "train", tmp_path / "all.npz", lighting_size=8)
    counts = cut_pack(tmp_path / "all.npz", tmp_path / "pieces", [0.02, 0.02, 1.0], val=2)
    assert counts["p3"] >= 1
    refit = tmp_path / "refit"
    refit.mkdir()
    (tmp_path / "pieces" / "p3.npz").rename(refit / "refit.npz")     # scenes the DiT's round does not train on
    model = REPO_ROOT / "models" / "default"
    files = [f"packs/{p}.npz={tmp_path / 'pieces' / f'{p}.npz'}" for p in ("p1", "p2")]
    files += [f"aux/val.npz={tmp_path / 'pieces' / 'val.npz'}", f"aux/test.npz={tmp_path / 'pieces' / 'val.npz'}",
              f"aux/model={model}", f"refit/refit.npz={refit / 'refit.npz'}",
              f"aux/refit-val.npz={tmp_path / 'pieces' / 'val.npz'}"]
    planned = calls.plan_calls(files, tmp_path / "calls", 34.0, run="bash scripts/gpu_whole_round.sh 0.02 0.02")
    sizes = [sum((tmp_path / "calls" / f"c{i}" / f).stat().st_size for f in c["files"]) / 1e6
             for i, c in enumerate(planned, 1)]
    assert len(planned) >= 2 and max(sizes) <= 34.0                             # the DiT's 33.5 MB alone in one
    assert sorted(f for c in planned for f in c["files"]) == sorted(
        [*(f"aux/model/{f.name}" for f in model.iterdir() if f.is_file()), "packs/p1.npz", "packs/p2.npz",
         "aux/val.npz", "aux/test.npz", "refit/refit.npz", "aux/refit-val.npz"])   # every file, once
    plan = (tmp_path / "calls" / "calls.md").read_text()
    assert plan.count("carry") == len(planned) and plan.rstrip().endswith("0.02 0.02`")
    listed = (tmp_path / "calls" / f"c{len(planned)}" / calls.INVENTORY).read_text().split("\n")[:-1]
    assert sorted(line.split(" ", 1)[1] for line in listed) == sorted(f for c in planned for f in c["files"])
    with pytest.raises(ValueError, match="more than one call's"):
        calls.plan_calls(files, tmp_path / "calls2", 20.0)
    with pytest.raises(SystemExit):                                          # the CLI: one sentence, no traceback
        calls.main(["aux/val.npz", "--out", str(tmp_path / "calls3")])
    assert "is not DEST=SOURCE" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        calls.main([f"aux/x.npz={tmp_path / 'nowhere.npz'}", "--out", str(tmp_path / "calls3")])
    assert "nothing at" in capsys.readouterr().err
    with pytest.raises(ValueError, match="not an earlier plan"):             # never clears a folder of other files
        calls.plan_calls(files, tmp_path / "pieces", 34.0)
    assert (tmp_path / "pieces" / "val.npz").is_file()
    machine = tmp_path / "machine"
    machine.mkdir()
    for number in range(1, len(planned) + 1):                                    # each call copies its folder in
        subprocess.run(["cp", "-r", f"{tmp_path / 'calls' / f'c{number}'}/.", f"{machine}/"], check=True)
    out = tmp_path / "out"
    env = dict(os.environ, GPU_DIR=str(machine), OUT=str(out), DEVICE="cpu", BATCH="2", LRS="1e-4",
               REFINE_LR="0", REFINE_BATCH="2", SAME="1", THREADS="1", VAL_EVERY="0.01", PYTHON=sys.executable,
               OMP_NUM_THREADS="1")
    whole_round = ["bash", str(REPO_ROOT / "scripts" / "gpu_whole_round.sh"), "0.02", "0.02"]
    # a machine that lost a file of an earlier call (given back between calls): the round stops before running
    (machine / "packs" / "p2.npz").rename(tmp_path / "p2.npz")
    stopped = subprocess.run(whole_round, env=dict(env, OUT=str(tmp_path / "out-missing")), capture_output=True,
                             text=True, timeout=60)
    assert stopped.returncode == 3 and "lacks 1 of the round's files (packs/p2.npz" in stopped.stdout
    assert (tmp_path / "out-missing" / "missing.txt").read_text() == "packs/p2.npz\n"
    assert not (machine / "work").exists()                                      # nothing ran
    (tmp_path / "p2.npz").rename(machine / "packs" / "p2.npz")
    done = subprocess.run(whole_round, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert f"all {len(listed)} files of the round are here" in done.stdout
    names = {p.name for p in out.iterdir()}
    assert names >= {"config.json", "dit-shard-0.safetensors", "refiner.safetensors", "relit_refiner.safetensors",
                     "round.tar.gz"} and len(names) <= 8
    assert all(p.stat().st_size <= 16 * 2 ** 20 for p in out.iterdir())        # ≤ 16 MiB a file
    listed = subprocess.run(["tar", "tzf", str(out / "round.tar.gz")], capture_output=True, text=True).stdout.split()
    assert {"round/pick.json", "refit/best-refiner.json", "refit/best-relit_refiner.json"} <= set(listed)
    # a refit stopped by the time limit hands back what its runs kept (HAND_BACK=1: no training, the best EMAs so far)
    kept = tmp_path / "kept"
    salvage = subprocess.run(["bash", str(REPO_ROOT / "scripts" / "gpu_refine.sh"), "0"], capture_output=True,
                             text=True, timeout=300,
                             env=dict(env, HAND_BACK="1", OUT=str(kept), RUNS_DIR=str(machine / "work" / "refit-runs"),
                                      DIT=str(machine / "work" / "round"), LIKE=str(machine / "aux" / "model"),
                                      PACKS=str(machine / "refit" / "*.npz"), VAL=str(machine / "aux" / "refit-val.npz")))
    assert salvage.returncode == 0, salvage.stdout[-2000:] + salvage.stderr[-2000:]
    assert {p.name for p in kept.iterdir()} == {"refiner.safetensors", "relit_refiner.safetensors",
                                                "best-refiner.json", "best-relit_refiner.json"}
    assert not any(p.name.endswith(".partial") for p in (machine / "work" / "refit-runs").rglob("*"))
    folder = assemble(model, tmp_path / "new", dit=out, refiners={"refiner": out / "refiner.safetensors",
                                                                  "relit_refiner": out / "relit_refiner.safetensors"})
    relighter = Relighter.load(str(folder))
    assert relighter.refiner is not None and relighter.relit_refiner is not None
    frames = np.random.default_rng(0).random((1, 64, 64, 3)).astype(np.float32)
    result = relighter.relight(RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32)))
    assert result.relit.shape == frames.shape and np.isfinite(result.albedo).all()
