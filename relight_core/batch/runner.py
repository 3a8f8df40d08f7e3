"""Batch relighting on Ray: manifest rows spread over worker actors that each hold one model.

* Ray: a local instance when no address is given, else the cluster at `address` (`ray start --head`).
* Workers: actors that load the model once and run rows one at a time. A GPU worker declares
  `gpus_per_worker` GPUs; a CPU worker declares `cpus_per_worker` CPUs and runs torch on as many threads.
* Each row writes into OUT/<row>/ through a hidden staging folder renamed into place, so a row folder
  is whole or absent; its result is appended to OUT/results.csv as it finishes (manifest.py).
* A bad row fails alone with its one-sentence reason; a worker that dies fails the row it held and is
  replaced. A model that cannot load stops the batch with its sentence (every row would fail).

Connecting, the worker plan, the loop and the progress bar are the engine's (engine.py, progress.py),
which `render-data` and `autolabel` (relight_core/data/) run on too.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from relight_core.batch.engine import (ModelWorker, check_reachable, connect, locked, run_units, sentence,
                                       sigterm_kept, stop_if_interrupted, worker_plan)
from relight_core.batch.manifest import (DONE, FAILED, ManifestRow, RowResult, append_result, is_finished,
                                         read_manifest, read_results, write_results)
from relight_core.batch.progress import Progress
from relight_core.errors import InputError
from relight_core.jobs import MediaJob

__all__ = ["BatchOptions", "BatchSummary", "RowWorker", "connect", "run_batch"]


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

class RowWorker(ModelWorker):
    """A Ray actor: one model, loaded once, running manifest rows one at a time."""

    def run(self, row: int, job: MediaJob, out: str) -> RowResult:
        """Run one row into OUT/<row>/; every failure is this row's result, with one sentence."""
        from relight_core.jobs import load_inputs, plan_job, write_job

        self.check()
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
        except Exception as exc:  # a bad input, a full disk, a bug: this row's result
            stop_if_interrupted(exc)
            return RowResult(row, FAILED, time.perf_counter() - started, (), sentence(exc, "row"))


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
        check_reachable(options.address)  # so is a cluster that is not there
    numbers = {r.row for r in rows}
    if options.rows is not None and not options.rows <= numbers:
        missing = min(options.rows - numbers)
        raise InputError(f"--rows names row {missing}, but the manifest has rows 1 to {len(rows)}.")
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    with locked(out):
        for stale in out.glob(".partial-*"):  # rows a killed run left half-written
            shutil.rmtree(stale, ignore_errors=True)
        results = read_results(out)
        todo = [r for r in rows if _wanted(r, results.get(r.row), out, options)]
        before = [r for n, r in results.items() if n not in {r.row for r in todo}]
        progress_bar = Progress(len(rows), sum(is_finished(r, out) for r in before),
                                sum(r.status == FAILED for r in before), len(todo), unit="row", desc="batch",
                                enabled=progress)
        try:
            for r in [r for r in todo if r.job is None]:  # a bad cell fails its row without a worker
                _record(out, results, RowResult(r.row, FAILED, 0.0, (), r.error), progress_bar)
            jobs = [r for r in todo if r.job is not None]
            if jobs:
                if not spec.trained:
                    progress_bar.note(f"note: model '{spec.name}' has random weights; results will be noise.")
                with connect(options.address) as ray, sigterm_kept():
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
    progress_bar.finished(f"row {result.row}", result)


def _run_rows(ray, rows: list[ManifestRow], out: Path, options: BatchOptions, results: dict[int, RowResult],
              progress_bar: Progress) -> None:
    plan = worker_plan(ray, len(rows), options.workers, options.device, options.cpus_per_worker,
                       options.gpus_per_worker)
    worker_class = ray.remote(RowWorker).options(**plan.demand)
    progress_bar.workers = plan.count
    run_units(ray, rows, plan.count,
              start_worker=lambda: worker_class.remote(options.model, plan.device, options.precision, plan.threads),
              call=lambda worker, row: worker.run.remote(row.row, row.job, str(out)),
              finish=lambda row, result: _record(out, results, result, progress_bar),
              failed=lambda row, text: RowResult(row.row, FAILED, 0.0, (), text),
              noun="row", retry=lambda row: f"run it again with --rows {row.row}")
