"""One evaluation run: load the model and items, measure everything, write the report as it goes."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from relight_core.errors import InputError
from relight_core.evaluation import light_follow, report
from relight_core.evaluation.harness import (
    EvalItem,
    RunOptions,
    load_items,
    mean_metrics,
    measure_full_resolution,
    measure_item,
    relight,
    resized,
    sigma_errors,
)
from relight_core.evaluation.metrics import albedo_metrics, protocol_metrics
from relight_core.pipeline import Relighter


@dataclass(frozen=True)
class EvalConfig:
    """What to measure and where to write it."""

    data: Path                          # dataset root (DATA/<split>/manifest.json)
    out: Path                           # metrics.json, metrics.md, grids/
    split: str = "test"
    model: str = "default"              # "default", a preset or a model folder
    limit: int | None = None            # first K items of the split (None: all)
    train_items: int = 4                # train-split items for train-set reproduction (0: none)
    sigma_items: int = 2                # items per split for the per-σ denoiser error (0: none)
    sigma_steps: int | None = None      # its σ schedule's steps (None: the run's steps, at least 20)
    steps_list: tuple[int, ...] = ()    # extra sampling-step counts for the steps-vs-quality table
    size: int | None = None             # measure at this long side (None: the model's working size)
    eval_size: int | None = None        # also measure full-resolution output at this long side
    margin: bool = True                 # the probe-following margin (one more model run per item)
    follow_scenes: int = 0              # held-out scenes rendered here under a turning sun (light_follow.py)
    grids: bool = True
    device: str | None = None
    precision: str | None = None        # None: the model's (normally auto)
    run: RunOptions = field(default_factory=RunOptions)
    command: str = ""                   # the command line, for the report


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _mean_sigma(per_item: list[list[dict]]) -> list[dict]:
    """Records of several items (aligned by σ) averaged per σ."""
    return [{key: float(np.mean([records[i][key] for records in per_item])) for key in per_item[0][i]}
            for i in range(len(per_item[0]))] if per_item else []


def _summary(records: list[dict]) -> dict:
    return {"items": len(records),
            "model": mean_metrics(records, "model"), "floor": mean_metrics(records, "floor"),
            "ceiling": mean_metrics(records, "ceiling"), "margin": mean_metrics(records, "margin"),
            "seconds_per_item": mean_metrics(records, "seconds"), "per_item": records}


def run_evaluation(config: EvalConfig, log: Callable[[str], None] = _log) -> dict:
    """Measure `config.model` on `config.data`; writes and returns the metrics (see report.py)."""
    started = time.perf_counter()
    relighter = Relighter.load(config.model, device=config.device, precision=config.precision)
    size, multiple = relighter.spec.size, relighter.frame_multiple
    if config.eval_size is not None and config.eval_size <= size:
        raise InputError(f"--eval-size {config.eval_size} must be larger than the model's working size "
                         f"({size} px): it measures bringing results up to a larger resolution.")
    options = replace(config.run, steps=config.run.steps or relighter.spec.steps,
                      sampler=config.run.sampler or relighter.spec.sampler)
    native = load_items(config.data, config.split, config.limit)
    if not native:
        raise InputError(f"No readable two-probe items in {config.data}/{config.split}; re-render the split.")
    measured = config.size or size  # another size: the model runs at its own, results come back guided
    test = [resized(item, measured, multiple) for item in native]
    train: list[EvalItem] = []
    train_note = None
    if config.train_items:
        try:
            train = [resized(item, measured, multiple)
                     for item in load_items(config.data, "train", config.train_items, spread=True)]
        except InputError as exc:
            train_note = str(exc)
    out = Path(config.out)
    (out / "grids").mkdir(parents=True, exist_ok=True)
    results = {
        "command": config.command,
        "model": {"name": relighter.spec.name, "source": str(config.model), "trained": relighter.spec.trained,
                  "size": size, "precision": getattr(relighter, "precision", None),
                  "tokenizer": relighter.spec.tokenizer, "steps": options.steps, "sampler": options.sampler,
                  "guidance": options.guidance, "seed": options.seed, "device": str(relighter.device)},
        "data": {"root": str(config.data), "split": config.split, "frames": int(test[0].input.shape[0]),
                 "native_size": list(native[0].input.shape[1:3]), "measured_size": list(test[0].input.shape[1:3])},
        "protocol": report.PROTOCOL,
    }
    log(f"evaluate: {relighter.spec.name} ({results['model']['precision']}, {options.steps} {options.sampler} "
        f"steps) on {len(test)} {config.split} + {len(train)} train items at {test[0].input.shape[2]}×"
        f"{test[0].input.shape[1]}")

    sets = {}
    outputs_by_item: dict[str, tuple[np.ndarray, dict]] = {}
    for split_name, items, with_margin in (("test", test, config.margin), ("train", train, False)):
        records = []
        for k, item in enumerate(items):
            metrics, outputs = measure_item(relighter, item, options, margin=with_margin)
            records.append(metrics)
            if split_name == "test":
                outputs_by_item[item.name] = (item.input, outputs)
            if config.grids:
                report.save_grid(out / "grids" / f"{split_name}_{k:03d}.png", item, outputs)
            log(f"  {split_name} [{k + 1}/{len(items)}] {item.name}: relit {metrics['model']['relit']['psnr']:.2f} dB "
                f"(floor {metrics['floor']['relit']['psnr']:.2f}, ceiling {metrics['ceiling']['relit']['psnr']:.2f}), "
                f"albedo {metrics['model']['albedo']['psnr']:.2f} dB "
                f"(ΔE2000 {metrics['model']['albedo']['delta_e2000']:.2f})"
                + (f", margin {metrics['margin']:+.2f} dB" if "margin" in metrics else "")
                + f", {metrics['seconds']:.1f} s")
        sets[split_name] = _summary(records)
    results["test"] = sets["test"]
    results["train"] = sets["train"] if train else {"items": 0, "note": train_note or "--train-items 0"}

    steps_rows = []
    for steps in sorted(set(config.steps_list)):
        if steps == options.steps:
            rows = [{"model": r["model"], "seconds": r["seconds"]} for r in results["test"]["per_item"]]
        else:
            rows = []
            for item in test:
                relit, albedo, seconds = relight(relighter, item.input, item.probe, replace(options, steps=steps))
                rows.append({"model": {"relit": protocol_metrics(relit, item.target, item.mask),
                                       "albedo": albedo_metrics(albedo, item.albedo, item.mask)},
                             "seconds": seconds})
        steps_rows.append({"steps": steps, **mean_metrics(rows, "model"),
                           "seconds_per_item": mean_metrics(rows, "seconds")})
        log(f"  steps {steps}: relit {steps_rows[-1]['relit']['psnr']:.2f} dB, albedo "
            f"{steps_rows[-1]['albedo']['psnr']:.2f} dB, {steps_rows[-1]['seconds_per_item']:.1f} s/item")
    results["steps"] = steps_rows

    sigma = {}
    sweep = replace(options, steps=config.sigma_steps or max(options.steps, 20))
    for split_name, items in (("test", test), ("train", train)):
        chosen = items[:config.sigma_items]
        with_light = [sigma_errors(relighter, item, sweep, lighting=True) for item in chosen]
        without = [sigma_errors(relighter, item, sweep, lighting=False) for item in chosen]
        rows = _mean_sigma(with_light)
        for row, dark in zip(rows, _mean_sigma(without)):
            row["relit_psnr_no_light"] = dark["relit_psnr"]
            row["relit_latent_mse_no_light"] = dark["relit_latent_mse"]
        sigma[split_name] = {"items": len(chosen), "steps": sweep.steps, "rows": rows}
        if chosen:
            log(f"  σ sweep on {len(chosen)} {split_name} items done")
    results["sigma"] = sigma

    if config.eval_size is not None:
        records = []
        for k, item in enumerate(native):
            metrics, outputs = measure_full_resolution(relighter, item, config.eval_size, options,
                                                       reuse=outputs_by_item.get(item.name))
            records.append(metrics)
            if config.grids:
                report.save_full_grid(out / "grids" / f"full_{k:03d}.png", outputs)
        results["full_resolution"] = {"size": config.eval_size, "items": len(records),
                                      "floor": mean_metrics(records, "floor"), "model": mean_metrics(records, "model"),
                                      "oracle": mean_metrics(records, "oracle"), "per_item": records}
        fr = results["full_resolution"]
        log(f"  full resolution {config.eval_size}: relit plain {fr['model']['relit']['plain']['psnr']:.2f} dB, "
            f"guided {fr['model']['relit']['guided']['psnr']:.2f} dB")
    if config.follow_scenes:
        results["light_follow"] = light_follow.measure(relighter, config.follow_scenes, options, measured, log=log)
        log(f"  light follow on {config.follow_scenes} scenes: follow "
            f"{results['light_follow']['summary']['follow']:.3f}, albedo shading "
            f"{results['light_follow']['summary']['albedo_shading']:.3f}")
    results["seconds"] = time.perf_counter() - started
    (out / "metrics.json").write_text(json.dumps(results, indent=1))
    (out / "metrics.md").write_text(report.markdown(results))
    return results

