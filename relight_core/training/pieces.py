"""Cut a pack into pieces that each fit one call to a GPU machine, keeping validation scenes out.

A GPU machine reached through a device tool takes ≤ 64 MiB a call (the repository's own files and the
initial weights included), so a few thousand scenes travel in several pieces (`p1.npz`, `p2.npz`,
…, each ≤ its `--pieces` size in MB), gathered again there with `fast --pack p1.npz p2.npz …`.
`--val N` keeps the last N scenes the `--seen` packs do not hold (the newest rendered, never trained
on) out of every piece, as `val.npz` for `fast --val-pack`; scenes a `--seen` pack holds go after
the unseen ones, so they fill only the room left. `--seen` takes the packs rounds before trained on
(their scene names are what count).

    python -m relight_core.training.pieces --pack cache/train.npz --seen cache/trained-on.npz \
        --val 128 --pieces 61 61 22 --out .dev/pieces
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from relight_core.training.pack import STREAMS, save_pack


def _write_subset(z, path: Path, indices: list[int]) -> float:
    """The pack `z`'s scenes `indices` (in that order) as a pack at `path`; its size in MB."""
    offsets, jpeg, n = z["offsets"], z["jpeg"], len(STREAMS)
    blobs = [jpeg[offsets[n * i + k]:offsets[n * i + k + 1]] for i in indices for k in range(n)]
    save_pack(path, blobs, z["mask"][indices], z["env"][indices], tuple(z["size"]), int(z["lighting_size"]),
              z["names"][indices])
    return path.stat().st_size / 1e6


def pack_names(paths: list[Path]) -> set[str]:
    """The scene names the packs at `paths` hold (what `--seen` compares by)."""
    return {str(n) for path in paths for n in np.load(path, allow_pickle=False)["names"]}


def cut_pack(pack: Path, out: Path, pieces_mb: list[float], seen: Path | list[Path] | None = None,
             val: int = 0) -> dict:
    """Write `out/val.npz` (if `val`) and `out/p<i>.npz`, each at most `pieces_mb[i-1]` MB; returns the
    scene counts ({"val": n, "p1": n, …, "left": n not placed})."""
    out.mkdir(parents=True, exist_ok=True)
    with np.load(pack, allow_pickle=False) as z:
        z = {k: z[k] for k in z.files}
    names = [str(n) for n in z["names"]]
    seen = [] if seen is None else [seen] if isinstance(seen, (str, Path)) else list(seen)
    held = pack_names(seen)
    unseen = [i for i, name in enumerate(names) if name not in held]
    if val > len(unseen):
        raise ValueError(f"--val {val} asks for more scenes than the {len(unseen)} not in the --seen packs")
    kept = unseen[len(unseen) - val:] if val else []
    order = unseen[:len(unseen) - val] + [i for i, name in enumerate(names) if name in held]
    per_scene = Path(pack).stat().st_size / 1e6 / max(len(names), 1)   # the first guess at how many fit
    counts = {}
    if val:
        _write_subset(z, out / "val.npz", kept)
        counts["val"] = len(kept)
    start = 0
    for number, budget in enumerate(pieces_mb, 1):
        path, take = out / f"p{number}.npz", max(1, int(budget / per_scene))
        path.unlink(missing_ok=True)
        if start >= len(order):  # no piece without scenes: an empty pack would not load
            counts[f"p{number}"] = 0
            continue
        fit, written = 0, 0
        for _ in range(8):  # from the guess, towards the most scenes that fit
            size = _write_subset(z, path, order[start:start + take])
            written = take
            guess = int(take * budget / size * 0.995)
            if size <= budget:
                fit = take
                if guess <= take or start + take >= len(order):
                    break
                take = guess
            else:
                take = max(min(take - 1, guess), fit)
                if take == fit:
                    break
        if fit == 0:
            path.unlink()
            raise ValueError(f"a piece of {budget} MB cannot hold even one scene ({size:.2f} MB)")
        take = fit
        if written != fit:
            _write_subset(z, path, order[start:start + take])
        counts[f"p{number}"] = len(order[start:start + take])
        start += take
    counts["left"] = len(order) - min(start, len(order))
    return counts


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pack", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--pieces", type=float, nargs="+", required=True, help="each piece's largest size, MB")
    parser.add_argument("--seen", type=Path, nargs="+", default=[],
                        help="packs of scenes already trained on: those scenes go last, never in val")
    parser.add_argument("--val", type=int, default=0, help="scenes kept out as val.npz (the last unseen ones)")
    args = parser.parse_args(argv)
    for path in (args.pack, *args.seen):
        if not path.is_file():
            parser.error(f"no pack at {path}; make one with python -m relight_core.training.pack")
    try:
        counts = cut_pack(args.pack, args.out, args.pieces, args.seen, args.val)
    except ValueError as error:
        parser.error(str(error))
    print(" ".join(f"{k} {v}" for k, v in counts.items()))


if __name__ == "__main__":
    main()
