"""Plan the calls that carry a GPU round's files to a device machine, each within what one call may carry.

A device machine takes ≤ 64 MiB a call, the repository's working tree included, and keeps /tmp from one
call to the next while it stays warm (30 s after each). `plan_calls` places every file — given as
DEST=SOURCE, SOURCE a file or a folder whose files go under DEST/ — into call folders `c1`, `c2`, … of at
most `--limit` MB each (largest first, each into the first call with room), as hard links where the file
system allows (copies else), and writes `calls.md`: for each call, the folder to carry and the command that
copies it into `--machine-dir` (/tmp/gpu) there; the last call then runs `--run`.

    python -m relight_core.training.calls --out ~/.cache/unirelight-studio/gpu-calls --limit 58 \\
        packs=$C/gpu-pieces-s7 aux/model=models/default refit/refit.npz=$C/refit-s8/p1.npz \\
        --run "bash scripts/gpu_whole_round.sh 5.5 2"

At the GPU session: copy (or `cp -al`) the folder into the repository's `.dev/` (in .gitignore, so that
it travels only when carried), take the large tracked files out of the working tree as calls.md says, and make the calls
one after another.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

MB = 1e6
INVENTORY = "round-files.txt"      # in the last call's folder: "SIZE DEST" a line, every file of the round


def _items(specs: list[str]) -> list[tuple[str, Path]]:
    """(destination, source file) for every DEST=SOURCE (a folder: each file in it, DEST/its name)."""
    items: list[tuple[str, Path]] = []
    for spec in specs:
        dest, sep, source = spec.partition("=")
        if not sep or not dest or not source:
            raise ValueError(f"'{spec}' is not DEST=SOURCE (a path on the machine, relative to its folder, = a file "
                             "or folder here)")
        path = Path(source).expanduser()
        if path.is_dir():
            items += [(f"{dest.rstrip('/')}/{f.name}", f) for f in sorted(path.iterdir()) if f.is_file()]
        elif path.is_file():
            items.append((dest, path))
        else:
            raise ValueError(f"nothing at {path} (from '{spec}')")
    seen: set[str] = set()
    for dest, _ in items:
        if dest in seen or Path(dest).is_absolute() or ".." in Path(dest).parts:
            raise ValueError(f"'{dest}' is named twice, or is not a path inside the machine's folder")
        seen.add(dest)
    return items


def plan_calls(specs: list[str], out: Path, limit_mb: float, run: str = "", machine_dir: str = "/tmp/gpu",
               repo_dir: str = ".dev/calls") -> list[dict]:
    """Write the call folders and calls.md (see the module docstring); returns [{"folder", "files", "mb"}] per call."""
    items = _items(specs)
    sizes = {dest: path.stat().st_size / MB for dest, path in items}
    too_big = [dest for dest, size in sizes.items() if size > limit_mb]
    if too_big:
        raise ValueError(f"{too_big[0]} is {sizes[too_big[0]]:.1f} MB, more than one call's {limit_mb} MB: cut it "
                         "smaller first (training.pieces for a pack)")
    calls: list[dict] = []
    for dest, path in sorted(items, key=lambda item: (-sizes[item[0]], item[0])):
        call = next((c for c in calls if c["mb"] + sizes[dest] <= limit_mb), None)
        if call is None:
            call = {"files": [], "mb": 0.0}
            calls.append(call)
        call["files"].append((dest, path))
        call["mb"] += sizes[dest]
    if out.exists():
        if not (out / "calls.json").is_file() and any(out.iterdir()):
            raise ValueError(f"{out} holds files that are not an earlier plan (no calls.json); give a new or empty --out")
        shutil.rmtree(out)                     # an earlier plan: made again from scratch
    out.mkdir(parents=True)
    lines = [f"# {len(calls)} calls to the GPU machine (≤ {limit_mb} MB each, the working tree besides)", "",
             "Before the first: copy this folder to the repository's `.dev/calls` (`cp -al` keeps it to links) and "
             "take the large tracked files out of the working tree, which travels with every call: "
             "`git ls-files -z models '*.png' | xargs -0 rm` (after the last call: `git checkout -- .`). "
             "Make each call as soon as the one before returns: the machine stays warm 30 s.", ""]
    # the last call also carries the list of every file of the round with its size, so that the round can check that
    # the machine still holds what the calls before brought (a machine given back between calls loses /tmp)
    inventory = "".join(f"{path.stat().st_size} {dest}\n" for dest, path in sorted(items, key=lambda item: item[0]))
    for number, call in enumerate(calls, 1):
        folder = out / f"c{number}"
        if number == len(calls):
            folder.mkdir(parents=True, exist_ok=True)
            (folder / INVENTORY).write_text(inventory)
        for dest, path in call["files"]:
            target = folder / dest
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(path, target)
            except OSError:
                shutil.copyfile(path, target)
        command = f"mkdir -p {machine_dir} && cp -r {repo_dir}/c{number}/. {machine_dir}/ && du -sh {machine_dir}"
        if number == len(calls) and run:
            command += f" && {run}"
        lines += [f"{number}. carry `[\"{repo_dir}/c{number}\"]` ({call['mb']:.1f} MB: "
                  + ", ".join(dest for dest, _ in call["files"]) + ")", f"   `{command}`", ""]
        call["folder"] = str(folder)
        call["files"] = [dest for dest, _ in call["files"]]
        call["mb"] = round(call["mb"], 1)
    (out / "calls.md").write_text("\n".join(lines))
    (out / "calls.json").write_text(json.dumps(calls, indent=1))
    return calls


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("files", nargs="+", help="DEST=SOURCE: where on the machine (relative to --machine-dir) = a "
                                                 "file or folder here")
    parser.add_argument("--out", type=Path, required=True, help="where the call folders c1, c2, … and calls.md go")
    parser.add_argument("--limit", type=float, default=58.0, help="MB a call carries at most (default 58: 64 MiB less "
                                                                  "a working tree of ~6 MB)")
    parser.add_argument("--run", default="", help="the command the last call runs once everything is there")
    parser.add_argument("--machine-dir", default="/tmp/gpu")
    parser.add_argument("--repo-dir", default=".dev/calls", help="where the call folders will be in the repository")
    args = parser.parse_args(argv)
    if not args.limit > 0:
        parser.error("--limit takes a size in MB above 0")
    try:
        calls = plan_calls(args.files, args.out, args.limit, args.run, args.machine_dir, args.repo_dir)
    except (ValueError, OSError) as error:
        parser.error(str(error))
    print((args.out / "calls.md").read_text())
    print(f"{len(calls)} calls in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
