"""The studio through its HTTP API (gradio_client), against a real server on a free localhost port."""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import numpy as np
import OpenEXR
import pytest
from gradio_client import Client, handle_file
from PIL import Image

from relight_core import media
from tests.factory import REPO, free_port, plain, relight_args, run_job, scene_image, start_studio, write_bad_inputs


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    demo, url, _ = start_studio(tmp)
    client = Client(url, verbose=False)
    yield client, tmp
    client.close()
    demo.close()


def test_relight_streams_previews_then_final_files(studio):
    client, tmp = studio
    updates = run_job(client, **relight_args(REPO / "examples" / "inputs" / "objects.png"))
    # Output order: status, input, relit, albedo, input video, relit video, albedo video, compare,
    # seeds, downloads.
    previews = [u for u in updates if u[2] and "preview" in Path(u[2]).name]
    assert len(previews) >= 3, [u[0] for u in updates]
    assert all(u[3] and "preview" in Path(u[3]).name for u in previews)
    final = updates[-1]
    assert "Done" in final[0]
    downloads = [Path(p) for p in final[9]]
    assert sorted(p.suffix for p in downloads) == [".exr", ".png", ".png"]
    for path in downloads:
        assert path.is_file()
        if path.suffix == ".png":
            assert Image.open(path).size == (256, 192)  # relit at 64×48, returned at the input's 256×192
        else:
            with OpenEXR.File(str(path)) as exr:
                pixels = next(iter(exr.channels().values())).pixels
            assert pixels.shape[:2] == (192, 256) and np.isfinite(pixels).all()
    relit = np.asarray(Image.open(final[2]))
    assert relit.shape == (192, 256, 3)
    before, after = final[7]
    assert Path(before).is_file() and Path(after).is_file()
    root, = (tmp / "studio").glob("unirelight-studio-*")  # the studio's own subfolder of --temp-dir
    assert list((root / "work" / "jobs").iterdir()) == []  # the job's own files are gone


def test_video_streams_chunks_and_keeps_fps(studio):
    client, tmp = studio
    # 25 frames: the tiny model's 17-frame chunks with a 9-frame overlap make two chunks.
    still = media.load_media(REPO / "examples" / "inputs" / "objects.png").frames[0]
    clip = tmp / "pan.mp4"
    media.save_video(clip, np.stack([np.roll(still, 4 * t, axis=1) for t in range(25)]), 12.0)
    shown = [plain(v) for v in client.predict(handle_file(str(clip)), api_name="/inspect_input")]
    assert "25 frames" in shown[-1]  # the info line
    assert shown[-3:-1] == [0, 24]  # first and last frame: the range defaults to the whole clip
    updates = run_job(client, **relight_args(clip, frame_start=0, frame_end=24, size=64))
    partial = [u for u in updates[:-1] if u[5] and "relit-part0" in str(u[5])]
    assert partial, "the first chunk's video should appear before the job finishes"
    first = partial[0][5]["video"] if isinstance(partial[0][5], dict) else partial[0][5]
    assert media.load_media(first).frames.shape[0] == 17  # exactly the first chunk's frames
    final = updates[-1]
    assert "Done" in final[0]
    relit_video = final[5]["video"] if isinstance(final[5], dict) else final[5]
    relit = media.load_media(relit_video)
    assert relit.is_video and relit.frames.shape == (25, 192, 256, 3) and relit.fps == pytest.approx(12.0)
    assert sorted(Path(p).suffix for p in final[9]) == [".mp4", ".mp4"]


def test_an_animated_gif_is_relit_as_a_clip_at_its_own_rate(studio):
    client, tmp = studio
    still = (media.load_media(REPO / "examples" / "inputs" / "objects.png").frames[0] * 255).astype(np.uint8)
    frames = [Image.fromarray(np.roll(still, 6 * t, axis=1)[::4, ::4]) for t in range(5)]
    gif = tmp / "pan.gif"
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=80, loop=0)
    shown = [plain(v) for v in client.predict(handle_file(str(gif)), api_name="/inspect_input")]
    assert shown[-1].startswith("Animation: 64×48, 5 frames at 12.5 fps") and shown[-3:-1] == [0, 4]
    preview = shown[1]["video"] if isinstance(shown[1], dict) else shown[1]
    assert Path(preview).suffix == ".mp4" and media.load_media(preview).frames.shape[0] == 5  # a browser plays it
    final = run_job(client, **relight_args(gif, frame_start=1, frame_end=4, size=64))[-1]
    assert "Done" in final[0]
    relit = media.load_media(final[5]["video"] if isinstance(final[5], dict) else final[5])
    assert relit.is_video and relit.frames.shape[:3] == (4, 48, 64) and relit.fps == pytest.approx(12.5)


