"""A studio that is safe to share, tried over real HTTP against a launched app (issue 8).

Uploaded HTML/SVG/JS never come back as live pages; files the studio did not write are not served,
whatever the path spelling; `--temp-dir DIR` gets a fresh subfolder; logins back off per client;
results are normal 0644 files in a 0700 folder; SIGTERM leaves no temp folder; the API takes any
valid frame range and refuses absurd numbers, one-frame videos and images named .mp4 in one sentence.
"""

from __future__ import annotations

import os
import signal
import socket
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


def test_active_content_in_the_studios_own_folders_is_a_download_too(studio):
    # Files under the allowed folders (the work folder, examples) are served inline by Gradio with the type
    # their name suggests; any type a browser could run as a page must still come back as a download.
    client, demo, _, tmp = studio
    folder = Path(demo.studio_root) / "work" / "odd-names"
    folder.mkdir(parents=True, exist_ok=True)
    page = '<x xmlns:h="http://www.w3.org/1999/xhtml"><h:script>alert(1)</h:script></x>'
    for name in ("evil.html", "evil.rdf", "evil.xslt", "evil.mml", "evil.atom", "evil.xht"):
        (folder / name).write_text(page)
        response = httpx.get(f"{client.src}gradio_api/file={folder / name}")
        assert response.status_code == 200, (name, response.status_code)
        kind = response.headers["content-type"]
        assert not any(t in kind for t in ("html", "svg", "javascript", "xml")), (name, kind)
        assert response.headers["content-disposition"].startswith("attachment"), name
    picture = scene_image(folder / "picture.png")  # what the studio does write there is still shown inline
    response = httpx.get(f"{client.src}gradio_api/file={picture}")
    assert response.headers["content-type"] == "image/png"
    assert not response.headers.get("content-disposition", "").startswith("attachment")


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


@pytest.mark.parametrize("value, words", [
    (float("nan"), "The number of steps must be a whole number within range, not nan."),
    (float("inf"), "not inf"), (1e308, "not 1e+308"), (2.5, "not 2.5"), ("many", "not 'many'"), (None, "not 'None'")])
def test_whole_number_fields_of_a_request_are_one_sentence(value, words):
    # API clients reach Studio.run with whatever JSON numbers they send (non-standard NaN included);
    # int() would say "cannot convert float NaN to integer" and a huge frame number would print 309 digits.
    from relight_core.errors import InputError
    from ui.inputs import whole_number

    with pytest.raises(InputError) as caught:
        whole_number(value, "number of steps")
    assert words in str(caught.value) and len(str(caught.value)) < 100
    assert whole_number(7.0, "seed") == 7 and whole_number("12", "seed") == 12
    assert whole_number(2 ** 63 - 1, "seed") == 2 ** 63 - 1  # the largest seed, exactly


def test_x_forwarded_for_keys_a_client_only_behind_the_share_tunnel():
    from ui.security import client_key

    tunnel = {"client": ("127.0.0.1", 50000), "headers": [(b"x-forwarded-for", b"6.6.6.6, 203.0.113.7")]}
    assert client_key(tunnel, trust_forwarded=True) == "203.0.113.7"  # the hop the tunnel added
    assert client_key(tunnel) == "127.0.0.1"                          # no tunnel: a local user's own header
    remote = {"client": ("198.51.100.2", 50000), "headers": tunnel["headers"]}
    assert client_key(remote, trust_forwarded=True) == "198.51.100.2"  # only a loopback peer can be a tunnel


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

        def login(password: str, client: str = "127.0.0.11", forwarded: str | None = None) -> int:
            # Clients are loopback addresses of their own (127.0.0.0/8 all reach the server).
            with httpx.Client(transport=httpx.HTTPTransport(local_address=client), timeout=120) as http:
                return http.post(f"{url}login", data={"username": "ann", "password": password},
                                 headers={"X-Forwarded-For": forwarded} if forwarded else {}).status_code

        assert [login(f"guess{i}") for i in range(4)] == [400] * 4
        assert waits.pop("127.0.0.11") == [0.5, 1.0, 2.0]  # before the 2nd, 3rd and 4th attempts
        assert login("wrong", client="127.0.0.12") == 400 and "127.0.0.12" not in waits  # others do not wait
        # Without a share tunnel X-Forwarded-For is not trusted: a fresh header per guess is no fresh client.
        assert login("guess4", forwarded="1.2.3.4") == 400 and waits.pop("127.0.0.11") == [4.0]
        assert "1.2.3.4" not in waits
        assert login("secret") == 200  # the right password still works, after its wait
        assert waits.pop("127.0.0.11") == [8.0]
        assert login("secret") == 200 and "127.0.0.11" not in waits  # success forgot the failures
        # Guessing in parallel does not help: one client's attempts are taken one at a time.
        threads = [threading.Thread(target=login, args=(f"p{i}", "127.0.0.13")) for i in range(5)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert waits.pop("127.0.0.13") == [0.5, 1.0, 2.0, 4.0]
        for _ in range(12):  # the wait stops growing at BACKOFF_MAX_S
            login("again", client="127.0.0.14")
        assert max(waits["127.0.0.14"]) == security.BACKOFF_MAX_S
        logged = [r.getMessage() for r in caplog.records if r.name == "unirelight.studio.auth"]
        assert "Failed login for user 'ann' from 127.0.0.11 (4 in a row); its next attempt waits 4.0 s." in logged
        assert any("succeeded after 5 failed attempts" in m for m in logged), logged
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


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # uvicorn's SystemExit(3)
def test_a_busy_port_a_foreign_address_and_an_unusable_temp_dir_are_one_sentence(tmp_path, monkeypatch, capfd):
    from relight_core.errors import InputError

    monkeypatch.setenv("GRADIO_TEMP_DIR", os.environ.get("GRADIO_TEMP_DIR", ""))  # restored afterwards
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(InputError, match=f"cannot listen on 127.0.0.1 at port {port}"):
            start_studio(tmp_path / "a", port=port)
    with pytest.raises(InputError, match="cannot listen on 203.0.113.9"):  # a documentation address
        start_studio(tmp_path / "b", host="203.0.113.9")
    assert "Errno" not in capfd.readouterr().err  # uvicorn's own bind error line is held back
    a_file = tmp_path / "a-file"
    a_file.write_text("not a folder")
    done = subprocess.run([sys.executable, "app.py", "--no-browser", "--temp-dir", str(a_file)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("error: ") and "a-file" in lines[0] and "not a folder" in lines[0], lines
