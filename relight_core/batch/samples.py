"""Dataset runs on the engine: `render-data` (a scene a unit, plain Ray tasks) and `autolabel` (a video a
unit, actors holding one model) write one sample folder per unit into OUT/SPLIT/, in the dataset
format of relight_core/data/dataset.py.

What they share here: one run at a time per split folder; finished samples (their `meta.json`
exists) skipped; progress; each failure reported with its sentence on stderr and appended to
OUT/SPLIT/failed.csv (`item,error`) as it happens; the split's manifest.json rewritten at the end.
A failed unit leaves no sample folder and is run again by the next run, which starts a fresh
failed.csv.
"""

from __future__ import annotations

import csv
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from relight_core.batch.engine import DONE, FAILED, UnitResult, run_units
from relight_core.batch.progress import Progress

FAILED_FILE = "failed.csv"


@dataclass(frozen=True)
class Sample:
    """One unit of a dataset run: the sample folder it writes and how it is named to the user."""

    folder: Path        # OUT/SPLIT/<name>
    item: str           # scene_000003, clip.mp4: in progress lines and failed.csv
    args: tuple = ()    # what the unit's function or worker is given
    error: str = ""     # set: the unit fails with this sentence without reaching a worker


@dataclass(frozen=True)
class DataSummary:
    """What a dataset run leaves: counts over the whole split, the manifest, and the failures."""

    total: int
    done: int
    failed: int
    ran: int                          # units run (or failed before reaching a worker) by this call
    manifest: Path
    failures: dict[str, str] = field(default_factory=dict)  # item → sentence, this run's
    seconds: float = 0.0              # wall seconds of the units' part of the run (start-up included)
    cpu_seconds: float = 0.0          # CPU seconds the units' workers report

    @property
    def failed_file(self) -> Path:
        return self.manifest.parent / FAILED_FILE


def remove_partial(folder: Path) -> None:
    """Remove what a failed unit left of its sample folder (never a finished sample)."""
    from relight_core.data.dataset import is_finished

    if folder.is_dir() and not is_finished(folder):
        shutil.rmtree(folder, ignore_errors=True)


def run_samples(split_dir: Path, total: int, todo: Sequence[Sample], ray, count: int,
                start_worker: Callable[[], Any] | None, call: Callable[[Any, Sample], Any], noun: str,
                desc: str, progress: bool = True, notes: Sequence[str] = (),
                deadline: float | None = None) -> DataSummary:
    """Run the unfinished samples `todo` (of `total` in the split) on `count` workers (see
    engine.run_units; none starts after the `time.monotonic()` `deadline`), report and record each
    failure, and rewrite the split's manifest."""
    from relight_core.data.dataset import write_manifest

    failed_file = split_dir / FAILED_FILE
    failed_file.unlink(missing_ok=True)  # this run retries every failure of the last one
    bar = Progress(total, total - len(todo), 0, len(todo), unit=noun, desc=desc, enabled=progress)
    bar.workers = count
    for text in notes:
        bar.note(text)
    failures: dict[str, str] = {}
    cpu, ran = [0.0], [0]

    def finish(sample: Sample, result: UnitResult) -> None:
        ran[0] += 1
        if result.status == FAILED:
            remove_partial(sample.folder)
            failures[sample.item] = result.error
            _append_failure(failed_file, sample.item, result.error)
        cpu[0] += result.cpu_seconds
        bar.finished(sample.item, result)

    started = time.perf_counter()
    try:
        for sample in [s for s in todo if s.error]:
            finish(sample, UnitResult(sample.item, FAILED, 0.0, sample.error))
        runnable = [s for s in todo if not s.error]
        if runnable:
            run_units(ray, runnable, count, start_worker, call, finish,
                      failed=lambda sample, text: UnitResult(sample.item, FAILED, 0.0, text),
                      noun=noun, retry=lambda sample: "run the command again to retry it", deadline=deadline)
    finally:
        bar.close()
        manifest = write_manifest(split_dir)
    return DataSummary(total, bar.done, len(failures), ran[0], manifest, failures,
                       time.perf_counter() - started, cpu[0])


def _append_failure(path: Path, item: str, error: str) -> None:
    fresh = not path.exists()
    with open(path, "a", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        if fresh:
            writer.writerow(("item", "error"))
        writer.writerow((item, error))
        f.flush()
        os.fsync(f.fileno())


def report(summary: DataSummary, noun: str) -> int:
    """Print a dataset run's outcome (the manifest on stdout, counts on stderr); the exit code: 0 when
    every unit is done, 1 when some failed."""
    import sys

    print(summary.manifest)
    plural = f"{noun}s" if summary.total != 1 else noun
    print(f"{summary.done} of {summary.total} {plural} done, {summary.failed} failed.", file=sys.stderr)
    if summary.failures:
        n = len(summary.failures)
        print(f"error: {n} {noun}{'s' * (n != 1)} failed; {'their reasons are' if n != 1 else 'its reason is'} "
              f"in {summary.failed_file} (a re-run retries {'them' if n != 1 else 'it'}).", file=sys.stderr)
        return 1
    return 0


__all__ = ["DONE", "FAILED", "DataSummary", "Sample", "remove_partial", "report", "run_samples"]
