"""`python -m relight_core batch` on a real local Ray instance (2 CPUs, the tiny preset): good rows
done, bad rows failed alone with their sentence, finished rows skipped, a killed run resumed.
The Ray instance (`ray_address`, conftest.py) is shared with the render-data and autolabel tests."""

import csv
import signal
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from relight_core.cli import main
from tests.factory import main_capturing, make_mp4, make_png, make_sun_probe, terminate_when

FAST = ["--model", "tiny", "--steps", "1", "--size", "32"]
TRUNCATED = "bad.png is damaged or truncated (image file is truncated); re-export or re-download it."
NOT_A_PROBE = "The light probe photo0.png is not an OpenEXR or Radiance HDR file; use .exr or .hdr."


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch-inputs")
    for i in range(3):
        make_png(d / f"photo{i}.png", seed=i)
    make_mp4(d / "clip.mp4", frames=9)
    make_sun_probe(d / "sun.exr")
    (d / "bad.png").write_bytes((d / "photo0.png").read_bytes()[:200])
    return d


def _manifest(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def _results(out: Path) -> dict[int, dict]:
    with open(out / "results.csv", newline="") as f:
        lines = list(csv.DictReader(f))
    assert list(lines[0]) == ["row", "status", "seconds", "outputs", "error"]
    return {int(line["row"]): line for line in lines}


@pytest.fixture(scope="module")
def first_run(inputs, ray_address, tmp_path_factory):
    """Seven rows on two workers: five good (PNG, MP4, albedo, two seeds), three bad (a truncated PNG,
    a probe that is a PNG, a rotation that is no number); returns (out, exit code, stdout, stderr)."""
    manifest = _manifest(inputs / "first.csv", [
        "input,mode,probe,rotation,seeds",
        "photo0.png,,sun.exr,45,",
        "clip.mp4,relight,sun.exr,,",
        "photo1.png,albedo,,,",
        "bad.png,relight,sun.exr,,",
        "photo2.png,random,,,0-1",
        "photo1.png,relight,photo0.png,,",
        "photo2.png,relight,sun.exr,east,",
    ])
    out = tmp_path_factory.mktemp("batch-out")
    code = main_capturing(["batch", str(manifest), "--out", str(out), "--workers", "2", *FAST])
    return out, *code


def test_good_rows_are_done_and_each_bad_row_fails_alone_with_its_sentence(first_run):
    out, code, stdout, stderr = first_run
    assert code == 1, stderr  # some rows failed
    assert stdout.strip() == str(out / "results.csv")
    results = _results(out)
    assert sorted(results) == [1, 2, 3, 4, 5, 6, 7]
    assert {row: r["status"] for row, r in results.items()} == {
        1: "done", 2: "done", 3: "done", 4: "failed", 5: "done", 6: "failed", 7: "failed"}
    assert results[4]["error"] == TRUNCATED
    assert results[6]["error"] == NOT_A_PROBE
    assert results[7]["error"] == "Its rotation cell is wrong: 'east' is not a number."
    assert results[1]["outputs"] == "1/relit.png;1/albedo.png"
    assert results[2]["outputs"] == "2/relit.mp4;2/albedo.mp4"
    assert results[3]["outputs"] == "3/albedo.png"
    assert results[5]["outputs"] == "5/seed0000_relit.png;5/seed0000_albedo.png;5/seed0001_relit.png;5/seed0001_albedo.png"
    for row, r in results.items():
        assert (r["outputs"] == "") == (r["status"] == "failed")
        assert float(r["seconds"]) >= 0
        for name in filter(None, r["outputs"].split(";")):
            if name.endswith(".png"):
                assert np.asarray(Image.open(out / name)).shape == (32, 48, 3)  # the input's resolution
            else:
                with av.open(str(out / name)) as container:
                    assert sum(1 for _ in container.decode(video=0)) == 9
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == \
        ["1", "2", "3", "5", "results.csv"]  # failed rows leave no folder, nothing is half-written
    assert f"row 4 failed: {TRUNCATED}" in stderr
    assert "error: 3 rows failed;" in stderr and "Traceback" not in stderr


def test_a_rerun_skips_finished_rows(first_run, inputs):
    out, *_ = first_run
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/*")}
    results = (out / "results.csv").read_text()
    code, _, stderr = main_capturing(["batch", str(inputs / "first.csv"), "--out", str(out), *FAST])
    assert code == 1
    assert "7 rows: 4 done, 3 failed before, 0 to run." in stderr
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/*")} == before
    assert (out / "results.csv").read_text() == results
    # A failed row is retried alone: it fails again with the same sentence, and nothing else runs.
    code, _, stderr = main_capturing(["batch", str(inputs / "first.csv"), "--out", str(out), "--rows", "7", *FAST])
    assert code == 1 and "1 to run" in stderr
    assert _results(out)[7]["error"] == "Its rotation cell is wrong: 'east' is not a number."
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/*")} == before


def test_manifest_mistakes_are_one_sentence_and_exit_2(inputs, tmp_path, capsys):
    cases = {
        "inputs,mode\nphoto0.png,relight\n": "has an unknown column 'inputs'",
        "mode\nrelight\n": "has no 'input' column",
        "input\n": "has no rows under its header",
    }
    for text, message in cases.items():
        manifest = tmp_path / "m.csv"
        manifest.write_text(text)
        assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), *FAST]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1 and "Traceback" not in err
    manifest = _manifest(tmp_path / "m.csv", ["input", str(inputs / "photo0.png")])
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--rows", "2", *FAST]) == 2
    assert "--rows names row 2, but the manifest has rows 1 to 1." in capsys.readouterr().err
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--model", "no-such-model"]) == 2
    assert "neither a model directory nor a preset" in capsys.readouterr().err
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--ray-address", "127.0.0.1:1", *FAST]) == 2
    assert "Nothing answers at 127.0.0.1:1" in capsys.readouterr().err


def test_gpu_workers_on_a_cluster_without_gpus_and_a_second_run_are_refused(inputs, ray_address, tmp_path, capsys):
    import fcntl

    manifest = _manifest(inputs / "gpu.csv", ["input,probe", "photo0.png,sun.exr"])
    argv = ["batch", str(manifest), "--out", str(tmp_path / "out"), *FAST]
    assert main([*argv, "--device", "cuda"]) == 2
    assert "the Ray cluster has no GPU; run with --device cpu" in capsys.readouterr().err
    with open(tmp_path / "out" / ".batch.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another run holds the output folder
        assert main(argv) == 2
    assert f"Another batch run is writing to {tmp_path / 'out'}" in capsys.readouterr().err


def test_a_line_torn_by_a_crash_loses_no_other_line(tmp_path):
    from relight_core.batch.manifest import RowResult, append_result, read_results

    append_result(tmp_path, RowResult(1, "done", 1.5, ("1/relit.png",)))
    with open(tmp_path / "results.csv", "a") as f:
        f.write("2,do")  # the process died mid-line
    append_result(tmp_path, RowResult(3, "failed", 0.25, (), "A sentence, with a comma."))
    assert read_results(tmp_path) == {1: RowResult(1, "done", 1.5, ("1/relit.png",)),
                                      3: RowResult(3, "failed", 0.25, (), "A sentence, with a comma.")}


def test_a_killed_run_resumes_where_it_stopped(inputs, ray_address, tmp_path):
    """A run killed (SIGKILL) after its first finished row loses nothing finished; the next run,
    with --retry-failed, does the rest and the row that had failed."""
    late = tmp_path / "late.png"  # missing at first: row 1 fails, then the file appears
    manifest = _manifest(tmp_path / "kill.csv", ["input,probe", f"{late},{inputs / 'sun.exr'}",
                                                 *[f"{inputs / f'photo{i % 3}.png'},{inputs / 'sun.exr'}"
                                                   for i in range(9)]])
    out = tmp_path / "out"
    terminate_when(["batch", manifest, "--out", out, "--ray-address", ray_address, "--workers", "1", *FAST],
                   lambda: bool(_done_rows(out)), "finished a row", sig=signal.SIGKILL, timeout_s=240)
    finished = _done_rows(out)
    assert 1 <= len(finished) < 9, "the run was not stopped halfway"
    stamps = {row: (out / str(row) / "relit.png").stat().st_mtime_ns for row in finished}

    late.write_bytes((inputs / "photo1.png").read_bytes())
    code, _, stderr = main_capturing(["batch", str(manifest), "--out", str(out), "--retry-failed", *FAST])
    assert code == 0, stderr
    results = _results(out)
    assert sorted(results) == list(range(1, 11)) and {r["status"] for r in results.values()} == {"done"}
    assert {row: (out / str(row) / "relit.png").stat().st_mtime_ns for row in finished} == stamps  # not redone
    assert not list(out.glob(".partial-*"))


def _done_rows(out: Path) -> list[int]:
    if not (out / "results.csv").exists():
        return []
    with open(out / "results.csv", newline="") as f:
        return [int(line["row"]) for line in csv.DictReader(f) if line.get("status") == "done"]
