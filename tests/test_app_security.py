"""A studio that is safe to share, tried over real HTTP against a launched app (issue 8).

Uploaded HTML/SVG/JS never come back as live pages; files the studio did not write are not served,
whatever the path spelling; `--temp-dir DIR` gets a fresh subfolder; logins back off per client;
results are normal 0644 files in a 0700 folder; SIGTERM leaves no temp folder; the API takes any
valid frame range and refuses absurd numbers, one-frame videos and images named .mp4 in one sentence.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import quote

import httpx
import numpy as np
import pytest
from gradio_client import Client, handle_file

from relight_core import media
from tests.factory import free_port, relight_args, run_job, scene_image, start_studio

ROOT = Path(__file__).resolve().parent.parent
SECRET = "top secret: not written by the studio"
ACTIVE = {  # name → content a browser would run if it were served inline from the app's origin
    "evil.html": "<html><script>alert(document.cookie)</script></html>",
    "evil.svg": '<svg xmlns="http://www.w3.org/2000/svg"><script>alert(1)</script></svg>',
    "evil.js": "alert(1)",
    "evil.xhtml": '<html xmlns="http://www.w3.org/1999/xhtml"><script>alert(1)</script></html>',
}


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("security")
    shared = tmp / "shared"
    shared.mkdir()
    (shared / "secret.txt").write_text(SECRET)
    demo, url, _ = start_studio(tmp, temp_dir=shared)
    client = Client(url, verbose=False)
    yield client, demo, shared, tmp
    client.close()
    demo.close()


def upload(url: str, name: str, content: bytes) -> str:
    response = httpx.post(f"{url}gradio_api/upload", files={"files": (name, content)})
    response.raise_for_status()
    return response.json()[0]


def test_uploaded_active_content_is_never_served_inline(studio):
    client, _, _, _ = studio
    for name, content in ACTIVE.items():
        path = upload(client.src, name, content.encode())
        response = httpx.get(f"{client.src}gradio_api/file={path}")
        assert response.status_code == 200, (name, response.status_code)  # a download, not a page
        kind = response.headers["content-type"]
        assert not any(t in kind for t in ("html", "svg", "javascript", "xml")), (name, kind)
        assert response.headers["content-disposition"].startswith("attachment"), name
        assert response.headers["x-content-type-options"] == "nosniff"


def test_temp_dir_gets_a_fresh_private_subfolder(studio):
    _, demo, shared, _ = studio
    root = Path(demo.studio_root)
    assert root.parent == shared.resolve() and root.name.startswith("unirelight-studio-")
    assert root.stat().st_mode & 0o777 == 0o700  # only the studio's user reads uploads and results
    assert os.environ["GRADIO_TEMP_DIR"] == str(root / "gradio")


def test_files_the_studio_did_not_write_are_not_served(studio):
    client, demo, shared, _ = studio
    root = Path(demo.studio_root)
    secret = shared.resolve() / "secret.txt"
    gradio_dir = root / "gradio"
    gradio_dir.mkdir(exist_ok=True)
    spellings = [
        str(secret),
        f"{gradio_dir}/../../secret.txt",
        f"{root}/work/../../secret.txt",
        quote(f"{gradio_dir}/../../secret.txt", safe=""),
        f"{gradio_dir}/%2e%2e/%2e%2e/secret.txt",
        f"{gradio_dir}/%252e%252e/%252e%252e/secret.txt",
        f"{gradio_dir}/..%5c..%5csecret.txt",
        f"{secret}%00.png",
        "/etc/passwd",
        str(ROOT / "app.py"),
    ]
    for spelling in spellings:
        for route in ("gradio_api/file=", "gradio_api/file/"):
            response = httpx.get(f"{client.src}{route}{spelling}")
            assert response.status_code in (400, 403, 404), (spelling, response.status_code)
            assert SECRET not in response.text and "root:" not in response.text


def test_results_are_plain_files_in_the_studios_own_folder(studio):
    client, demo, _, tmp = studio
    final = run_job(client, **relight_args(scene_image(tmp / "scene.png"), steps=1))[-1]
    assert "Done" in final[0]
    downloads = {Path(p).name: Path(p).read_bytes() for p in final[9]}  # the client's copies
    assert sorted(downloads) == ["albedo.png", "relit-linear.exr", "relit.png"]
    root = Path(demo.studio_root)
    served = [p for p in (root / "gradio").rglob("*") if p.is_file() and p.name in downloads]
    assert {p.name for p in served} == set(downloads)  # the served copies live under the 0700 root
    for path in served:
        assert path.stat().st_mode & 0o777 == 0o644, (path, oct(path.stat().st_mode))
        response = httpx.get(f"{client.src}gradio_api/file={path}")
        assert response.status_code == 200 and response.content == path.read_bytes()
    assert any(downloads[p.name] == p.read_bytes() for p in served)


def test_one_frame_videos_and_images_named_mp4_are_one_sentence(studio):
    client, _, _, tmp = studio
    one = tmp / "single.mp4"
    media.save_video(one, np.full((1, 32, 48, 3), 0.5, np.float32), 12.0)
    png_named_mp4 = tmp / "photo.mp4"
    png_named_mp4.write_bytes(scene_image(tmp / "photo.png").read_bytes())
    for path, fragment in [(one, "only 1 frame"), (png_named_mp4, "still image named like a video")]:
        with pytest.raises(Exception) as error:
            client.predict(handle_file(str(path)), api_name="/inspect_input")
        message = str(error.value)
        assert path.name in message and fragment in message and "Slider" not in message, message
    with pytest.raises(Exception, match="photo.mp4 is a still image named like a video"):
        run_job(client, **relight_args(png_named_mp4, steps=1))


def test_api_takes_any_valid_frame_range_and_refuses_past_the_end(studio):
    client, _, _, tmp = studio
    clip = tmp / "twenty.mp4"
    media.save_video(clip, np.random.default_rng(0).random((20, 32, 48, 3), dtype=np.float32), 10.0)
    # No /inspect_input first: the sliders still have their initial 0–1 range in this session.
    final = run_job(client, **relight_args(clip, frame_start=15, frame_end=19, steps=1))[-1]
    video = final[5]["video"] if isinstance(final[5], dict) else final[5]
    assert media.load_media(video).frames.shape[0] == 5
    with pytest.raises(Exception, match="past the end of twenty.mp4"):
        run_job(client, **relight_args(clip, frame_start=15, frame_end=20, steps=1))


def test_absurd_numbers_are_refused_and_the_next_job_runs(studio):
    client, _, _, tmp = studio
    image = scene_image(tmp / "numbers.png")
    for overrides, fragment in [(dict(rotate_light=True, sweep_start=-1e308), "sweep start"),
                                (dict(rotate_light=True, sweep_end=1e308), "sweep end"),
                                (dict(seed=1180591620717411303424), "seed")]:
        with pytest.raises(Exception) as error:
            run_job(client, **relight_args(image, steps=1, **overrides))
        message = str(error.value)
        assert "Traceback" not in message and len(message) < 400, message
        assert fragment in message, message
    assert "Done" in run_job(client, **relight_args(image, steps=1))[-1][0]


def test_a_truncated_video_is_refused_with_the_frames_read(studio):
    client, _, _, tmp = studio
    whole = tmp / "whole.mp4"
    media.save_video(whole, np.random.default_rng(1).random((17, 32, 48, 3), dtype=np.float32), 12.0)
    half = tmp / "half.mp4"
    half.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(Exception, match=r"half.mp4 is truncated or damaged: only \d+ of its 17 frames"):
        run_job(client, **relight_args(half, frame_start=0, frame_end=16, steps=1))


def test_failed_logins_back_off_per_client_and_are_logged(tmp_path, monkeypatch, caplog):
    # The server's clock stands still except while it waits, so the waits it asks for are exact
    # however slow this machine is; `waits` records them per client.
    import ui.security as security

    clock = [1000.0]
    waits: dict[str, list[float]] = {}

    async def sleep(seconds: float) -> None:
        waits.setdefault(security._client.get(), []).append(round(seconds, 6))
        clock[0] += seconds

    monkeypatch.setattr(security, "_now", lambda: clock[0])
    monkeypatch.setattr(security, "_sleep", sleep)
    monkeypatch.setattr(security, "BACKOFF_BASE_S", 0.5)
    demo, url, _ = start_studio(tmp_path, auth=("ann", "secret"))
    try:
        assert httpx.get(f"{url}config").status_code == 401

        def login(password: str, client: str = "10.0.0.1") -> int:
            return httpx.post(f"{url}login", data={"username": "ann", "password": password},
                              headers={"X-Forwarded-For": client}, timeout=120).status_code

        assert [login(f"guess{i}") for i in range(4)] == [400] * 4
        assert waits.pop("10.0.0.1") == [0.5, 1.0, 2.0]  # before the 2nd, 3rd and 4th attempts
        assert login("wrong", client="10.0.0.2") == 400 and "10.0.0.2" not in waits  # others do not wait
        assert login("secret") == 200  # the right password still works, after its wait
        assert waits.pop("10.0.0.1") == [4.0]
        assert login("secret") == 200 and "10.0.0.1" not in waits  # success forgot the failures
        # Guessing in parallel does not help: one client's attempts are taken one at a time.
        threads = [threading.Thread(target=login, args=(f"p{i}", "10.0.0.3")) for i in range(5)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert waits.pop("10.0.0.3") == [0.5, 1.0, 2.0, 4.0]
        for _ in range(12):  # the wait stops growing at BACKOFF_MAX_S
            login("again", client="10.0.0.4")
        assert max(waits["10.0.0.4"]) == security.BACKOFF_MAX_S
        logged = [r.getMessage() for r in caplog.records if r.name == "unirelight.studio.auth"]
        assert "Failed login for user 'ann' from 10.0.0.1 (4 in a row); its next attempt waits 4.0 s." in logged
        assert any("succeeded after 4 failed attempts" in m for m in logged), logged
    finally:
        demo.close()


def test_sigterm_stops_the_app_and_removes_its_temp_folder(tmp_path):
    temp = tmp_path / "temp"
    port = free_port()
    proc = subprocess.Popen([sys.executable, "app.py", "--model", "tiny", "--no-browser", "--port", str(port),
                             "--temp-dir", str(temp)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}/"
    try:
        deadline = time.monotonic() + 480  # a loaded 2-core machine can take minutes to import and build
        while True:
            assert proc.poll() is None, proc.communicate()[0]
            assert time.monotonic() < deadline, "the app did not start"
            try:
                if httpx.get(f"{url}config", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.5)
        upload(url, "upload.png", scene_image(tmp_path / "u.png").read_bytes())
        assert len(list(temp.iterdir())) == 1 and list(temp.glob("*/gradio/*/upload.png"))
        proc.send_signal(signal.SIGTERM)
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    assert "Traceback" not in output
    assert list(temp.iterdir()) == [], list(temp.rglob("*"))[:5]
