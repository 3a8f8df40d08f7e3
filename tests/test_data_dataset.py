"""render-data output: determinism, resume, the manifest, the torch Dataset, bad samples, the CLI."""

import argparse
import json
import os

import pytest
import torch

pytest.importorskip("mitsuba")

from relight_core.data.cli import add_data_commands  # noqa: E402
from relight_core.data.dataset import RelightDataset  # noqa: E402
from relight_core.data.generate import RenderConfig, render_dataset  # noqa: E402
from relight_core.errors import InputError  # noqa: E402

TINY = dict(scenes=2, frames=2, size=32, spp=4, seed=11, workers=1)


def _files(root):
    out = {}
    for dirpath, _, names in os.walk(root):
        for name in names:
            path = os.path.join(dirpath, name)
            out[os.path.relpath(path, root)] = open(path, "rb").read()
    return out


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    render_dataset(RenderConfig(out=root, **TINY), progress=False)
    return root


def test_same_seed_gives_identical_files(rendered, tmp_path):
    # Scene 1 alone, in a fresh folder: byte-identical to the same scene of the first run.
    render_dataset(RenderConfig(out=tmp_path, **{**TINY, "scenes": 1}), progress=False)
    first = {k: v for k, v in _files(rendered).items() if k.startswith("train/scene_000000")}
    again = {k: v for k, v in _files(tmp_path).items() if k.startswith("train/scene_000000")}
    assert first.keys() == again.keys() and len(first) == 1 + 6 * TINY["frames"]
    assert first == again


def test_resume_skips_finished_scenes(rendered):
    meta = rendered / "train" / "scene_000000" / "meta.json"
    before = meta.stat().st_mtime_ns
    render_dataset(RenderConfig(out=rendered, **TINY), progress=False)
    assert meta.stat().st_mtime_ns == before
    manifest = json.loads((rendered / "train" / "manifest.json").read_text())
    assert [s["path"] for s in manifest["samples"]] == ["scene_000000", "scene_000001"]
    assert all(s["lights"] == 2 and s["frames"] == 2 for s in manifest["samples"])


def test_dataset_yields_documented_shapes(rendered):
    dataset = RelightDataset(rendered, "train")
    assert len(dataset) == 4  # two scenes × (0→1, 1→0)
    item = dataset[0]
    for key in ("input", "relit", "albedo", "env_ldr", "env_log", "env_dir"):
        assert item[key].shape == (3, 2, 32, 32), key
        assert item[key].dtype == torch.float32
        assert item[key].min() >= -1 and item[key].max() <= 1
    assert item["mask"].shape == (1, 2, 32, 32)
    assert set(item["mask"].unique().tolist()) <= {0.0, 1.0}
    assert bool(item["has_input"]) and bool(item["has_lighting"])
    assert not torch.equal(item["input"], item["relit"])
    # The two directions of one scene swap input and target and share albedo.
    other = dataset[1]
    assert torch.equal(item["input"], other["relit"]) and torch.equal(item["albedo"], other["albedo"])
    image = RelightDataset(rendered, "train", clip_frames=1)[0]
    assert image["relit"].shape == (3, 1, 32, 32)


def test_corrupt_and_missing_samples_are_reported_and_skipped(rendered, tmp_path):
    import shutil

    corrupt = tmp_path / "corrupt"
    shutil.copytree(rendered, corrupt)
    (corrupt / "train" / "scene_000000" / "rgb1" / "0001.png").write_bytes(b"not a png")
    dataset = RelightDataset(corrupt, "train")
    with pytest.warns(RuntimeWarning, match=r"scene_000000.*0001\.png"):
        item = dataset[0]
    assert item["path"].endswith("scene_000001")  # the next good sample, never the corrupt one
    assert list(dataset.skipped) == [str(corrupt / "train" / "scene_000000")]

    missing = tmp_path / "missing"
    shutil.copytree(rendered, missing)
    (missing / "train" / "scene_000001" / "meta.json").unlink()
    with pytest.warns(RuntimeWarning, match="scene_000001"):
        dataset = RelightDataset(missing, "train")
    assert len(dataset) == 2 and all("scene_000000" in dataset[i]["path"] for i in range(2))


def test_missing_manifest_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="render-data"):
        RelightDataset(tmp_path, "train")


def test_cli_registers_render_data(tmp_path):
    parser = argparse.ArgumentParser()
    add_data_commands(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["render-data", "--out", str(tmp_path), "--scenes", "1", "--frames", "1",
                              "--size", "32", "--spp", "2", "--workers", "1", "--split", "test", "--quiet"])
    assert args.func(args) == 0
    meta = json.loads((tmp_path / "test" / "scene_000000" / "meta.json").read_text())
    assert meta["frames"] == 1 and meta["scene"]["split"] == "test"
    with pytest.raises(InputError, match="multiple of 16"):
        args.size = 40
        args.func(args)
    with pytest.raises(SystemExit):
        parser.parse_args(["render-data", "--out", str(tmp_path), "--scenes", "0"])


def test_extended_probes_render_and_a_folder_keeps_one_probe_library(tmp_path):
    from relight_core.data.generate import check_library

    config = RenderConfig(out=tmp_path, scenes=2, frames=1, size=16, spp=1, workers=1, probes="extended")
    assert not render_dataset(config, progress=False).failures
    meta = json.loads((tmp_path / "train" / "scene_000001" / "meta.json").read_text())
    assert meta["probe_library"] == "extended"
    assert meta["probes"] == ["file:extra/lobby", "file:extra/apartment"]  # seed 0's scene 1 in this library
    assert len(RelightDataset(tmp_path, "train", clip_frames=1)) == 4  # two scenes × two directions
    # A folder of one library is not resumed with the other (nor a classic one, whose meta names none, with it).
    with pytest.raises(InputError, match="holds scenes of the extended probe library"):
        render_dataset(RenderConfig(out=tmp_path, scenes=3, frames=1, size=16, spp=1, workers=1), progress=False)
    assert not (tmp_path / "train" / "scene_000002").exists()
    classic = tmp_path / "classic" / "train" / "scene_000000"
    classic.mkdir(parents=True)
    (classic / "meta.json").write_text('{"kind": "synthetic", "frames": 1}')
    check_library(RenderConfig(out=tmp_path / "classic"), classic.parent)
    with pytest.raises(InputError, match="holds scenes of the classic probe library"):
        check_library(config, classic.parent)
