"""Command-line plumbing shared by `python -m relight_core` and `app.py`.

* `OneLineParser`: argparse errors as one line on stderr and exit code 2 (no usage block).
* Checked argument types: seeds (0 … 2⁶³−1), finite numbers within a range, whole numbers
  within a range; each refuses a bad value with one sentence.
* `terminate_as_interrupt()`: SIGTERM (e.g. from `timeout` or `kill`) handled like Ctrl+C, so
  `finally` blocks run and temporary files are removed.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import threading

MAX_SEED = 2**63 - 1
MAX_ROTATION_DEG = 3600.0  # ten turns: a yaw or sweep end beyond this is a typo, not a light setting
MAX_INTENSITY = 1e6
MAX_SEEDS = 256  # seeds in one list: one result each
MAX_ENSEMBLE = 16  # samples averaged into one result, at most (ModelSpec.ensemble, RelightRequest.ensemble)
SHIFT_AVERAGES = (1, 2, 4)  # ModelSpec.shift_average: copies of a sample at half-token shifts (Relighter._members)
PRECISIONS = ("auto", "fp32", "bf16", "fp16")  # compute precisions (precision.py); here so parsers need no torch


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, `error: ...`, and exit code 2."""

    def error(self, message: str):
        message = " ".join(str(message).split()).rstrip(".")
        self.exit(2, f"error: {message} (see '{self.prog} --help').\n")


def seed(text: str) -> int:
    """argparse type: a seed, a whole number from 0 to 2⁶³−1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a seed; use a whole number from 0 to {MAX_SEED}.") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"the seed {text} is out of range; use a whole number from 0 to {MAX_SEED}.")
    return value


def seed_list(text: str) -> list[int]:
    """argparse type: "0-7" → [0..7]; "1,5,9" → [1,5,9]; "3" → [3]. Seeds are 0 … 2⁶³−1, at most 256."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part[1:]:
                lo_text, hi_text = part.rsplit("-", 1)
                lo, hi = int(lo_text), int(hi_text)
                if hi < lo:
                    raise argparse.ArgumentTypeError(
                        f"the seed range '{part}' is reversed; write the smaller seed first, e.g. {hi}-{lo}.")
                if hi - lo + 1 > MAX_SEEDS - len(seeds):  # checked before the range is expanded
                    raise argparse.ArgumentTypeError(
                        f"'{text}' names more than {MAX_SEEDS} seeds; give between 1 and {MAX_SEEDS}, e.g. 0-7.")
                seeds.extend(range(lo, hi + 1))
            else:
                seeds.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a seed list; write e.g. 0-7 or 1,5,9.") from None
    if not seeds or len(seeds) > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"Give between 1 and {MAX_SEEDS} seeds, e.g. 0-7.")
    outside = [s for s in seeds if not 0 <= s <= MAX_SEED]
    if outside:
        raise argparse.ArgumentTypeError(f"the seed {outside[0]} is out of range; seeds are whole numbers "
                                         f"from 0 to {MAX_SEED}.")
    return seeds


def row_list(text: str) -> set[int]:
    """argparse type: "3", "1,4", "2-5" → row numbers (from 1), e.g. for `batch --rows`."""
    rows: set[int] = set()
    try:
        for part in text.split(","):
            low, _, high = part.strip().partition("-")
            first, last = int(low), int(high or low)
            if first < 1 or last < first or last - first > 10**6:
                raise ValueError
            rows.update(range(first, last + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of rows; write e.g. 3 or 1,4 or 2-5 "
                                         "(rows count from 1 under the header).") from None
    return rows


def finite_float(low: float, high: float, *, low_open: bool = False, what: str = "value"):
    """argparse type: a finite number in [low, high] (or (low, high] when `low_open`)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number.") from None
        too_low = value <= low if low_open else value < low
        if not math.isfinite(value) or too_low or value > high:
            bound = f"above {_num(low)} and at most" if low_open else f"from {_num(low)} to"
            raise argparse.ArgumentTypeError(f"the {what} {text} is out of range; use a finite number {bound} "
                                             f"{_num(high)}.")
        return value

    parse.__name__ = what  # argparse names the type in some messages
    return parse


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else f"{x:g}"


def int_range(low: int, high: int, what: str = "value"):
    """argparse type: a whole number in [low, high]."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number.") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"the {what} {text} is out of range; use {low} to {high}.")
        return value

    parse.__name__ = what
    return parse


def int_at_least(minimum: int):
    """argparse type: a whole number ≥ `minimum`, or one sentence saying what is wrong."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number.") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"'{text}' must be at least {minimum}.")
        return value

    parse.__name__ = f"whole number ≥ {minimum}"
    return parse


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl+C's KeyboardInterrupt so that cleanup runs."""

    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def terminate_as_interrupt():
    """Within the block, SIGTERM raises `Terminated` (a KeyboardInterrupt) in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
