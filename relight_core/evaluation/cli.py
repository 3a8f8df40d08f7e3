"""The `evaluate` subcommand."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from relight_core.arguments import MAX_ENSEMBLE, PRECISIONS, int_at_least, int_range
from relight_core.data.cli import positive_int


def _steps_list(text: str) -> tuple[int, ...]:
    """"5,10,20,35" → (5, 10, 20, 35)."""
    try:
        values = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of step counts; write e.g. 5,10,20,35.") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"'{text}' must list step counts of at least 1, e.g. 5,10,20,35.")
    return values


_count = int_at_least(0)  # argparse type: a whole number ≥ 0


def add_evaluation_commands(subparsers) -> None:
    """Register `evaluate` on an argparse subparsers object (sets `func`)."""
    p = subparsers.add_parser("evaluate", help="measure a model on a rendered dataset (PSNR/SSIM, floor, "
                                               "ceiling, train reproduction, probe margin, σ sweep)")
    p.add_argument("--data", required=True, type=Path, help="dataset root written by render-data")
    p.add_argument("--split", default="test", help="split to measure (default: test)")
    p.add_argument("--model", default="default", help="'default', a preset or a model folder")
    p.add_argument("--steps", type=positive_int, default=None, help="sampling steps (default: the model's)")
    p.add_argument("--sampler", default=None, help="res2ab, euler or heun (default: the model's)")
    p.add_argument("--guidance", type=float, default=0.0, help="classifier-free guidance on the lighting")
    p.add_argument("--limit", type=positive_int, default=None, help="only the first K items of the split")
    p.add_argument("--train-items", type=_count, default=4, help="train-split items for train-set reproduction")
    p.add_argument("--sigma-items", type=_count, default=2, help="items per split for the per-σ denoiser error")
    p.add_argument("--sigma-steps", type=positive_int, default=None,
                   help="steps of the Karras σ schedule it sweeps (default: --steps, at least 20)")
    p.add_argument("--steps-list", type=_steps_list, default=(), metavar="N,N,...",
                   help="also sample with these step counts, e.g. 5,10,20,35 (steps-vs-quality table)")
    p.add_argument("--size", type=positive_int, default=None,
                   help="measure at this long side (default: the model's size); the model runs at its "
                        "size and results come back by guided ratio upsampling, as in the CLI and studio")
    p.add_argument("--eval-size", type=positive_int, default=None,
                   help="also measure full-resolution output at this long side: plain resize vs guided ratio")
    p.add_argument("--no-margin", action="store_true", help="skip the probe-following margin (one run per item)")
    p.add_argument("--follow-scenes", type=_count, default=0, metavar="N",
                   help="also render N held-out test scenes under the sunset probe turned to 4 yaws and score "
                        "how the results follow it and how much shading the albedo keeps (light_follow.py; "
                        "needs Mitsuba, ~15 s a scene at 128 px)")
    p.add_argument("--no-grids", action="store_true", help="write no image grids")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ensemble", type=int_range(1, MAX_ENSEMBLE, "ensemble"), default=None,
                   help="samples averaged into each result (default: the model's)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--precision", choices=PRECISIONS, default=None, help="compute precision (default: the model's)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: evaluations/<model>-<split>)")
    p.set_defaults(func=_evaluate)


def _evaluate(args) -> int:
    from relight_core.evaluation.harness import RunOptions
    from relight_core.evaluation.runner import EvalConfig, run_evaluation

    out = args.out or Path("evaluations") / f"{Path(str(args.model)).name}-{args.split}"
    config = EvalConfig(
        data=args.data, out=out, split=args.split, model=args.model, limit=args.limit,
        train_items=args.train_items, sigma_items=args.sigma_items, sigma_steps=args.sigma_steps,
        steps_list=args.steps_list,
        size=args.size, eval_size=args.eval_size, margin=not args.no_margin, follow_scenes=args.follow_scenes,
        grids=not args.no_grids, device=args.device,
        precision=args.precision,
        run=RunOptions(steps=args.steps, sampler=args.sampler, guidance=args.guidance, seed=args.seed,
                       ensemble=args.ensemble),
        command="python -m relight_core " + shlex.join(sys.argv[1:]) if sys.argv[1:2] == ["evaluate"] else "")
    results = run_evaluation(config)
    test = results["test"]
    print(f"relit {test['model']['relit']['psnr']:.2f} dB / {test['model']['relit']['ssim']:.3f} "
          f"(floor {test['floor']['relit']['psnr']:.2f}, ceiling {test['ceiling']['relit']['psnr']:.2f}), "
          f"albedo {test['model']['albedo']['psnr']:.2f} dB / {test['model']['albedo']['ssim']:.3f}"
          + (f", margin {test['margin']:+.2f} dB" if test.get("margin") is not None else ""))
    print(out / "metrics.md")
    return 0
