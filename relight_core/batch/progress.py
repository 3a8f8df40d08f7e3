"""The batch's progress on stderr: rows done / failed / left and an ETA, as a bar or one line a row."""

from __future__ import annotations

import sys
from pathlib import Path

from relight_core.batch.manifest import DONE, FAILED, ManifestRow, RowResult, is_finished


class Progress:
    """Rows done / failed / left and an ETA: a progress bar on a terminal, one line a row otherwise."""

    def __init__(self, total: int, todo: list[ManifestRow], results: dict[int, RowResult], out: Path,
                 enabled: bool = True):
        from tqdm import tqdm

        todo_rows = {r.row for r in todo}
        self.done = sum(is_finished(r, out) for n, r in results.items() if n not in todo_rows)
        self.failed = sum(r.status == FAILED for n, r in results.items() if n not in todo_rows)
        self.left, self.workers, self.row_seconds = len(todo), 1, []
        self.enabled = enabled
        self.lines = enabled and not sys.stderr.isatty()
        self.bar = tqdm(total=len(todo), desc="batch", unit="row", file=sys.stderr,
                        disable=None if enabled else True, dynamic_ncols=True)
        self._postfix()
        if enabled:
            self.note(f"{total} row{'s' * (total != 1)}: {self.done} done, {self.failed} failed before, "
                      f"{self.left} to run.")

    def note(self, text: str) -> None:
        if self.enabled:
            self.bar.write(text, file=sys.stderr)

    def finished(self, result: RowResult) -> None:
        self.left -= 1
        if result.seconds:  # run by a worker (rows failed at parsing take no time)
            self.row_seconds.append(result.seconds)
        self.done += result.status == DONE
        self.failed += result.status == FAILED
        self.bar.update(1)
        self._postfix()
        if result.status == FAILED and not self.lines:
            self.note(f"row {result.row} failed: {result.error}")
        elif self.lines:
            # Rows still to run × a row's mean time, shared by the workers (their start-up is not counted).
            mean = sum(self.row_seconds) / len(self.row_seconds) if self.row_seconds else 0.0
            eta = mean * self.left / self.workers
            what = f"failed: {result.error}" if result.status == FAILED else f"done in {result.seconds:.1f} s"
            self.note(f"row {result.row} {what} [{self.done} done, {self.failed} failed, {self.left} left, "
                      f"ETA {eta:.0f} s]")

    def _postfix(self) -> None:
        self.bar.set_postfix(done=self.done, failed=self.failed, left=self.left)

    def close(self) -> None:
        self.bar.close()
