"""Serving the studio: temp folders, the queue, upload limits, auth and the share link."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class ServerOptions:
    """How to serve the studio (the command line of app.py, as data)."""

    host: str = "127.0.0.1"
    port: int | None = None               # None: the first free port from 7860
    model: str = "default"
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
    """Point Gradio's uploads and VTK at the right places before they are imported; return the root."""
    if temp_dir is None:
        root = Path(tempfile.mkdtemp(prefix="unirelight-studio-"))
        atexit.register(shutil.rmtree, root, ignore_errors=True)
    else:
        root = Path(temp_dir)
        root.mkdir(parents=True, exist_ok=True)
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
    """Build and launch the studio; returns (demo, local_url, share_url) when not blocking."""
    root = prepare_environment(options.temp_dir)
    from ui.layout import build_demo, launch_kwargs  # after the environment is set
    from ui.studio import Studio, StudioConfig

    studio = Studio(StudioConfig(model=options.model, envmaps_dir=options.envmaps_dir,
                                 work_dir=root / "work", max_upload_mb=options.max_upload_mb,
                                 model_choice=options.visitors_choose_model))
    demo = build_demo(studio, options.examples_dir)
    demo.queue(max_size=options.queue_size, default_concurrency_limit=options.concurrency)

    share = options.share
    if share and not share_server_reachable(options.share_timeout_s):
        print("* Could not reach the Gradio share server, so there is no public link "
              "(is this machine offline?). The studio keeps serving locally.", flush=True)
        share = False
    _, local_url, share_url = demo.launch(
        server_name=options.host, server_port=options.port, share=share, auth=options.auth,
        inbrowser=options.inbrowser, max_file_size=f"{options.max_upload_mb}mb",
        allowed_paths=[str(root), str(options.examples_dir)], prevent_thread_lock=True,
        show_error=True, footer_links=["api", "settings"], quiet=True, **launch_kwargs())
    print(f"* UniRelight Studio is running at {local_url} (model: {options.model}; Ctrl+C to stop)", flush=True)
    if share and share_url is None:
        print("* The share link could not be created; the studio keeps serving locally.", flush=True)
    if share_url:
        print(f"* Public share link for reviewers: {share_url}", flush=True)
    if block:
        demo.block_thread()
    return demo, local_url, share_url
