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
