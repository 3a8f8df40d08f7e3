"""The Ray engine shared by `batch` (manifest rows), `render-data` (scenes) and `autolabel` (videos).

* `connect`: a local Ray instance when no address is given, else the cluster at `address`.
* `worker_plan`: how many workers fit, with which resources and device (a GPU worker declares GPUs,
  a CPU worker a CPU budget and runs torch on as many threads).
* `run_units`: units of work spread over Ray actors (one model each, loaded once) or plain Ray
  tasks, at most `count` at a time, each result handed to the caller as it arrives. A unit's own
  failure is its result (one sentence, made by `sentence`); a worker process that dies fails the
  unit it held alone and is replaced. With no Ray (`ray=None`) the same loop runs the units one
  after another in this process: the cheap start of a one-worker job on one machine.
* `ModelWorker`: what an actor (or the in-process worker) that holds one `Relighter` shares.
* `locked`: one run at a time per output folder.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, TypeVar

from relight_core.errors import InputError

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the folder that holds relight_core/
POLL_S = 0.5  # how often the driver wakes while waiting, so Ctrl+C and SIGTERM act at once
DONE, FAILED = "done", "failed"

Unit = TypeVar("Unit")


@dataclass(frozen=True)
class UnitResult:
    """What one unit of work (a scene, a video) left: done, or failed with its one sentence."""

    name: str
    status: str               # done | failed
    seconds: float = 0.0      # wall seconds on its worker
    error: str = ""
    cpu_seconds: float = 0.0  # CPU seconds of its worker process (0 when not measured)


def stop_if_interrupted(exc: BaseException) -> None:
    """Re-raise a Ctrl+C or SIGTERM that a native library wrapped in an error of its own.

    A signal handler's exception raised while Dr.Jit runs Mitsuba's render comes back as a RuntimeError
    caused by it; caught as a unit's failure, a SIGTERM would fail one scene and the run would go on.
    """
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            raise cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__


def sentence(exc: BaseException, noun: str = "row") -> str:
    """The one-sentence reason a unit failed with `exc` (InputError's text, a disk error, a bug)."""
    if isinstance(exc, InputError):
        text = str(exc)
    elif isinstance(exc, OSError):  # an output folder that cannot be written, a full disk
        where = f" ({exc.filename})" if exc.filename else ""
        text = f"{exc.strerror or exc}{where}; free some space or choose another output folder."
    else:  # a bug must fail its unit, not the run
        text = f"Unexpected {type(exc).__name__} ({exc}); please report it with this {noun}."
    return " ".join(text.split())


# ---------------------------------------------------------------------------------------------
# Connecting
# ---------------------------------------------------------------------------------------------

def _ray():
    try:
        import ray
    except ImportError:
        raise InputError("Ray is not installed, and this command runs on it; install it with "
                         "pip install -r requirements.txt.") from None
    return ray


@contextlib.contextmanager
def connect(address: str | None = None, num_cpus: int | None = None) -> Iterator[object]:
    """Connect to the Ray cluster at `address`, or start a local instance (of `num_cpus` CPUs; None:
    all); disconnect (and stop a local instance) on leaving. A process already connected keeps its
    connection."""
    ray = _ray()
    if ray.is_initialized():
        yield ray
        return
    # Workers import relight_core from this checkout: a local instance inherits the path from this
    # process (so Ray's pre-started workers serve it); a cluster's nodes get it as the job's environment.
    path = os.pathsep.join(filter(None, [str(PACKAGE_ROOT), os.environ.get("PYTHONPATH")]))
    common = dict(log_to_driver=False, logging_level=logging.ERROR)
    if address and address != "auto":
        check_reachable(address)  # Ray itself would retry an unreachable address for minutes
    try:
        with _own_signal_handlers():
            if address:
                ray.init(address=address, runtime_env={"env_vars": {"PYTHONPATH": path}}, **common)
            else:
                with _environment(PYTHONPATH=path,
                                  RAY_USAGE_STATS_ENABLED=os.environ.get("RAY_USAGE_STATS_ENABLED", "0")):
                    ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, **common)
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as exc:
        ray.shutdown()
        reason = " ".join(str(exc).split())[:200]
        if address:
            raise InputError(f"Could not connect to the Ray cluster at {address} ({reason}); check that it runs "
                             "there and, if it uses token authentication, set RAY_AUTH_MODE=token and its token "
                             "here too (docs/SCALE.md).") from None
        raise InputError(f"Could not start a local Ray instance ({reason}); start one with 'ray start --head' and "
                         "pass its address as --ray-address.") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Raise InputError unless something accepts connections at HOST:PORT (also `ray://HOST:PORT`)."""
    if address == "auto":
        return
    host, _, port = address.split("://")[-1].rstrip("/").rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"'{address}' is not a Ray address; give HOST:PORT as 'ray start --head' prints it, "
                         "e.g. 10.0.0.1:6379.")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise InputError(f"Nothing answers at {address} ({exc.strerror or exc}); start the cluster with "
                         "'ray start --head' there, or check the address.") from None


@contextlib.contextmanager
def _own_signal_handlers():
    """Keep this process's SIGTERM and SIGINT handlers across the block: ray.init installs its own, which
    abort the process, where ours stop the run cleanly (arguments.terminate_as_interrupt)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {number: signal.getsignal(number) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for number, handler in saved.items():
            if handler is not None:
                signal.signal(number, handler)


@contextlib.contextmanager
def sigterm_kept():
    """ray.wait turns the exception a signal handler raises into a plain KeyboardInterrupt; after a SIGTERM,
    raise the handler's own (Terminated: exit code 143, not Ctrl+C's 130)."""
    handler = signal.getsignal(signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread() or not callable(handler):
        yield
        return
    received = []
    signal.signal(signal.SIGTERM, lambda number, frame: received.append(number) or handler(number, frame))
    try:
        yield
    except KeyboardInterrupt:
        if received:
            handler(signal.SIGTERM, None)
        raise
    finally:
        signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def _environment(**values: str):
    """Set environment variables for the block (the processes it starts inherit them)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextlib.contextmanager
def engine(address: str | None, workers: int | None, num_cpus: int | None = None) -> Iterator[object | None]:
    """Ray for a run (connected as `connect` does), or None: run in this process. In-process is chosen
    only for one worker and no address (`--workers 1` on one machine), where starting Ray would cost
    more than the job."""
    if workers == 1 and not address:
        yield None
        return
    with connect(address, num_cpus) as ray, sigterm_kept():
        yield ray


# ---------------------------------------------------------------------------------------------
# Workers
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class WorkerPlan:
    """How many workers a run starts, what each declares to Ray, and where it runs."""

    count: int
    demand: dict          # Ray resources of one worker: num_cpus, num_gpus
    device: str           # cpu | cuda…
    threads: int          # torch threads of a CPU worker


def worker_plan(ray, units: int, workers: int | None = None, device: str | None = None,
                cpus_per_worker: float = 1.0, gpus_per_worker: float = 1.0, gpu_capable: bool = True) -> WorkerPlan:
    """Workers for `units` units on this cluster: GPU workers when it has GPUs (or `device` says cuda)
    and the work can use one, else CPU workers; `workers` None fills the cluster, more than fit are cut
    to what fits, with a note."""
    resources = ray.cluster_resources()
    gpus, cpus = resources.get("GPU", 0.0), resources.get("CPU", 0.0)
    use_gpu = gpu_capable and (gpus > 0 if device is None else device.startswith("cuda"))
    if use_gpu and gpus == 0:
        raise InputError("GPU workers were asked for (--device cuda), but the Ray cluster has no GPU; "
                         "run with --device cpu or add GPU nodes.")
    per_worker = gpus_per_worker if use_gpu else cpus_per_worker
    room = max(1, math.floor((gpus if use_gpu else cpus) / per_worker + 1e-9))
    count = workers or room
    if count > room:
        kind = f"{per_worker:g} GPU" if use_gpu else f"{per_worker:g} CPU"
        print(f"note: the Ray cluster has room for {room} worker{'s' * (room != 1)} of {kind} each; "
              f"running {room}.", file=sys.stderr)
        count = room
    demand = {"num_gpus": gpus_per_worker, "num_cpus": cpus_per_worker} if use_gpu else \
        {"num_cpus": cpus_per_worker}
    where = (device or "cuda") if use_gpu else "cpu"
    return WorkerPlan(max(1, min(count, units)), demand, where, max(1, int(cpus_per_worker)))


class ModelWorker:
    """A worker holding one model, loaded once: a Ray actor, or the in-process worker.

    A model that cannot load is kept as `load_error` and raised by `check()` at the first unit, where
    the driver reads it as one sentence and stops the run (every unit would fail)."""

    def __init__(self, model: str, device: str | None, precision: str | None, threads: int | None):
        import torch

        from relight_core.pipeline import Relighter

        if device == "cpu" and threads:
            torch.set_num_threads(threads)
        self.load_error = ""
        try:
            self.relighter = Relighter.load(model, device=device, precision=precision)
        except InputError as exc:
            self.load_error = str(exc)
        except Exception as exc:  # damaged weights, a GPU that fails: every unit on this worker would fail
            self.load_error = " ".join(f"The model '{model}' could not be loaded on {device or 'this machine'} "
                                       f"({type(exc).__name__}: {exc}); check the model folder.".split())

    def check(self) -> None:
        if self.load_error:
            raise InputError(self.load_error)


# ---------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------

def run_units(ray, units: Sequence[Unit], count: int, start_worker: Callable[[], Any] | None,
              call: Callable[[Any, Unit], Any], finish: Callable[[Unit, Any], None],
              failed: Callable[[Unit, str], Any], noun: str, retry: Callable[[Unit], str],
              deadline: float | None = None) -> None:
    """Run `units`, at most `count` at a time, and hand each result to `finish(unit, result)` as it comes;
    after the `time.monotonic()` `deadline` (if any) no unit starts, those running finish, the rest are left.

    `start_worker()` makes a worker (a Ray actor; with `ray` None, an object in this process), or is
    None for plain Ray tasks. `call(worker, unit)` starts a unit: with Ray it returns the ObjectRef
    (`worker.run.remote(…)` or `task.remote(…)`), without it the result itself. A unit's own errors
    are its result; the loop turns what happens outside the unit's code into `failed(unit, sentence)`:
    a worker process that died (the unit alone fails, `retry(unit)` says how to run it again, and an
    actor is replaced) or an exception escaping the worker. An InputError escaping a worker stops the
    run with that sentence (a model that cannot load: every unit would fail)."""
    def time_left() -> bool:
        return deadline is None or time.monotonic() < deadline

    if ray is None:
        worker = start_worker() if start_worker else None
        for unit in units:
            if not time_left():
                return
            finish(unit, call(worker, unit))
        return
    from ray.exceptions import RayError, RayTaskError

    idle = [start_worker() if start_worker else None for _ in range(count)]
    pending, running = deque(units), {}
    try:
        while running or (pending and time_left()):
            while idle and pending and time_left():  # each worker holds one unit at a time
                worker, unit = idle.pop(), pending.popleft()
                running[call(worker, unit)] = (worker, unit)
            if not running:  # the deadline passed between the two checks
                break
            ready, _ = ray.wait(list(running), num_returns=1, timeout=POLL_S)
            for ref in ready:
                worker, unit = running.pop(ref)
                try:
                    result = ray.get(ref)
                except RayTaskError as exc:
                    if isinstance(exc.cause, InputError):  # the model cannot load: every unit would fail
                        raise InputError(str(exc.cause)) from None
                    result = failed(unit, f"Unexpected {type(exc.cause).__name__} in the worker; please report "
                                          f"it with this {noun}.")
                except RayError as exc:  # its process died (out of memory, a lost node), its result was lost
                    reason = " ".join(str(exc).split())[:160]
                    result = failed(unit, f"The worker running this {noun} stopped ({reason}); {retry(unit)}.")
                    if worker is not None:
                        ray.kill(worker)
                        worker = start_worker()
                finish(unit, result)
                idle.append(worker)
    finally:
        for worker in idle + [worker for worker, _ in running.values()]:
            if worker is not None:
                ray.kill(worker)
        if start_worker is None:
            for ref in running:  # tasks still rendering on a cluster that outlives this run
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)


# ---------------------------------------------------------------------------------------------
# Output folders
# ---------------------------------------------------------------------------------------------

@contextlib.contextmanager
def locked(folder: Path, lock_name: str = ".batch.lock", what: str = "batch run", flag: str = "--out"):
    """Hold FOLDER/LOCK_NAME so that two runs never write one output folder at once."""
    with open(Path(folder) / lock_name, "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(f"Another {what} is writing to {folder}; wait for it to end or choose another "
                             f"{flag}.") from None
        yield
