"""A run's progress on stderr: units (rows, scenes, videos) done / failed / left and an ETA, as a bar or
one line a unit. Shared by `batch`, `render-data` and `autolabel`."""

from __future__ import annotations

import sys

from relight_core.batch.engine import DONE, FAILED


class Progress:
    """Units done / failed / left and an ETA: a progress bar on a terminal, one line a unit otherwise.

    `done` and `failed` count the units finished or failed before this run, `left` the units it runs;
    `finished(label, result)` takes each result (anything with `status`, `seconds`, `error`)."""

    def __init__(self, total: int, done: int, failed: int, left: int, unit: str = "row", desc: str = "batch",
                 enabled: bool = True):
        from tqdm import tqdm

        self.done, self.failed, self.left = done, failed, left
        self.workers, self.unit_seconds = 1, []
        self.enabled = enabled
        self.lines = enabled and not sys.stderr.isatty()
        self.bar = tqdm(total=left, desc=desc, unit=unit, file=sys.stderr,
                        disable=None if enabled else True, dynamic_ncols=True)
        self._postfix()
        if enabled:
            before = f", {failed} failed before" if failed else ""
            self.note(f"{total} {unit}{'s' * (total != 1)}: {done} done{before}, {left} to run.")

    def note(self, text: str) -> None:
        if self.enabled:
            self.bar.write(text, file=sys.stderr)

    def eta(self) -> float:
        """Seconds left: units still to run × a unit's mean time, shared by the workers (their start-up
        is not counted)."""
        mean = sum(self.unit_seconds) / len(self.unit_seconds) if self.unit_seconds else 0.0
        return mean * self.left / max(1, self.workers)

    def finished(self, label: str, result) -> None:
        self.left -= 1
        if result.seconds:  # run by a worker (units failed before they reached one take no time)
            self.unit_seconds.append(result.seconds)
        self.done += result.status == DONE
        self.failed += result.status == FAILED
        self.bar.update(1)
        self._postfix()
        if result.status == FAILED and not self.lines:
            self.note(f"{label} failed: {result.error}")
        elif self.lines:
            what = f"failed: {result.error}" if result.status == FAILED else f"done in {result.seconds:.1f} s"
            self.note(f"{label} {what} [{self.done} done, {self.failed} failed, {self.left} left, "
                      f"ETA {self.eta():.0f} s]")

    def _postfix(self) -> None:
        self.bar.set_postfix(done=self.done, failed=self.failed, left=self.left)

    def close(self) -> None:
        self.bar.close()
