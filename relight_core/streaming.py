"""Samplers report through a plain callback; `stream` turns those calls into generator items on
the caller's side, running the work on a worker thread that stops at its next callback when the
generator is closed (or when the work raises `Stopped`).

`stop_all()` stops and joins every worker still running; a process calls it before it exits. A
SIGTERM or Ctrl+C raised in the main thread while `Thread.start()` waits for the new thread, or
while the caller's loop body runs and the generator is left suspended, would otherwise leave a
daemon worker inside a torch call at interpreter exit, where Python ends it with a forced unwind
through C++ frames: "terminate called without an active exception" and an abort (exit -6)
instead of the clean exit the signal asked for.
"""

from __future__ import annotations

import queue
import threading
from typing import Callable

_WORKERS: dict[threading.Thread, tuple[threading.Event, threading.Event]] = {}  # thread: (stop, began)
_WORKERS_LOCK = threading.Lock()
_LIMBO_WAIT_S = 0.5  # a worker whose start() was interrupted: how long to wait for it to begin

class Stopped(Exception):
    """Raised from the sampler callback when the caller asked to stop."""


def stream(work: Callable[[Callable[[object], None]], object]):
    """Run `work(emit)` on a worker thread and yield what it emits; return its result.

    Samplers report through a plain callback; a thread turns those calls into generator items
    without the sampler knowing. Closing the generator stops the worker at its next callback.
    """
    events: queue.Queue = queue.Queue()
    stop, began = threading.Event(), threading.Event()
    outcome: dict = {}

    def emit(event) -> None:
        if stop.is_set():
            raise Stopped
        events.put(event)

    def target() -> None:
        began.set()
        try:
            if stop.is_set():  # stopped before it began
                raise Stopped
            outcome["value"] = work(emit)
        except BaseException as exc:  # re-raised on the caller's thread below
            outcome["error"] = exc
        finally:
            events.put(_DONE)
            with _WORKERS_LOCK:
                _WORKERS.pop(threading.current_thread(), None)

    worker = threading.Thread(target=target, name="relight-sampler", daemon=True)
    with _WORKERS_LOCK:
        _WORKERS[worker] = (stop, began)
    try:
        worker.start()
        while (event := events.get()) is not _DONE:
            yield event
    finally:
        _stop_and_join(worker, stop, began)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def stop_all() -> None:
    """Stop every worker that is still running and wait for each to end (at its next callback)."""
    with _WORKERS_LOCK:
        workers = list(_WORKERS.items())
    for worker, (stop, began) in workers:
        _stop_and_join(worker, stop, began)


def _stop_and_join(worker: threading.Thread, stop: threading.Event, began: threading.Event) -> None:
    stop.set()
    if began.is_set() or began.wait(_LIMBO_WAIT_S):  # never began: start() was interrupted before it
        worker.join()
    with _WORKERS_LOCK:
        _WORKERS.pop(worker, None)


_DONE = object()
