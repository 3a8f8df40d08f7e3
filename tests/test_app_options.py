"""Who may pick the model: open on a local-only server, locked behind a share link or LAN address."""

from pathlib import Path

import pytest

from relight_core.errors import InputError
from ui.server import ServerOptions
from ui.studio import Studio, StudioConfig

ROOT = Path(__file__).resolve().parent.parent


def test_model_choice_is_open_only_on_a_local_server():
    assert ServerOptions().visitors_choose_model
    assert not ServerOptions(share=True).visitors_choose_model
    assert not ServerOptions(host="0.0.0.0").visitors_choose_model
    assert ServerOptions(share=True, model_choice=True).visitors_choose_model
    assert not ServerOptions(model_choice=False).visitors_choose_model


def test_a_fixed_model_refuses_other_folders(tmp_path):
    studio = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / "work",
                                 model_choice=False))
    with pytest.raises(InputError, match="fixed model"):
        studio.relighter(str(tmp_path))
    assert studio.relighter("") is studio.relighter("tiny")


def test_the_model_line_shows_the_precision_in_use(tmp_path):
    import app

    assert app.parse_args(["--precision", "fp32"]).precision == "fp32"
    assert app.parse_args([]).precision is None
    studio = Studio(StudioConfig(model="tiny", precision="fp32", envmaps_dir=ROOT / "envmaps",
                                 work_dir=tmp_path / "work"))
    assert studio.relighter().precision == "fp32"
    assert "Precision: **fp32** (as asked)" in studio.model_notice()
    auto = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / "work2"))
    assert f"Precision: **{auto.relighter().precision}** (auto, by this machine)" in auto.model_notice()


def test_app_refuses_fp16_on_the_cpu_in_one_sentence(capsys):
    import app
    import torch

    if torch.cuda.is_available():
        pytest.skip("fp16 is valid where the studio runs on a GPU")

    assert app.main(["--precision", "fp16", "--model", "tiny", "--no-browser"]) == 2
    assert capsys.readouterr().err.strip() == \
        "error: fp16 runs only on a CUDA GPU, not on cpu; use --precision auto, fp32 or bf16 here."


def test_the_working_size_starts_at_the_models_and_says_where_results_come_back(tmp_path):
    import gradio as gr

    from ui.layout import build_demo

    def size_dropdown(full_resolution: bool):
        studio = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / str(full_resolution),
                                     full_resolution=full_resolution))
        demo = build_demo(studio)
        found = [block for block in demo.blocks.values()
                 if isinstance(block, gr.Dropdown) and block.label.startswith("Working resolution")]
        assert len(found) == 1
        return studio.relighter().spec, found[0]

    spec, dropdown = size_dropdown(True)
    assert dropdown.value == spec.size == 64
    assert "own size is 64 px" in dropdown.info and "input's own resolution" in dropdown.info
    _, raw = size_dropdown(False)
    assert "own size is 64 px" in raw.info and "resolution" not in raw.info


def test_the_ensemble_slider_starts_at_the_models_and_counts_in_the_estimate(tmp_path):
    import gradio as gr

    from tests.factory import scene_image
    from ui.layout import build_demo

    studio = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path))
    found = [block for block in build_demo(studio).blocks.values()
             if isinstance(block, gr.Slider) and block.elem_id == "ensemble"]
    assert len(found) == 1 and found[0].value == studio.relighter().spec.ensemble == 1
    assert (found[0].minimum, found[0].maximum) == (1, 16)
    image = str(scene_image(tmp_path / "scene.png"))

    relighter = studio.relighter("tiny")
    asked = []
    estimate = relighter.estimate_seconds
    relighter.estimate_seconds = lambda *args: asked.append(args[-1]) or 1000 * estimate(*args)
    for ensemble in (None, 1, 16):
        assert studio.estimate(image, "Relight", 0, 0, 64, 4, 1, "tiny", ensemble).startswith("About **")
    assert asked == [None, 1, 16]
    assert estimate(1, 64, 64, 4, 16) > estimate(1, 64, 64, 4, 1)   # exact scaling: test_ensemble.py
    assert "from 1 to 16" in studio.estimate(image, "Relight", 0, 0, 64, 4, 1, "tiny", 0)


