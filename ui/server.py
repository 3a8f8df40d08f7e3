"""Serving the studio: temp folders, the queue, upload limits, auth and the share link."""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import signal
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

from relight_core.errors import InputError
from relight_core.streaming import stop_all

REPO_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class ServerOptions:
    """How to serve the studio (the command line of app.py, as data)."""

    host: str = "127.0.0.1"
    port: int | None = None               # None: the first free port from 7860
    model: str = "default"
    precision: str | None = None          # None: the model's (normally auto); see relight_core/precision.py
    share: bool = False
    share_timeout_s: float = 5.0          # how long to try reaching the share server
    auth: tuple[str, str] | None = None
    inbrowser: bool = True
    max_upload_mb: int = 500
    queue_size: int = 16                  # jobs waiting beyond this are turned away with a message
    concurrency: int = 1                  # model runs at once; more only helps with spare accelerator memory
    temp_dir: Path | None = None          # None: a fresh folder under the system temp, removed at exit
    envmaps_dir: Path = REPO_ROOT / "envmaps"
    examples_dir: Path = REPO_ROOT / "examples"
    model_choice: bool | None = None      # may visitors load another model? None: only on a local-only server

    @property
    def visitors_choose_model(self) -> bool:
        """Whether the Advanced "Model" box is open: by default not behind a share link or a LAN address,
        where strangers could make the server load arbitrary folders."""
        if self.model_choice is not None:
            return self.model_choice
        return not self.share and self.host in ("127.0.0.1", "localhost", "::1")


def prepare_environment(temp_dir: Path | None) -> Path:
    """Point Gradio's uploads and VTK at the right places before they are imported; return the root.

    The root is always a fresh folder the studio creates (mode 0700, so only this user reads
    uploads and results) and removes at exit: under the system temp, or under `temp_dir` when
    given, never `temp_dir` itself, whose other files must not become servable.
    """
    parent = None
    try:
        if temp_dir is not None:
            parent = Path(temp_dir)
            parent.mkdir(parents=True, exist_ok=True)
        root = Path(tempfile.mkdtemp(prefix="unirelight-studio-", dir=parent)).resolve()
    except OSError as exc:  # a file, a folder this user cannot write, a full disk
        where = f"--temp-dir {temp_dir}" if temp_dir is not None else "the system temp folder"
        reason = "it is a file, not a folder" if parent is not None and parent.is_file() else exc.strerror or exc
        raise InputError(f"The studio cannot make its folder in {where} ({reason}); "
                         "pass --temp-dir with a folder this user can write.") from None
    atexit.register(shutil.rmtree, root, ignore_errors=True)
    os.environ["GRADIO_TEMP_DIR"] = str(root / "gradio")
    os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    return root


def share_server_reachable(timeout_s: float) -> bool:
    """Whether Gradio's share-link server answers within `timeout_s` (it cannot on an offline machine)."""
    import httpx
    from gradio.networking import GRADIO_API_SERVER

    try:
        httpx.get(GRADIO_API_SERVER, timeout=timeout_s).raise_for_status()
    except (httpx.HTTPError, OSError):
        return False
    return True


