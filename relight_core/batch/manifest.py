"""The batch's two CSV files: the manifest it reads (one job a row) and the results it writes.

Manifest: a header, then one row per job. `input` is required; `mode`, `probe`, `rotation`,
`intensity`, `seeds`, `steps` and `size` are optional, and an empty cell takes the command
line's value. Relative paths are relative to the manifest's folder. Rows are numbered from 1 (the
first row under the header); row N writes into `OUT/N/`.

Results (`OUT/results.csv`): `row,status,seconds,outputs,error`, status `done` or `failed`,
outputs the files written (relative to OUT, `;`-separated), error the row's one-sentence reason.
A line is appended as each row finishes, so a crash loses nothing finished; the last line of a
row wins, and the file is rewritten with one line per row when a run ends.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

from relight_core.arguments import (MAX_INTENSITY, MAX_ROTATION_DEG, finite_float, int_at_least, int_range,
                                    seed_list)
from relight_core.errors import InputError
from relight_core.jobs import MediaJob
from relight_core.pipeline import MODES

COLUMNS = ("input", "mode", "probe", "rotation", "intensity", "seeds", "steps", "size")
RESULT_COLUMNS = ("row", "status", "seconds", "outputs", "error")
RESULTS_FILE = "results.csv"
DONE, FAILED = "done", "failed"
DEFAULT_SEEDS = {"random": tuple(range(8))}  # as `augment`; the other modes: seed 0

_PARSERS = {
    "rotation": finite_float(-MAX_ROTATION_DEG, MAX_ROTATION_DEG, what="rotation"),
    "intensity": finite_float(0.0, MAX_INTENSITY, low_open=True, what="intensity"),
    "seeds": lambda text: tuple(seed_list(text)),
    "steps": int_range(1, 1000, "number of steps"),
    "size": int_at_least(1),
}


@dataclass(frozen=True)
class ManifestRow:
    """One manifest row: its job, or the one sentence saying why it cannot run."""

    row: int
    job: MediaJob | None
    error: str = ""


@dataclass(frozen=True)
class RowResult:
    """One line of results.csv."""

    row: int
    status: str               # done | failed
    seconds: float = 0.0
    outputs: tuple[str, ...] = ()  # relative to the output folder
    error: str = ""


def read_manifest(path: Path, template: MediaJob, seeds: tuple[int, ...] | None = None) -> list[ManifestRow]:
    """Parse a manifest; `template` holds the command line's values for empty cells (`seeds`: None
    means the mode's default). A bad file raises InputError; a bad cell fails only its row."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"The manifest {path} does not exist; give a CSV file with an 'input' column.")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [name.strip().lower() for name in next(reader, [])]
            lines = [cells for cells in reader if any(cell.strip() for cell in cells)]
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"The manifest {path.name} is not a readable CSV file ({exc}); save it as UTF-8 CSV.") \
            from None
    unknown = [name for name in header if name not in COLUMNS]
    if "input" not in header or unknown:
        what = f"has an unknown column '{unknown[0]}'" if unknown else "has no 'input' column"
        raise InputError(f"The manifest {path.name} {what}; its header names columns from "
                         f"{', '.join(COLUMNS)} (input is required).")
    if len(set(header)) != len(header):
        raise InputError(f"The manifest {path.name} names a column twice in its header; name each column once.")
    if not lines:
        raise InputError(f"The manifest {path.name} has no rows under its header; add one row per input.")
    folder = path.resolve().parent
    rows = []
    for number, cells in enumerate(lines, start=1):
        if len(cells) > len(header):
            rows.append(ManifestRow(number, None, f"The row has {len(cells)} cells but the header names "
                                                  f"{len(header)} columns; quote cells that contain commas."))
            continue
        values = {name: cell.strip() for name, cell in zip(header, cells) if cell.strip()}
        try:
            rows.append(ManifestRow(number, _row_job(values, template, seeds, folder)))
        except InputError as exc:
            rows.append(ManifestRow(number, None, str(exc)))
    return rows


def _row_job(values: dict[str, str], template: MediaJob, seeds: tuple[int, ...] | None, folder: Path) -> MediaJob:
    if "input" not in values:
        raise InputError("The row has no input; fill its input cell with an image or video path.")
    mode = values.get("mode", template.mode).lower()
    if mode not in MODES:
        raise InputError(f"The mode '{values['mode']}' is not one of {', '.join(MODES)}; fix its mode cell.")
    parsed = {}
    for name, text in values.items():
        if name in _PARSERS:
            try:
                parsed[name] = _PARSERS[name](text)
            except argparse.ArgumentTypeError as exc:
                raise InputError(f"Its {name} cell is wrong: {exc}") from None
    probe = _path(values["probe"], folder) if "probe" in values else template.probe
    return dataclasses.replace(template, mode=mode, input=_path(values["input"], folder), probe=probe,
                               seeds=parsed.pop("seeds", None) or seeds or DEFAULT_SEEDS.get(mode, (0,)), **parsed)


def _path(text: str, folder: Path) -> Path:
    path = Path(text).expanduser()
    return path if path.is_absolute() else folder / path


# ---------------------------------------------------------------------------------------------
# results.csv
# ---------------------------------------------------------------------------------------------

def read_results(out: Path) -> dict[int, RowResult]:
    """The last result of each row in OUT/results.csv (empty when there is none); unreadable lines are skipped."""
    path = Path(out) / RESULTS_FILE
    if not path.is_file():
        return {}
    results = {}
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        for line in csv.DictReader(f):
            try:
                row, status = int(line["row"]), line["status"]
                seconds = float(line["seconds"] or 0)
            except (KeyError, TypeError, ValueError):
                continue  # a line torn by a crash, or edited by hand
            if status in (DONE, FAILED):
                outputs = tuple(p for p in (line.get("outputs") or "").split(";") if p)
                results[row] = RowResult(row, status, seconds, outputs, line.get("error") or "")
    return results


def is_finished(result: RowResult | None, out: Path) -> bool:
    """A row is finished when its last result is done and every file it names is still there."""
    return result is not None and result.status == DONE and all((Path(out) / p).is_file() for p in result.outputs)


def _line(result: RowResult) -> list[str]:
    return [str(result.row), result.status, f"{result.seconds:.2f}", ";".join(result.outputs), result.error]


def append_result(out: Path, result: RowResult) -> None:
    """Append one row's result to OUT/results.csv and force it to disk."""
    path = Path(out) / RESULTS_FILE
    fresh = not path.exists() or path.stat().st_size == 0
    torn = False
    if not fresh:  # a line torn by an earlier crash must not swallow this one
        with open(path, "rb") as f:
            f.seek(-1, os.SEEK_END)
            torn = f.read(1) != b"\n"
    with open(path, "a", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        if fresh:
            writer.writerow(RESULT_COLUMNS)
        elif torn:
            f.write("\n")
        writer.writerow(_line(result))
        f.flush()
        os.fsync(f.fileno())


def write_results(out: Path, results: dict[int, RowResult]) -> None:
    """Rewrite OUT/results.csv with one line per row, in row order (atomically)."""
    path = Path(out) / RESULTS_FILE
    partial = path.with_name(f".{RESULTS_FILE}.partial")
    with open(partial, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(RESULT_COLUMNS)
        writer.writerows(_line(results[row]) for row in sorted(results))
        f.flush()
        os.fsync(f.fileno())
    os.replace(partial, path)