def test_same_seed_reproduces_a_random_illumination(studio):
    client, tmp = studio
    image = scene_image(tmp / "seeds.png")
    batch = run_job(client, **relight_args(image, mode="Random illumination", num_seeds=2, seed=7))
    gallery = batch[-1][8]  # [{"image": path, "caption": "seed N"}, ...]
    assert [item["caption"] for item in gallery] == ["seed 7", "seed 8"]
    again = run_job(client, **relight_args(image, mode="Random illumination", num_seeds=1, seed=8))
    first, second = (np.asarray(Image.open(item["image"])) for item in gallery)
    assert np.abs(first.astype(int) - second.astype(int)).mean() > 1  # different seeds differ
    np.testing.assert_array_equal(second, np.asarray(Image.open(again[-1][8][0]["image"])))


def test_light_preview_endpoint_changes_with_rotation(studio):
    client, _ = studio
    a = client.predict("studio", None, 0.0, 0.0, "Relight", api_name="/light_preview")
    b = client.predict("studio", None, 90.0, 0.0, "Relight", api_name="/light_preview")
    assert np.abs(np.asarray(Image.open(a), np.int16) - np.asarray(Image.open(b), np.int16)).mean() > 2
    # With the light sweeping across a clip, the preview shows frame 0: the sweep's start angle.
    swept = client.predict("studio", None, 0.0, 0.0, "Relight", True, 90.0, api_name="/light_preview")
    np.testing.assert_array_equal(np.asarray(Image.open(swept)), np.asarray(Image.open(b)))
    # A lower colour temperature makes the light, and so the balls, warmer.
    warm = client.predict("studio", None, 0.0, 0.0, "Relight", False, 0.0, 3000.0, api_name="/light_preview")
    red_minus_blue = [float(np.mean(image[..., 0]) - np.mean(image[..., 2]))
                      for image in (np.asarray(Image.open(p), np.float32) for p in (a, warm))]
    assert red_minus_blue[1] > red_minus_blue[0] + 10, red_minus_blue


@pytest.mark.parametrize("mode, relit, albedo, downloads", [
    ("Albedo only", False, True, ["albedo.png"]),
    ("Render from albedo", True, False, ["relit-linear.exr", "relit.png"]),
])
def test_other_modes_make_only_their_results(studio, mode, relit, albedo, downloads):
    client, _ = studio
    probe = handle_file(str(REPO / "envmaps" / "sunset.exr"))
    updates = run_job(client, **relight_args(REPO / "examples" / "inputs" / "objects.png", mode=mode,
                                             probe_upload=probe, temperature=3200.0))
    final = updates[-1]
    assert "Done" in final[0]
    # Output 2 is the relit image, 3 the albedo: a mode that makes no such result never shows one,
    # not even as a step preview.
    for index, made in ((2, relit), (3, albedo)):
        if made:
            assert np.asarray(Image.open(final[index])).shape == (192, 256, 3)
        else:
            assert all(u[index] is None for u in updates), mode
    assert sorted(Path(p).name for p in final[9]) == downloads
    assert (final[7] is not None) == relit  # before/after only for a mode that makes a relit image


def test_stop_cancels_a_running_job_and_the_next_one_runs(studio):
    client, _ = studio
    image = REPO / "examples" / "inputs" / "objects.png"
    job = client.submit(**relight_args(image, steps=1000, size=128), api_name="/relight")  # minutes of work
    previews = 0
    for update in job:
        previews += plain(update[2]) is not None  # a step preview arrived: the job is sampling
        if previews >= 2:
            break
    stopped_at = time.monotonic()
    client.predict(api_name="/stop")
    # The worker stops at its next step, so the next job does not wait behind 1000 steps.
    assert "Done" in run_job(client, **relight_args(image))[-1][0]
    assert time.monotonic() - stopped_at < 30
    assert job.done() and not any("Done" in str(plain(u[0])) for u in job.outputs())


