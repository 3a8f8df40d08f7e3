"""Samplers report through a plain callback; `stream` turns those calls into generator items on
the caller's side, running the work on a worker thread that stops at its next callback when the
generator is closed (or when the work raises `Stopped`)."""

from __future__ import annotations

import queue
import threading
from typing import Callable

class Stopped(Exception):
    """Raised from the sampler callback when the caller asked to stop."""


def stream(work: Callable[[Callable[[object], None]], object]):
    """Run `work(emit)` on a worker thread and yield what it emits; return its result.

    Samplers report through a plain callback; a thread turns those calls into generator items
    without the sampler knowing. Closing the generator stops the worker at its next callback.
    """
    events: queue.Queue = queue.Queue()
    stop = threading.Event()
    outcome: dict = {}

    def emit(event) -> None:
        if stop.is_set():
            raise Stopped
        events.put(event)

    def target() -> None:
        try:
            outcome["value"] = work(emit)
        except BaseException as exc:  # re-raised on the caller's thread below
            outcome["error"] = exc
        finally:
            events.put(_DONE)

    worker = threading.Thread(target=target, name="relight-sampler", daemon=True)
    worker.start()
    try:
        while (event := events.get()) is not _DONE:
            yield event
    finally:
        stop.set()
        worker.join()
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


_DONE = object()
