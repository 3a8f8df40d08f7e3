"""Fit a residual model's offset gains (`ModelSpec.residual_gain`) on training items and write them
into its config.json.

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

    python -m relight_core.training.calibrate --model DIR --data ~/.cache/unirelight-studio/data --items 48
    python -m relight_core.training.calibrate ... --write     # also store the gains in DIR/config.json
    python -m relight_core.training.calibrate ... --split test --skip 16 --items 48   # held-out scenes
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

GRID = (0.0, 0.25, 0.375, 0.5, 0.625, 0.75, 1.0)


def measure_gains(relighter, items, grid=GRID, seed: int = 0) -> dict[float, dict[str, float]]:
    """{gain: {"relit": mean PSNR, "albedo": mean PSNR}} with both clips' gains set to `gain`.

    The relit and albedo outputs of one sampling run do not depend on each other's gain (the gain
    scales each clip's x0), so one run per gain measures both curves."""
    from relight_core.evaluation.harness import RunOptions, relight
    from relight_core.evaluation.metrics import albedo_metrics, protocol_metrics

    spec = relighter.spec
    table = {}
    try:
        for gain in grid:
            relighter.spec = replace(spec, residual_gain=(gain, gain))
            relit_psnr, albedo_psnr = [], []
            for item in items:
                relit, albedo, _ = relight(relighter, item.input, item.probe, RunOptions(seed=seed))
                relit_psnr.append(protocol_metrics(relit, item.target, item.mask)["psnr"])
                albedo_psnr.append(albedo_metrics(albedo, item.albedo, item.mask)["psnr"])
            table[gain] = {"relit": float(np.mean(relit_psnr)), "albedo": float(np.mean(albedo_psnr))}
    finally:
        relighter.spec = spec
    return table


def best_gains(table: dict[float, dict[str, float]]) -> tuple[float, float]:
    """(relit gain, albedo gain) with the highest mean PSNR each."""
    return (max(table, key=lambda g: table[g]["relit"]), max(table, key=lambda g: table[g]["albedo"]))


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
        items = [resized(item, relighter.spec.size, relighter.frame_multiple)
                 for item in load_items(args.data, args.split, args.items, spread=True, skip=args.skip)]
    except InputError as exc:
        parser.exit(2, f"error: {exc}\n")
    table = measure_gains(relighter, items)
    after = f" (after its first {args.skip})" if args.skip else ""
    print(f"{len(items)} {args.split} items{after}, relit / albedo PSNR (dB) by offset gain:")
    for gain, row in table.items():
        print(f"  gain {gain:5.3f}: relit {row['relit']:6.2f}  albedo {row['albedo']:6.2f}"
              + ("   (the input unchanged)" if gain == 0 else ""))
    gains = best_gains(table)
    print(f"best: relit gain {gains[0]}, albedo gain {gains[1]}")
    if args.write:
        config = Path(weights) / CONFIG_FILE if weights is not None else None
        if config is None or not config.is_file():
            parser.exit(2, f"error: {args.model} has no config.json to write the gains into.\n")
        data = json.loads(config.read_text())
        data["residual_gain"] = list(gains)
        data.setdefault("notes", {})["calibration"] = {
            "split": args.split, "items": len(items), "skipped": args.skip,
            "metric": "protocol PSNR (scale fit, foreground)",
            "table": {str(g): {k: round(v, 3) for k, v in row.items()} for g, row in table.items()}}
        config.write_text(json.dumps(data, indent=2) + "\n")
        print(f"wrote residual_gain {list(gains)} into {config}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