def start(options: ServerOptions, block: bool = True):
    """Build and launch the studio; returns (demo, local_url, share_url) when not blocking.

    Blocking, it serves until Ctrl+C or SIGTERM, then stops and removes its temp folder.
    """
    if block and _main_thread():
        signal.signal(signal.SIGTERM, _terminate)  # from here on, like Ctrl+C (atexit cleans up)
    root = prepare_environment(options.temp_dir)
    from ui.layout import build_demo, launch_kwargs  # after the environment is set
    from ui.studio import Studio, StudioConfig

    studio = Studio(StudioConfig(model=options.model, precision=options.precision,
                                 envmaps_dir=options.envmaps_dir,
                                 work_dir=root / "work", max_upload_mb=options.max_upload_mb,
                                 model_choice=options.visitors_choose_model))
    demo = build_demo(studio, options.examples_dir)
    demo.queue(max_size=options.queue_size, default_concurrency_limit=options.concurrency)

    share = options.share
    if share and not share_server_reachable(options.share_timeout_s):
        print("* Could not reach the Gradio share server, so there is no public link "
              "(is this machine offline?). The studio keeps serving locally.", flush=True)
        share = False
    # Only folders of files the studio itself writes are "allowed" (served inline): its work folder
    # and the bundled examples. Uploads stay in Gradio's upload folder, which Gradio serves inline
    # only for media types that cannot run script; FileHeaders enforces that on every file route.
    from starlette.middleware import Middleware

    from ui.security import ClientAddress, FileHeaders, LoginGuard

    auth = None
    if options.auth is not None:
        auth = LoginGuard({options.auth[0]: options.auth[1]}).check  # failures are logged as warnings
    demo.studio_root = root  # the studio's own temp folder (tests and shutdown use it)
    local_url = share_url = None
    try:  # a SIGTERM/Ctrl+C from the moment the server may answer is a normal stop (exit 0)
        _, local_url, share_url = _launch(
            demo, options, server_name=options.host, server_port=options.port, share=share, auth=auth,
            inbrowser=options.inbrowser, max_file_size=f"{options.max_upload_mb}mb",
            allowed_paths=[str(studio.work_dir.resolve()), str(options.examples_dir)], prevent_thread_lock=True,
            app_kwargs={"middleware": [Middleware(FileHeaders), Middleware(ClientAddress, trust_forwarded=share)]},
            show_error=True, footer_links=["api", "settings"], quiet=True, **launch_kwargs())
        print(f"* UniRelight Studio is running at {local_url} (model: {options.model}, "
              f"{studio.relighter().precision}; Ctrl+C to stop)", flush=True)
        if share and share_url is None:
            print("* The share link could not be created; the studio keeps serving locally.", flush=True)
        if share_url:
            print(f"* Public share link for reviewers: {share_url}", flush=True)
        if block:
            demo.block_thread()  # returns on Ctrl+C, and on SIGTERM through _terminate
    except KeyboardInterrupt:
        if not block:
            raise
    finally:
        if block:
            shutdown(demo)
    return demo, local_url, share_url


def _launch(demo, options: ServerOptions, **kwargs):
    """`demo.launch`, with a port that is taken or an address that is not this machine's said in one sentence
    (Gradio raises one OSError for both: "Cannot find empty port in range: ..."). Uvicorn's own log line
    about a failed bind is held back meanwhile: the sentence says it."""
    uvicorn_log = logging.getLogger("uvicorn.error")
    hold = logging.Filter("held back while launching")  # passes no uvicorn.error record
    uvicorn_log.addFilter(hold)
    try:
        return demo.launch(**kwargs)
    except OSError as exc:
        from gradio.http_server import INITIAL_PORT_VALUE, TRY_NUM_PORTS

        ports = (f"port {options.port}" if options.port is not None
                 else f"any port from {INITIAL_PORT_VALUE} to {INITIAL_PORT_VALUE + TRY_NUM_PORTS - 1}")
        raise InputError(f"The studio cannot listen on {options.host} at {ports} ({_reason(exc)}); pass a free "
                         "--port, and a --host that is one of this machine's addresses.") from None
    finally:
        uvicorn_log.removeFilter(hold)


def _reason(exc: OSError) -> str:
    if exc.strerror:
        return exc.strerror.lower()
    text = str(exc)
    return "in use or not available" if text.startswith("Cannot find empty port") else text.split(". ")[0]


def shutdown(demo) -> None:
    """Stop serving and remove the studio's temp folder (uploads, results, work files)."""
    demo.close(verbose=False)
    stop_all()  # a job still sampling stops at its next step; no sampler thread outlives the server
    root = getattr(demo, "studio_root", None)
    if root is not None:
        shutil.rmtree(root, ignore_errors=True)


def _terminate(signum, frame):
    """SIGTERM is handled like Ctrl+C: stop serving, clean up, exit."""
    raise KeyboardInterrupt


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()

