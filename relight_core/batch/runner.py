"""Batch relighting on Ray: manifest rows spread over worker actors that each hold one model.

* Ray: a local instance when no address is given, else the cluster at `address` (`ray start --head`).
* Workers: actors that load the model once and run rows one at a time. A GPU worker declares
  `gpus_per_worker` GPUs; a CPU worker declares `cpus_per_worker` CPUs and runs torch on as many threads.
* Each row writes into OUT/<row>/ through a hidden staging folder renamed into place, so a row folder
  is whole or absent; its result is appended to OUT/results.csv as it finishes (manifest.py).
* A bad row fails alone with its one-sentence reason; a worker that dies fails the row it held and is
  replaced. A model that cannot load stops the batch with its sentence (every row would fail).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import math
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from relight_core.batch.manifest import (DONE, FAILED, ManifestRow, RowResult, append_result, is_finished,
                                         read_manifest, read_results, write_results)
from relight_core.batch.progress import Progress
from relight_core.errors import InputError
from relight_core.jobs import MediaJob

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the folder that holds relight_core/
POLL_S = 0.5  # how often the driver wakes while waiting, so Ctrl+C and SIGTERM act at once


@dataclass(frozen=True)
class BatchOptions:
    """How to run a batch: where, on how many workers, which model, which rows."""

    address: str | None = None         # a running Ray cluster; None: start a local instance
    workers: int | None = None         # None: one per GPU, else one per `cpus_per_worker` CPUs
    cpus_per_worker: float = 1.0       # a CPU worker's budget (its torch threads); a GPU worker's host CPUs
    gpus_per_worker: float = 1.0       # GPUs a GPU worker holds (fractions share one)
    model: str = "default"
    device: str | None = None          # cpu | cuda; None: GPU workers when the cluster has GPUs
    precision: str | None = None
    retry_failed: bool = False         # also run rows whose last result is failed
    rows: frozenset[int] | None = None  # run exactly these rows, whatever their results


@dataclass(frozen=True)
class BatchSummary:
    """What a batch run leaves: counts over the whole manifest and where the results are."""

    rows: int
    done: int
    failed: int
    ran: int        # rows run (or failed at parsing) by this call
    results: Path


# ---------------------------------------------------------------------------------------------
# The worker
# ---------------------------------------------------------------------------------------------

class RowWorker:
    """A Ray actor: one model, loaded once, running manifest rows one at a time."""

    def __init__(self, model: str, device: str, precision: str | None, threads: int):
        import torch

        from relight_core.pipeline import Relighter

        if device == "cpu":
            torch.set_num_threads(threads)
        self.load_error = ""
        try:
            self.relighter = Relighter.load(model, device=device, precision=precision)
        except InputError as exc:  # raised again by run(), where the driver reads it as one sentence
            self.load_error = str(exc)
        except Exception as exc:  # damaged weights, a GPU that fails: every row on this worker would fail
            self.load_error = " ".join(f"The model '{model}' could not be loaded on {device} "
                                       f"({type(exc).__name__}: {exc}); check the model folder.".split())

    def run(self, row: int, job: MediaJob, out: str) -> RowResult:
        """Run one row into OUT/<row>/; every failure is this row's result, with one sentence."""
        from relight_core.jobs import load_inputs, plan_job, write_job

        if self.load_error:
            raise InputError(self.load_error)
        started = time.perf_counter()
        try:
            inputs = load_inputs(job)
            plan = plan_job(job, self.relighter, inputs)
            staging = Path(tempfile.mkdtemp(prefix=f".partial-{row}-", dir=out))
            try:
                written = write_job(job, self.relighter, inputs, plan, staging)
                folder = Path(out) / str(row)
                shutil.rmtree(folder, ignore_errors=True)  # an earlier run's outputs of this row
                os.replace(staging, folder)
            finally:
                shutil.rmtree(staging, ignore_errors=True)
            return RowResult(row, DONE, time.perf_counter() - started, tuple(f"{row}/{p.name}" for p in written))
        except InputError as exc:
            error = str(exc)
        except OSError as exc:  # an output folder that cannot be written, a full disk
            where = f" ({exc.filename})" if exc.filename else ""
            error = f"{exc.strerror or exc}{where}; free some space or choose another output folder."
        except Exception as exc:  # a bug must fail its row, not the batch
            error = f"Unexpected {type(exc).__name__} ({exc}); please report it with this row."
        return RowResult(row, FAILED, time.perf_counter() - started, (), " ".join(error.split()))


# ---------------------------------------------------------------------------------------------
# Ray
# ---------------------------------------------------------------------------------------------

