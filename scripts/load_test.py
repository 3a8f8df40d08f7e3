"""Load test: N clients × M relight jobs against a studio this script launches on loopback.

    python scripts/load_test.py --clients 8 --jobs 2            # tiny model, 64 px, 2 steps
    python scripts/load_test.py --clients 16 --jobs 1 --queue-size 4   # overflow the queue on purpose

Bounded: at most 32 clients × 10 jobs, a wall-clock limit (--timeout), and the app listens on
127.0.0.1 only. It prints submitted / completed / rejected (with the queue-full message) / failed /
lost, the app's RSS before, at its peak and after, then stops the app with SIGTERM and reports the
temp files left behind (there should be none). Exit code 0 when nothing was lost or left.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_bytes(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--jobs", type=int, default=2, help="jobs per client")
    parser.add_argument("--queue-size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--model", default="tiny")
    parser.add_argument("--timeout", type=float, default=900.0, help="wall-clock limit in seconds")
    args = parser.parse_args()
    if not (1 <= args.clients <= 32 and 1 <= args.jobs <= 10 and 0 < args.timeout <= 3600):
        parser.error("use 1–32 clients, 1–10 jobs each and a timeout of at most 3600 s")

    work = Path(tempfile.mkdtemp(prefix="unirelight-load-"))
    try:
        return _run(args, work)
    finally:  # whatever happened (an app that never started, Ctrl+C): no server and no files left behind
        shutil.rmtree(work, ignore_errors=True)


def _stop(app: subprocess.Popen) -> int | str:
    """SIGTERM the app (as a user would) and wait; kill it if it does not stop within 120 s."""
    if app.poll() is not None:
        return app.returncode
    app.send_signal(signal.SIGTERM)
    try:
        return app.wait(timeout=120)
    except subprocess.TimeoutExpired:
        app.kill()
        app.wait()
        return "killed after 120 s"


def _run(args, work: Path) -> int:
    """Launch the app with its temp folder in `work`, load it, stop it; the app is stopped whatever happens."""
    from relight_core import media

    image = work / "scene.png"
    yy, xx = np.mgrid[0:48, 0:64] / np.array([48, 64])[:, None, None]
    media.save_image(image, np.stack([xx, yy, 0.5 * xx * yy], -1).astype(np.float32))
    temp = work / "temp"
    port = free_port()
    app = subprocess.Popen([sys.executable, str(ROOT / "app.py"), "--model", args.model, "--no-browser",
                            "--host", "127.0.0.1", "--port", str(port), "--temp-dir", str(temp),
                            "--queue-size", str(args.queue_size)], cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        return _load(args, app, port, image, temp)
    finally:
        if app.poll() is None:  # not stopped by _load (it did not start, or an error): stop it now
            _stop(app)


def _load(args, app: subprocess.Popen, port: int, image: Path, temp: Path) -> int:
    """Wait for the app, run the clients, print the numbers, then SIGTERM it and count the files it left."""
    from gradio_client import Client, handle_file

    url = f"http://127.0.0.1:{port}/"
    deadline = time.monotonic() + args.timeout
    while True:
        if app.poll() is not None or time.monotonic() > deadline:
            print("the app did not start")
            return 1
        try:
            if httpx.get(f"{url}config", timeout=2).status_code == 200:
                break
        except httpx.HTTPError:
            time.sleep(0.5)

    rss = {"before": rss_bytes(app.pid), "peak": rss_bytes(app.pid)}
    stop_sampling = threading.Event()

    def sample() -> None:
        while not stop_sampling.wait(0.2):
            rss["peak"] = max(rss["peak"], rss_bytes(app.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    counts: Counter = Counter()
    messages: Counter = Counter()
    lock = threading.Lock()

    def client_run(index: int) -> None:
        client = Client(url, verbose=False)
        for job_index in range(args.jobs):
            with lock:
                counts["submitted"] += 1
            try:
                job = client.submit(handle_file(str(image)), "Relight", "studio", None, 90.0, 0.0, False, 0, 360,
                                    1, 0, 0, 64, args.steps, "euler", index * 100 + job_index, 0.0, args.model,
                                    api_name="/relight")
                outputs = job.result(timeout=max(1.0, deadline - time.monotonic()))
                status = str(outputs[0] if isinstance(outputs, (list, tuple)) else outputs)
                kind = "completed" if "Done" in status else "lost"
            except Exception as exc:  # noqa: BLE001 - every outcome is counted
                text = " ".join(str(exc).split())[:160]
                kind = "rejected" if "queue" in text.lower() and "full" in text.lower() else \
                    ("lost" if "timeout" in type(exc).__name__.lower() else "failed")
                with lock:
                    messages[f"{kind}: {text}"] += 1
            with lock:
                counts[kind] += 1
        client.close()

    started = time.monotonic()
    threads = [threading.Thread(target=client_run, args=(i,), daemon=True) for i in range(args.clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(max(0.0, deadline - time.monotonic()))
    lost_threads = sum(thread.is_alive() for thread in threads)
    seconds = time.monotonic() - started
    time.sleep(1.0)
    stop_sampling.set()
    rss["after"] = rss_bytes(app.pid)

    code = _stop(app)
    left = [p for p in temp.rglob("*") if p.is_file()] if temp.exists() else []

    gb = 2**30
    print(f"clients {args.clients} × jobs {args.jobs} (queue size {args.queue_size}, model {args.model}, "
          f"{args.steps} steps, 64 px) in {seconds:.1f} s")
    print(f"submitted {counts['submitted']}, completed {counts['completed']}, rejected {counts['rejected']}, "
          f"failed {counts['failed']}, lost {counts['lost'] + lost_threads}")
    for message, count in messages.most_common(5):
        print(f"  {count} × {message}")
    print(f"app RSS: before {rss['before'] / gb:.2f} GB, peak {rss['peak'] / gb:.2f} GB, "
          f"after {rss['after'] / gb:.2f} GB")
    print(f"SIGTERM: exit code {code}; temp files left: {len(left)}")
    return 0 if counts["lost"] + lost_threads == 0 and not left and code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
