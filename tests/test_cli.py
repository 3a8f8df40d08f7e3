"""The command line end to end on real files, and its one-sentence errors (exit code 2)."""

import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from relight_core.cli import main
from tests.factory import make_mp4, make_png, make_sun_probe, write_exr

ROOT = Path(__file__).resolve().parent.parent
FAST = ["--model", "tiny", "--steps", "2", "--size", "48"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    return {
        "png": make_png(d / "photo.png"),
        "mp4": make_mp4(d / "clip.mp4", frames=12, audio=True),
        "probe": make_sun_probe(d / "sun.exr"),
    }


def test_relight_image_writes_relit_and_albedo_png(files, tmp_path):
    assert main(["relight", str(files["png"]), "--probe", str(files["probe"]), "--rotation", "45",
                 "--out", str(tmp_path), *FAST]) == 0
    for name in ("relit.png", "albedo.png"):
        img = np.asarray(Image.open(tmp_path / name))
        assert img.shape == (32, 48, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["albedo.png", "relit.png"]


def test_relight_video_keeps_frames_fps_and_audio(files, tmp_path):
    assert main(["relight", str(files["mp4"]), "--probe", str(files["probe"]), "--rotate-light",
                 "--out", str(tmp_path), *FAST]) == 0
    for name in ("relit.mp4", "albedo.mp4"):
        with av.open(str(tmp_path / name)) as container:
            video = container.streams.video[0]
            assert round(float(video.average_rate)) == 12
            assert sum(1 for _ in container.decode(video=0)) == 12
            assert len(container.streams.audio) == 1


def test_an_animated_gif_is_relit_as_a_video_without_sound(files, tmp_path):
    still = np.asarray(Image.open(files["png"]).convert("RGB"))
    frames = [Image.fromarray(np.roll(still, 5 * t, axis=1)) for t in range(6)]
    gif = tmp_path / "pan.gif"
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=50, loop=0)
    assert main(["relight", str(gif), "--probe", str(files["probe"]), "--out", str(tmp_path / "out"), *FAST]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["albedo.mp4", "relit.mp4"]
    with av.open(str(tmp_path / "out" / "relit.mp4")) as container:
        video = container.streams.video[0]
        assert round(float(video.average_rate)) == 20 and not container.streams.audio
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == 6 and decoded[0].shape == still.shape
    assert np.abs(decoded[0].astype(int) - decoded[-1].astype(int)).mean() > 1  # the frames move as the input's


def test_augment_writes_one_result_per_seed(files, tmp_path):
    assert main(["augment", str(files["png"]), "--seeds", "0-2", "--out", str(tmp_path), *FAST]) == 0
    outs = sorted(p.name for p in tmp_path.iterdir())
    assert outs == [f"seed000{seed}_{kind}.png" for seed in range(3) for kind in ("albedo", "relit")]
    a, b = (np.asarray(Image.open(tmp_path / f"seed000{seed}_relit.png")) for seed in (0, 1))
    assert not np.array_equal(a, b)


def test_albedo_command(files, tmp_path):
    assert main(["albedo", str(files["png"]), "--out", str(tmp_path), *FAST]) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["albedo.png"]


def test_render_command_writes_only_the_rendering(files, tmp_path):
    # The albedo is render's input: writing it back would only be the tokenizer's copy of it.
    assert main(["render", str(files["png"]), "--probe", str(files["probe"]), "--out", str(tmp_path), *FAST]) == 0
    assert [p.name for p in tmp_path.iterdir()] == ["relit.png"]


def _bad_inputs(d: Path) -> dict:
    truncated = d / "truncated.png"
    truncated.write_bytes(make_png(d / "whole.png").read_bytes()[:200])
    text_mp4 = d / "notes.mp4"
    text_mp4.write_text("these are not video frames\n" * 20)
    nan_probe = write_exr(d / "nan.exr", np.full((8, 16, 3), np.nan, np.float32))
    empty = d / "empty.mp4"
    with av.open(str(empty), "w") as container:  # a valid container whose video stream has no frames
        stream = container.add_stream("libx264", rate=12)
        stream.width, stream.height = 48, 32
    return {"truncated": truncated, "text_mp4": text_mp4, "nan_probe": nan_probe, "empty": empty}


@pytest.mark.parametrize("case", ["truncated", "text_mp4", "nan_probe", "empty", "missing"])
def test_bad_input_exits_2_with_one_sentence_and_writes_nothing(case, files, tmp_path, capsys):
    bad = _bad_inputs(tmp_path)
    out = tmp_path / "out"
    media, probe = files["png"], files["probe"]
    if case == "nan_probe":
        probe = bad["nan_probe"]
    elif case == "missing":
        media = tmp_path / "no_such_file.png"
    else:
        media = bad[case]
    code = main(["relight", str(media), "--probe", str(probe), "--out", str(out), *FAST])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    message = [line for line in err if line.startswith("error: ")]
    assert len(message) == 1 and "Traceback" not in "\n".join(err)
    assert not out.exists() or not any(out.iterdir()), "nothing may be written half-way"


def test_module_entry_point_runs_as_a_program(files, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "relight_core", "relight", str(files["png"]), "--probe",
                           str(tmp_path / "absent.exr"), "--out", str(tmp_path / "o"), *FAST],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: ") and "Traceback" not in proc.stderr


def test_frame_range_of_a_video(files, tmp_path):
    assert main(["albedo", str(files["mp4"]), "--frames", "4:10", "--out", str(tmp_path), *FAST]) == 0
    with av.open(str(tmp_path / "albedo.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 6
        assert len(container.streams.audio) == 1


def test_an_output_folder_that_cannot_be_made_is_one_sentence(files, tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("a file where the output folder should go")
    code = main(["albedo", str(files["png"]), "--out", str(blocker / "out"), *FAST])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("error: ")] == [err.splitlines()[-1]]


def test_intensity_is_applied_where_the_studio_applies_it(files, tmp_path, monkeypatch):
    """One place scales the probe: the pipeline's `adjust_light`, from the request (CLI, batch and studio)."""
    from relight_core import lighting

    used = []
    adjust = lighting.adjust_light
    monkeypatch.setattr(lighting, "adjust_light", lambda probe, intensity, kelvin, tint: used.append(
        (intensity, float(probe.max()))) or adjust(probe, intensity, kelvin, tint))
    args = ["relight", str(files["png"]), "--probe", str(files["probe"]), *FAST]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--out", str(tmp_path / "three"), "--intensity", "3"]) == 0
    assert [intensity for intensity, _ in used] == [1.0, 3.0]
    assert used[0][1] == used[1][1]  # the probe itself arrives unscaled both times


def test_light_colour_temperature(files, tmp_path, capsys, monkeypatch):
    from relight_core import lighting

    used = []  # the colour temperature each probe is adjusted with (the tiny model's output ignores light)
    adjust = lighting.adjust_light
    monkeypatch.setattr(lighting, "adjust_light", lambda probe, intensity, kelvin, tint: used.append((kelvin, tint))
                        or adjust(probe, intensity, kelvin, tint))
    args = ["relight", str(files["png"]), "--probe", str(files["probe"]), *FAST]
    assert main([*args, "--out", str(tmp_path / "neutral")]) == 0
    assert main([*args, "--out", str(tmp_path / "warm"), "--temperature", "3000", "--tint", "0.01"]) == 0
    assert used == [(lighting.NEUTRAL_KELVIN, 0.0), (3000.0, 0.01)]
    assert main([*args, "--out", str(tmp_path / "bad"), "--temperature", "100"]) == 2
    err = capsys.readouterr().err
    assert "colour temperature 100" in err and "Traceback" not in err
    assert main([*args, "--out", str(tmp_path / "bad"), "--tint", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "tint" in err and "Traceback" not in err


def test_ensemble_averages_mirrored_samples_of_images_and_chunked_videos(files, tmp_path, capsys):
    args = ["relight", "--probe", str(files["probe"]), *FAST]
    for media in ("png", "mp4"):   # the tiny model cuts the clip into overlapping chunks
        assert main([args[0], str(files[media]), *args[1:], "--out", str(tmp_path / media / "1")]) == 0
        assert main([args[0], str(files[media]), *args[1:], "--ensemble", "3",
                     "--out", str(tmp_path / media / "3")]) == 0
    one, three = (np.asarray(Image.open(tmp_path / "png" / n / "relit.png"), np.float32) for n in ("1", "3"))
    assert one.shape == three.shape and np.abs(one - three).mean() > 0.1
    with av.open(str(tmp_path / "mp4" / "3" / "relit.mp4")) as video:
        assert sum(1 for _ in video.decode(video=0)) == 12
    with pytest.raises(SystemExit) as refused:
        main([args[0], str(files["png"]), *args[1:], "--ensemble", "0", "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err
    assert refused.value.code == 2 and not (tmp_path / "bad").exists()
    assert "ensemble 0 is out of range" in err and "Traceback" not in err


def test_a_video_is_relit_at_the_working_size_and_written_at_its_own_a_block_at_a_time(tmp_path, monkeypatch):
    # The command line never holds a video at its own resolution: it decodes the frames at the working size for the
    # model, then again 16 at a time to bring each block's results to full size as it writes them. The blocks must
    # be exactly the frames of upsampling the whole clip at once; and with the decode budget cut to 10 of the 40
    # frames at full size (a long 720p video) the job still runs, its sound kept.
    from relight_core import media
    from relight_core.errors import InputError
    from relight_core.jobs import MediaJob, finished_result, load_inputs, plan_job
    from relight_core.media import iter_video, load_video, video
    from relight_core.outputs import FullVideo, full_resolution_blocks, result_clips
    from relight_core.pipeline import Relighter

    clip = make_mp4(tmp_path / "clip.mp4", frames=40, width=96, height=64, fps=12, audio=True)
    probe = make_sun_probe(tmp_path / "sun.exr")
    job = MediaJob(mode="relight", input=clip, probe=probe, size=32, steps=1, seeds=(1,))
    relighter = Relighter.load("tiny", device="cpu")
    inputs = load_inputs(job)
    assert inputs.source is None and inputs.video.num_frames == 40
    plan = plan_job(job, relighter, inputs)
    full = load_video(clip).frames
    assert np.array_equal(plan.frames, media.resize_frames(full, 32)) and plan.source.audio_path == str(clip)
    result = finished_result("clip", relighter.run(plan.requests[0][1]))
    whole = result_clips(result, "relight", plan.frames, full)
    for name in ("relit", "albedo"):
        blocks = list(full_resolution_blocks(FullVideo(str(clip)), plan.frames, getattr(result, name)))
        assert [len(b) for b in blocks] == [16, 16, 8]
        assert np.array_equal(np.concatenate(blocks), whole[name]), name
    with monkeypatch.context() as patch:
        patch.setattr(video, "MAX_DECODED_PIXELS", 10 * 96 * 64)
        with pytest.raises(InputError, match="more than this tool holds"):
            load_video(clip)
        assert main(["relight", str(clip), "--probe", str(probe), "--model", "tiny", "--size", "32", "--steps", "1",
                     "--seed", "1", "--out", str(tmp_path / "out")]) == 0
    for name in ("relit", "albedo"):
        written = np.concatenate(list(iter_video(tmp_path / "out" / f"{name}.mp4", block=7)))
        media.save_video(tmp_path / f"whole-{name}.mp4", whole[name], 12)
        encoded = np.concatenate(list(iter_video(tmp_path / f"whole-{name}.mp4")))
        assert written.shape == encoded.shape == (40, 64, 96, 3)
        # two x264 encodes of the same frames (measured: 0 to 0.008 apart); a frame out of place: 0.10
        assert np.abs(written - encoded).mean() < 0.03, name
        with av.open(str(tmp_path / "out" / f"{name}.mp4")) as container:
            assert container.streams.audio, name


def test_a_video_written_in_blocks_refuses_a_short_count(tmp_path):
    from relight_core.errors import InputError
    from relight_core.media import save_video

    blocks = (np.zeros((4, 16, 16, 3), np.float32) for _ in range(2))
    with pytest.raises(InputError, match="got 8 frames where 9 were due"):
        save_video(tmp_path / "short.mp4", blocks, 12, num_frames=9)
    assert not list(tmp_path.iterdir())  # nothing half-written left behind