def test_bad_inputs_give_readable_errors_and_the_app_keeps_serving(studio):
    client, tmp = studio
    bad = write_bad_inputs(tmp)
    good = scene_image(tmp / "good.png")
    cases = [
        (relight_args(bad["corrupt"]), "corrupt.png"),
        (relight_args(bad["fake_video"]), "fake.mp4"),
        (relight_args(good, probe_upload=handle_file(str(bad["nan_probe"]))), "nan.exr"),
    ]
    for args, name in cases:
        with pytest.raises(Exception) as error:
            run_job(client, **args)
        message = str(error.value)
        assert name in message and len(message) < 400, message
        # ...and the next good request is served normally.
        assert "Done" in run_job(client, **relight_args(good))[-1][0]
    # Oversized uploads: the client refuses them, and so does the server if a client does not.
    with pytest.raises(ValueError, match="maximum file size"):
        client.predict(**relight_args(bad["big"]), api_name="/relight")
    with bad["big"].open("rb") as f:
        response = httpx.post(f"{client.src}gradio_api/upload", files={"files": f})
    assert response.status_code == 413 and "maximum allowed size" in response.text
    assert "Done" in run_job(client, **relight_args(good))[-1][0]


def test_an_ensemble_runs_through_the_api_and_a_bad_count_is_one_sentence(studio):
    client, tmp = studio
    image = scene_image(tmp / "ensemble.png", size=(80, 48))  # content of its own: gradio caches by content
    one = run_job(client, **relight_args(image, steps=1))[-1]
    three = run_job(client, **relight_args(image, steps=1, ensemble=3))[-1]
    assert "Done" in one[0] and "Done" in three[0]
    relit_one, relit_three = (np.asarray(Image.open(final[2]), np.float32) for final in (one, three))
    assert relit_one.shape == relit_three.shape and np.abs(relit_one - relit_three).mean() > 0.1
    with pytest.raises(Exception) as error:
        run_job(client, **relight_args(image, steps=1, ensemble=0))
    message = str(error.value)
    assert "less than minimum value 1" in message and len(message) < 400, message   # the slider's own check
    assert "Done" in run_job(client, **relight_args(image, steps=1))[-1][0]


def test_inspect_input_reports_corrupt_files(studio):
    client, tmp = studio
    bad = write_bad_inputs(tmp)
    with pytest.raises(Exception, match="fake.mp4"):
        client.predict(handle_file(str(bad["fake_video"])), api_name="/inspect_input")


def test_command_line_options():
    from app import parse_args

    options = parse_args(["--model", "tiny", "--port", "9000", "--auth", "ann:pa:ss", "--share", "--no-browser"])
    assert (options.model, options.port, options.auth, options.share, options.inbrowser) == \
        ("tiny", 9000, ("ann", "pa:ss"), True, False)
    defaults = parse_args([])
    assert (defaults.model, defaults.host, defaults.inbrowser, defaults.auth) == ("default", "127.0.0.1", True, None)
    with pytest.raises(SystemExit):
        parse_args(["--auth", "nopassword"])


def test_auth_protects_the_app(tmp_path):
    demo, url, _ = start_studio(tmp_path, auth=("ann", "secret"))
    try:
        assert httpx.get(f"{url}config").status_code == 401
        client = Client(url, auth=("ann", "secret"), verbose=False)
        assert client.predict("studio", None, 10.0, 0.0, "Relight", api_name="/light_preview")
        with pytest.raises(Exception):
            Client(url, auth=("ann", "wrong"), verbose=False)
    finally:
        demo.close()


def test_share_falls_back_to_local_when_the_tunnel_is_unreachable(tmp_path, capsys, monkeypatch):
    # Point the share server at a closed local port so the check fails fast, online or not.
    monkeypatch.setattr("gradio.networking.GRADIO_API_SERVER", f"http://127.0.0.1:{free_port()}/v1")
    demo, url, share_url = start_studio(tmp_path, share=True, share_timeout_s=1.0)
    try:
        assert share_url is None
        assert "keeps serving locally" in capsys.readouterr().out
        assert Client(url, verbose=False).predict("studio", None, 10.0, 0.0, "Relight",
                                                  api_name="/light_preview")
    finally:
        demo.close()


def test_progress_counts_the_steps_chosen_and_the_whole_jobs_time():
    from relight_core.pipeline import Progress
    from ui.views import _progress_text

    blank = np.zeros((2, 2, 3), np.float32)
    last = Progress(21, 21, 0, 1, blank, blank, eta_s=0.0, steps=20)  # the final clean-x0 evaluation
    assert _progress_text(last, 0, 1, 7).startswith("Step 20 of 20 · ")
    # Random illuminations: seed 2 of 4 nearly done, two more to come: the time left covers them.
    text = _progress_text(Progress(3, 6, 0, 1, blank, blank, eta_s=1.0, steps=5), 1, 4, 8, eta_s=125.0)
    assert text == "Step 3 of 5 · seed 8 (2 of 4) · about 2 min 05 s left"

