"""autolabel: real videos → (video, albedo) samples that RelightDataset serves as single-illumination data;
on Ray (actors holding the model) a corrupt file fails alone with its sentence and a re-run skips
finished videos."""

import csv
import json

import numpy as np
import torch

from relight_core import media
from relight_core.data.dataset import RelightDataset
from tests.factory import main_capturing, make_mp4

FAST = ["--model", "tiny", "--size", "32", "--steps", "1"]
NOT_MEDIA = "{} is not a supported image or video; use PNG, JPEG, WebP, GIF, EXR, HDR, MP4, MOV or WebM."


def test_autolabel_writes_video_albedo_pairs_in_the_dataset_format(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    rng = np.random.default_rng(0)
    media.save_video(videos / "clip one.mp4", rng.random((9, 32, 48, 3)).astype(np.float32), fps=8.0)
    media.save_image(videos / "still.png", rng.random((32, 32, 3)).astype(np.float32))
    (videos / "notes.txt").write_text("not a video")
    # One worker and no --ray-address: in this process, without starting Ray.
    code, stdout, stderr = main_capturing(["autolabel", str(videos), "--out", str(tmp_path / "out"), *FAST,
                                            "--workers", "1"])
    assert code == 1, stderr  # notes.txt failed
    assert stdout.strip() == str(tmp_path / "out" / "real" / "manifest.json")
    assert f"notes.txt failed: {NOT_MEDIA.format('notes.txt')}" in stderr and "Traceback" not in stderr

    dataset = RelightDataset(tmp_path / "out", "real")
    assert len(dataset) == 2
    by_name = {item["path"].rsplit("/", 1)[-1]: item for item in (dataset[0], dataset[1])}
    assert set(by_name) == {"real_clip_one", "real_still"}
    clip = by_name["real_clip_one"]
    assert clip["relit"].shape == clip["albedo"].shape and clip["relit"].shape[:2] == (3, 9)
    assert by_name["real_still"]["relit"].shape[:2] == (3, 1)
    assert not bool(clip["has_input"]) and not bool(clip["has_lighting"]) and bool(clip["has_albedo"])
    assert torch.count_nonzero(clip["input"]) == 0 and torch.count_nonzero(clip["env_ldr"]) == 0
    assert clip["albedo"].std() > 0  # the model's output, not a placeholder


def test_autolabel_on_ray_labels_good_videos_reports_a_corrupt_one_and_skips_finished_ones(ray_address, tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    make_mp4(videos / "drive.mp4", frames=9)
    make_mp4(videos / "walk.mp4", frames=5)
    (videos / "broken.mp4").write_bytes((videos / "drive.mp4").read_bytes()[:300])  # a cut-off download
    out = tmp_path / "out"
    argv = ["autolabel", str(videos), "--out", str(out), *FAST, "--ray-address", ray_address, "--workers", "2"]

    code, _, stderr = main_capturing(argv)
    assert code == 1, stderr
    sentence = NOT_MEDIA.format("broken.mp4")
    assert f"broken.mp4 failed: {sentence}" in stderr and "Traceback" not in stderr
    assert "2 of 3 videos done, 1 failed." in stderr
    with open(out / "real" / "failed.csv", newline="") as f:
        assert list(csv.reader(f)) == [["item", "error"], ["broken.mp4", sentence]]
    manifest = json.loads((out / "real" / "manifest.json").read_text())
    assert [(s["path"], s["frames"]) for s in manifest["samples"]] == [("real_drive", 9), ("real_walk", 5)]
    assert not (out / "real" / "real_broken").exists()
    assert len(RelightDataset(out, "real")) == 2

    stamps = {p: p.stat().st_mtime_ns for p in (out / "real").glob("real_*/**/*")}
    code, _, stderr = main_capturing(argv)
    assert code == 1 and "3 videos: 2 done, 1 to run." in stderr
    assert f"broken.mp4 failed: {sentence}" in stderr
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # the labelled videos were not redone
