"""autolabel: real videos → (video, albedo) samples that RelightDataset serves as single-illumination data."""

import argparse

import numpy as np
import pytest
import torch

from relight_core import media
from relight_core.data.cli import add_data_commands
from relight_core.data.dataset import RelightDataset


def test_autolabel_writes_video_albedo_pairs_in_the_dataset_format(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    rng = np.random.default_rng(0)
    media.save_video(videos / "clip one.mp4", rng.random((9, 32, 48, 3)).astype(np.float32), fps=8.0)
    media.save_image(videos / "still.png", rng.random((32, 32, 3)).astype(np.float32))
    (videos / "notes.txt").write_text("not a video")
    parser = argparse.ArgumentParser()
    add_data_commands(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["autolabel", str(videos), "--out", str(tmp_path / "out"), "--model", "tiny",
                              "--size", "32", "--steps", "1"])
    with pytest.warns(RuntimeWarning, match="notes.txt"):
        assert args.func(args) == 0

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