def _ray():
    try:
        import ray
    except ImportError:
        raise InputError("Batch runs need Ray, which is not installed; install it with "
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
        _check_reachable(address)  # Ray itself would retry an unreachable address for minutes
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
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        reason = " ".join(str(exc).split())[:200]
        raise InputError(f"Could not connect to {where} ({reason}); start one with 'ray start --head' and "
                         "pass its address as --ray-address.") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Raise InputError unless something accepts connections at HOST:PORT (also `ray://HOST:PORT`)."""
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
    abort the process, where ours stop the batch cleanly (arguments.terminate_as_interrupt)."""
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
def _sigterm_kept():
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


def _worker_plan(ray, options: BatchOptions, rows: int) -> tuple[int, dict, str, int]:
    """(number of workers, their Ray resources, their device, their torch threads) for this cluster."""
    resources = ray.cluster_resources()
    gpus, cpus = resources.get("GPU", 0.0), resources.get("CPU", 0.0)
    use_gpu = gpus > 0 if options.device is None else options.device.startswith("cuda")
    if use_gpu and gpus == 0:
        raise InputError("GPU workers were asked for (--device cuda), but the Ray cluster has no GPU; "
                         "run with --device cpu or add GPU nodes.")
    per_worker = options.gpus_per_worker if use_gpu else options.cpus_per_worker
    room = max(1, math.floor((gpus if use_gpu else cpus) / per_worker + 1e-9))
    workers = options.workers or room
    if workers > room:
        kind = f"{per_worker:g} GPU" if use_gpu else f"{per_worker:g} CPU"
        print(f"note: the Ray cluster has room for {room} worker{'s' * (room != 1)} of {kind} each; "
              f"running {room}.", file=sys.stderr)
        workers = room
    demand = {"num_gpus": options.gpus_per_worker, "num_cpus": options.cpus_per_worker} if use_gpu else \
        {"num_cpus": options.cpus_per_worker}
    device = (options.device or "cuda") if use_gpu else "cpu"
    return min(workers, rows), demand, device, max(1, int(options.cpus_per_worker))


@contextlib.contextmanager
def _locked(out: Path):
    """Hold OUT/.batch.lock so that two runs never write one results manifest."""
    with open(out / ".batch.lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(f"Another batch run is writing to {out}; wait for it to end or choose another "
                             "--out.") from None
        yield


# ---------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------

def run_batch(manifest: Path, out: Path, template: MediaJob, seeds: tuple[int, ...] | None = None,
              options: BatchOptions = BatchOptions(), progress: bool = True) -> BatchSummary:
    """Run a manifest's unfinished rows on Ray; results go to OUT/<row>/ and OUT/results.csv."""
    from relight_core.checkpoint import resolve_model

    rows = read_manifest(manifest, template, seeds)
    spec, _ = resolve_model(options.model)  # an unknown model is one sentence before Ray starts
    if options.address and options.address != "auto":
        _check_reachable(options.address)  # so is a cluster that is not there
    numbers = {r.row for r in rows}
    if options.rows is not None and not options.rows <= numbers:
        missing = min(options.rows - numbers)
        raise InputError(f"--rows names row {missing}, but the manifest has rows 1 to {len(rows)}.")
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    with _locked(out):
        for stale in out.glob(".partial-*"):  # rows a killed run left half-written
            shutil.rmtree(stale, ignore_errors=True)
        results = read_results(out)
        todo = [r for r in rows if _wanted(r, results.get(r.row), out, options)]
        progress_bar = Progress(len(rows), todo, results, out, enabled=progress)
        try:
            for r in [r for r in todo if r.job is None]:  # a bad cell fails its row without a worker
                _record(out, results, RowResult(r.row, FAILED, 0.0, (), r.error), progress_bar)
            jobs = [r for r in todo if r.job is not None]
            if jobs:
                if not spec.trained:
                    progress_bar.note(f"note: model '{spec.name}' has random weights; results will be noise.")
                with connect(options.address) as ray, _sigterm_kept():
                    _run_rows(ray, jobs, out, options, results, progress_bar)
        finally:
            progress_bar.close()
            if results:
                write_results(out, results)
    done = sum(r.row in results and is_finished(results[r.row], out) for r in rows)
    failed = sum(results[r.row].status == FAILED for r in rows if r.row in results)
    return BatchSummary(len(rows), done, failed, len(todo), out / "results.csv")


def _wanted(row: ManifestRow, result: RowResult | None, out: Path, options: BatchOptions) -> bool:
    if options.rows is not None:
        return row.row in options.rows
    if result is not None and result.status == FAILED:
        return options.retry_failed
    return not is_finished(result, out)


def _record(out: Path, results: dict[int, RowResult], result: RowResult, progress_bar: Progress) -> None:
    append_result(out, result)
    results[result.row] = result
    progress_bar.finished(result)


def _run_rows(ray, rows: list[ManifestRow], out: Path, options: BatchOptions, results: dict[int, RowResult],
              progress_bar: Progress) -> None:
    count, demand, device, threads = _worker_plan(ray, options, len(rows))
    worker_class = ray.remote(RowWorker).options(**demand)

    def start_worker():
        return worker_class.remote(options.model, device, options.precision, threads)

    idle = [start_worker() for _ in range(count)]
    progress_bar.workers = count
    pending, running = deque(rows), {}
    try:
        while pending or running:
            while idle and pending:  # each worker holds one row at a time
                worker, row = idle.pop(), pending.popleft()
                running[worker.run.remote(row.row, row.job, str(out))] = (worker, row.row)
            ready, _ = ray.wait(list(running), num_returns=1, timeout=POLL_S)
            for ref in ready:
                worker, row = running.pop(ref)
                result, alive = _outcome(ray, ref, row)
                if not alive:
                    ray.kill(worker)
                    worker = start_worker()
                _record(out, results, result, progress_bar)
                idle.append(worker)
    finally:
        for worker in idle + [worker for worker, _ in running.values()]:
            ray.kill(worker)


def _outcome(ray, ref, row: int) -> tuple[RowResult, bool]:
    """A finished call's RowResult, and whether its worker is still alive."""
    from ray.exceptions import RayActorError, RayTaskError

    try:
        return ray.get(ref), True
    except RayTaskError as exc:
        if isinstance(exc.cause, InputError):  # the model cannot load: every row would fail
            raise InputError(str(exc.cause)) from None
        return RowResult(row, FAILED, 0.0, (), f"Unexpected {type(exc.cause).__name__} in the worker; "
                                               "please report it with this row."), True
    except RayActorError as exc:  # the worker's process died: out of memory, a lost node
        reason = " ".join(str(exc).split())[:160]
        return RowResult(row, FAILED, 0.0, (), f"The worker running this row stopped ({reason}); run it again "
                                               f"with --rows {row}."), False