def test_the_studio_relights_a_wide_photo_on_the_default_models_own_grid(tmp_path):
    # The default model's frames need multiples of 8 px, not 16: a 16:9 upload works at 128×72 (its own shape)
    # and comes back at the input's resolution. The studio once rounded to 16 (128×64, squashed).
    from types import SimpleNamespace

    import numpy as np
    from PIL import Image

    from relight_core import media
    from relight_core.media.image import resize

    image = tmp_path / "wide.png"
    media.save_image(image, resize(media.load_media(ROOT / "examples" / "inputs" / "objects.png").frames, 180, 320)[0])
    studio = Studio(StudioConfig(model="default", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / "work"))
    assert "at 128×72" in studio.estimate(str(image), "Relight", 0, 0, 128, 1, 1, "default")
    shapes = []  # read while streaming: the job's folder goes when the run ends (Gradio has copied it by then)
    for update in studio.run(str(image), "Relight", "sunset", None, 0.0, 0.0, False, 0, 360, 1, 0, 0, 128, 1,
                             "res2ab", 0, 0.0, "default", 6500.0, 0.0, 0.0, request=SimpleNamespace(session_hash="w")):
        if "Done" in str(update[0]):
            shapes.append(np.asarray(Image.open(update[2])).shape)
    assert shapes == [(180, 320, 3)]


def test_the_studio_brings_a_video_too_long_to_hold_back_at_its_own_size(tmp_path, monkeypatch):
    # A video's results come back at the file's own size from the file, a block of frames at a time: with the
    # decode budget cut to 4 of the clip's 12 frames at that size, the input, the relit clip and their stills are
    # still 48×32, all 12 frames (the blocks' frames equal the whole clip's: test_cli.py).
    from types import SimpleNamespace

    import numpy as np

    from relight_core import media
    from relight_core.media import iter_video, video
    from tests.factory import make_mp4, plain

    clip = make_mp4(tmp_path / "clip.mp4", frames=12, width=48, height=32)
    studio = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / "work"))
    monkeypatch.setattr(video, "MAX_DECODED_PIXELS", 4 * 48 * 32)
    latest, seen = {}, {}
    for update in studio.run(str(clip), "Relight", "sunset", None, 0.0, 0.0, False, 0, 360, 1, 0, 11, 32, 1,
                             "euler", 0, 0.0, "tiny", 6500.0, 0.0, 0.0, request=SimpleNamespace(session_hash="v")):
        # status, input still, relit still, albedo still, input video, relit video, albedo video, ...
        latest.update({k: v for k, v in enumerate(plain(value) for value in update) if isinstance(v, str)})
        if "Done" in latest[0]:  # read while streaming: the job's folder goes when the run ends
            seen = {"input": np.concatenate(list(iter_video(latest[4]))),
                    "relit": np.concatenate(list(iter_video(latest[5]))),
                    "stills": [media.load_media(latest[k]).frames.shape for k in (1, 2, 3)]}
    assert seen["input"].shape == seen["relit"].shape == (12, 32, 48, 3)
    assert seen["stills"] == [(1, 32, 48, 3)] * 3


def test_an_upload_is_a_clip_by_its_content_and_its_name_must_agree(tmp_path):
    import numpy as np
    from PIL import Image

    from tests.factory import make_mp4
    from ui.inputs import is_clip, is_video

    frames = [Image.fromarray(np.full((8, 8, 3), 60 * k, np.uint8)) for k in range(3)]
    frames[0].save(tmp_path / "anim.gif", save_all=True, append_images=frames[1:], duration=100)
    frames[0].save(tmp_path / "anim.png", save_all=True, append_images=frames[1:], duration=100)  # APNG
    frames[0].save(tmp_path / "still.gif")
    assert is_video(tmp_path / "anim.gif") and is_video(tmp_path / "anim.png")
    assert not is_video(tmp_path / "still.gif") and not is_clip(tmp_path / "still.gif")
    # A real video under an image's name (even one an animation could have) is still named in one sentence.
    make_mp4(tmp_path / "clip.mp4")
    for name in ("clip.png", "clip.gif"):
        (tmp_path / name).write_bytes((tmp_path / "clip.mp4").read_bytes())
        with pytest.raises(InputError, match="is a video named like an image"):
            is_video(tmp_path / name)
        assert not is_clip(tmp_path / name)
