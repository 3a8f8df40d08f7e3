"""Fit a residual model's offset gains (`ModelSpec.residual_gain`) and offset filter radii
(`ModelSpec.offset_filter`) on items and write them into its config.json.

A residual model (`ModelSpec.residual`) predicts relit − input and albedo − input. Trained briefly,
its offsets point the right way but overshoot: the shipped CPU-trained model scored below the
input-copy floor at gain 1 and above it at gain ½ (docs/QUALITY.md). The gain of each clip is chosen
here on **training** items — never on the items it is then reported on — by the evaluation protocol's
PSNR (per-channel scale fit on the foreground mask, `evaluation.metrics`), among a grid that starts
at 0 (the input returned unchanged). Sampling runs through `Relighter` as users run it.

Train items flatter the model (it follows the probe better on scenes it was trained on), so the gain
they pick can overshoot on new scenes. `--split test --skip 16` instead chooses it on held-out scenes
(probes, meshes and textures training never sees) after the first 16 items, which `evaluate --limit 16`
reports on and which the choice therefore never sees.

Each gain's outputs are also scored after the edge-aware smoothing of their offset
(`upsample.smooth_offset`, guided by the input) at each radius of `RADII` (0 = none): a post-process
on the same run, so the radii cost no extra sampling. Relit and albedo each get the (gain, radius)
pair with the highest mean PSNR. `--size` scores at another size than the model's (its data's, for a
model trained smaller): the filter still works at the model's size, as in `Relighter`, and the results
come back by guided ratio upsampling, as in the CLI and the studio.

    python -m relight_core.training.calibrate --model DIR --data ~/.cache/unirelight-studio/data --items 48
    python -m relight_core.training.calibrate ... --write     # also store the gains in DIR/config.json
    python -m relight_core.training.calibrate ... --split test --skip 16 --items 48   # held-out scenes

`--strengths` instead fits the model's refiners (refiner.py): each one's `strength`, the factor on its
corrections, from `STRENGTHS` (the gains and filter stay as they are). A refiner trained on the
training scenes' DiT outputs can correct too hard on new scenes, as the offsets could (docs/QUALITY.md,
2026-12-06); each clip's result comes from one refiner, so one run per strength, with every refiner at
it, scores each refiner on the clips it supplies.

    python -m relight_core.training.calibrate ... --split test --skip 16 --items 48 --strengths --write
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

# Past 1: a best gain of 1 is then a peak, not the grid's edge. Finer between 0.75 and 1.1, where every
# model so far peaked (a 0.25 step there left up to ~0.1 dB on the table, docs/QUALITY.md).
GRID = (0.0, 0.25, 0.375, 0.5, 0.625, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25)
RADII = (0, 2, 3, 4, 6, 8, 12, 16)  # offset filter radii (px at the model's size); 0 = the model's output as it is
STRENGTHS = (0.0, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0, 1.1)  # refiner strengths; 0 = the refiner off
STRENGTH_MIN_GAIN = 0.02   # dB over strength 1 a strength must gain to replace it (less is the items' noise)


def measure_gains(relighter, items, grid=GRID, seed: int = 0, radii=RADII, eps: float | None = None
                  ) -> dict[tuple[float, int], dict[str, float]]:
    """{(gain, radius): {"relit": mean PSNR, "albedo": mean PSNR}}, both clips' gains set to `gain`
    and both offsets smoothed at `radius` (the model's own filter switched off while measuring), the
    filter's regularisation `eps` (default `upsample.GUIDE_EPS`, what `Relighter` uses)."""
    from relight_core.upsample import GUIDE_EPS

    eps = GUIDE_EPS if eps is None else eps
    table = measure_filters(relighter, items, grid, radii, (eps,), seed)
    return {(gain, radius): scores for (gain, radius, _), scores in table.items()}


def measure_filters(relighter, items, grid, radii, epsilons, seed: int = 0
                    ) -> dict[tuple[float, int, float], dict[str, float]]:
    """`measure_gains` at several filter regularisations: {(gain, radius, eps): {"relit", "albedo"}}.

    The relit and albedo outputs of one sampling run do not depend on each other's gain (the gain
    scales each clip's x0) nor on the filter (a post-process), so one run per gain measures every
    clip, radius and eps."""
    from relight_core.evaluation.harness import RunOptions, brought_back, model_size, relight
    from relight_core.evaluation.metrics import protocol_psnr
    from relight_core.upsample import smooth_offset

    spec = relighter.spec
    filters = [(radius, eps) for radius in radii for eps in epsilons]
    table = {}
    try:
        for gain in grid:
            relighter.spec = replace(spec, residual_gain=(gain, gain), offset_filter=(0, 0))
            scores = {f: ([], []) for f in filters}
            for item in items:
                small = model_size(relighter, item.input)   # the filter works at the model's size, as in Relighter
                relit, albedo, _ = relight(relighter, small, item.probe, RunOptions(seed=seed))
                for (radius, eps), (relit_psnr, albedo_psnr) in scores.items():
                    smooth = (brought_back(item.input, small, smooth_offset(small, relit, radius, eps)),
                              brought_back(item.input, small, smooth_offset(small, albedo, radius, eps)))
                    relit_psnr.append(protocol_psnr(smooth[0], item.target, item.mask))
                    albedo_psnr.append(protocol_psnr(smooth[1], item.albedo, item.mask))
            for (radius, eps), (relit_psnr, albedo_psnr) in scores.items():
                table[gain, radius, eps] = {"relit": float(np.mean(relit_psnr)), "albedo": float(np.mean(albedo_psnr))}
    finally:
        relighter.spec = spec
    return table


def refiner_owners(relighter) -> dict[str, list[str]]:
    """{slot: the clips whose result it supplies} for the model's refiners (`Relighter.clip_refiners`
    inverted: where both correct a clip, the relit refiner's result is the one used)."""
    owners = {}
    for clip, slot in relighter.clip_refiners().items():
        owners.setdefault(slot, []).append(clip)
    return owners


def measure_strengths(relighter, items, grid=STRENGTHS, seed: int = 0) -> dict[float, dict[str, float]]:
    """{strength: {"relit": mean PSNR, "albedo": mean PSNR}} with every refiner of the model at that
    strength (`RefinerConfig.strength`), the model's gains and filter as they are."""
    from relight_core.evaluation.harness import RunOptions, relight
    from relight_core.evaluation.metrics import protocol_psnr

    refiners = [r for r in (relighter.refiner, relighter.relit_refiner) if r is not None]
    configs = [r.config for r in refiners]
    table = {}
    try:
        for strength in grid:
            for refiner, config in zip(refiners, configs):
                refiner.config = replace(config, strength=float(strength))
            relit_psnr, albedo_psnr = [], []
            for item in items:
                relit, albedo, _ = relight(relighter, item.input, item.probe, RunOptions(seed=seed))
                relit_psnr.append(protocol_psnr(relit, item.target, item.mask))
                albedo_psnr.append(protocol_psnr(albedo, item.albedo, item.mask))
            table[strength] = {"relit": float(np.mean(relit_psnr)), "albedo": float(np.mean(albedo_psnr))}
    finally:
        for refiner, config in zip(refiners, configs):
            refiner.config = config
    return table


def best_strengths(table: dict[float, dict[str, float]], owners: dict[str, list[str]]) -> dict[str, float]:
    """{slot: the strength with the highest mean PSNR over the clips it supplies}; on a tie the one
    nearest 1 (the refiner as trained), and 1 itself unless the best gains `STRENGTH_MIN_GAIN` over it."""
    def score(strength, clips):
        return float(np.mean([table[strength][c] for c in clips]))

    best = {}
    for slot, clips in owners.items():
        top = max(sorted(table), key=lambda s: (round(score(s, clips), 6), -abs(s - 1)))
        keep = 1.0 in table and score(top, clips) - score(1.0, clips) < STRENGTH_MIN_GAIN
        best[slot] = 1.0 if keep else top
    return best


def best_gains(table: dict[tuple[float, int], dict[str, float]]) -> tuple[tuple[float, int], tuple[float, int]]:
    """((relit gain, radius), (albedo gain, radius)) with the highest mean PSNR each; on a tie the
    smaller gain and radius (the one that changes the model's output least)."""
    def best(clip):
        return max(sorted(table), key=lambda key: (round(table[key][clip], 6), -key[0], -key[1]))
    return best("relit"), best("albedo")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", required=True, help="a residual model folder")
    parser.add_argument("--data", type=Path, required=True, help="render-data output (its train split is used)")
    parser.add_argument("--split", default="train")
    parser.add_argument("--items", type=int, default=48,
                        help="items spread over the split (16 proved too few to choose a gain)")
    parser.add_argument("--skip", type=int, default=0,
                        help="leave out the split's first items: with --split test --skip 16 the gain is "
                             "chosen on held-out scenes that `evaluate --limit 16` never reports")
    parser.add_argument("--size", type=int, default=None,
                        help="score at this long side (default: the model's size); results come back to it "
                             "by guided ratio upsampling, as in the CLI and studio")
    parser.add_argument("--strengths", action="store_true",
                        help="fit the refiners' strengths instead of the gains and filter")
    parser.add_argument("--write", action="store_true", help="store the gains in the model's config.json")
    args = parser.parse_args(argv)
    if args.skip < 0:
        parser.error(f"--skip takes a count of items, 0 or more, not {args.skip}.")

    from relight_core.checkpoint import CONFIG_FILE, resolve_model
    from relight_core.errors import InputError
    from relight_core.evaluation.harness import load_items, resized
    from relight_core.pipeline import Relighter

    try:
        spec, weights = resolve_model(args.model)
        if not spec.residual:
            raise InputError(f"{args.model} is not a residual model; only its offsets can be calibrated.")
        relighter = Relighter.load(args.model)
        if args.size is not None and args.size < 8:
            raise InputError(f"--size takes a long side in pixels, 8 or more, not {args.size}.")
        items = [resized(item, args.size or relighter.spec.size, relighter.frame_multiple)
                 for item in load_items(args.data, args.split, args.items, spread=True, skip=args.skip)]
        if args.strengths and not refiner_owners(relighter):
            raise InputError(f"{args.model} has no refiner; --strengths fits refiners' strengths.")
    except InputError as exc:
        parser.exit(2, f"error: {exc}\n")
    after = f" (after its first {args.skip})" if args.skip else ""
    if args.strengths:
        return write_strengths(args, weights, items, relighter, after)
    if refiner_owners(relighter):
        print(f"note: {args.model} has refiners, made for the frames of its own gains and filter; this table "
              "runs them on others, so keep those and fit the refiners' strengths (--strengths) instead.")
    table = measure_gains(relighter, items)
    gains, radii = sorted({g for g, _ in table}), sorted({r for _, r in table})
    for clip in ("relit", "albedo"):
        print(f"{len(items)} {args.split} items{after}, {clip} PSNR (dB) by offset gain (rows) "
              f"and offset filter radius (columns):")
        print("  gain   " + "".join(f"  r={r:<5d}" for r in radii))
        for gain in gains:
            print(f"  {gain:5.3f}  " + "".join(f"  {table[gain, r][clip]:7.2f}" for r in radii)
                  + ("   (gain 0, radius 0: the input unchanged)" if gain == 0 else ""))
    (relit_gain, relit_radius), (albedo_gain, albedo_radius) = best_gains(table)
    print(f"best: relit gain {relit_gain} radius {relit_radius}, albedo gain {albedo_gain} radius {albedo_radius}")
    if args.write:
        config = Path(weights) / CONFIG_FILE if weights is not None else None
        if config is None or not config.is_file():
            parser.exit(2, f"error: {args.model} has no config.json to write the gains into.\n")
        data = json.loads(config.read_text())
        data["residual_gain"] = [relit_gain, albedo_gain]
        data["offset_filter"] = [relit_radius, albedo_radius]
        data.setdefault("notes", {})["calibration"] = {
            "split": args.split, "items": len(items), "skipped": args.skip,
            "size": int(max(items[0].input.shape[1:3])),
            "metric": "protocol PSNR (scale fit, foreground)",
            "table": {str(g): {str(r): {k: round(v, 3) for k, v in table[g, r].items()} for r in radii}
                      for g in gains}}
        config.write_text(json.dumps(data, indent=2) + "\n")
        print(f"wrote residual_gain {data['residual_gain']} and offset_filter {data['offset_filter']} into {config}")
    return 0


def write_strengths(args, weights, items, relighter, after: str) -> int:
    """`main` with --strengths: the table, the best strength of each refiner, and with --write the
    strengths stored in its config.json entry."""
    from relight_core.checkpoint import CONFIG_FILE

    owners = refiner_owners(relighter)
    table = measure_strengths(relighter, items)
    print(f"{len(items)} {args.split} items{after}, PSNR (dB) by refiner strength (0: no refiner):")
    print("  strength   relit    albedo")
    for strength in sorted(table):
        print(f"  {strength:8.3f}  {table[strength]['relit']:7.3f}  {table[strength]['albedo']:7.3f}")
    best = best_strengths(table, owners)
    print("best: " + ", ".join(f"{slot} ({'/'.join(owners[slot])}) strength {s}" for slot, s in best.items()))
    if args.write:
        config = Path(weights) / CONFIG_FILE if weights is not None else None
        if config is None or not config.is_file():
            print(f"error: {args.model} has no config.json to write the strengths into.", file=sys.stderr)
            return 2
        data = json.loads(config.read_text())
        for slot, strength in best.items():
            if strength == 1.0:
                data[slot].pop("strength", None)    # as trained: the config reads as it did before
            else:
                data[slot]["strength"] = strength
        data.setdefault("notes", {})["strength_calibration"] = {
            "split": args.split, "items": len(items), "skipped": args.skip,
            "size": int(max(items[0].input.shape[1:3])), "owners": owners,
            "metric": "protocol PSNR (scale fit, foreground)",
            "table": {str(s): {k: round(v, 3) for k, v in table[s].items()} for s in sorted(table)}}
        config.write_text(json.dumps(data, indent=2) + "\n")
        print("wrote " + ", ".join(f"{slot} strength {s}" for slot, s in best.items()) + f" into {config}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
