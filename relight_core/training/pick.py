"""Pick the model to keep from a round of runs, on held-out scenes.

Scores each run's model folder, the mean of their weights (when more than one) and that mean with
the weights they started from (`--init`) by one-step sampled relit + albedo PSNR on a validation
pack (`fast.sampled_quality`, as `fast --val-pack` scores its EMAs), and writes the best as ≤ 15 MB
shards + config.json in `--out` (what a GPU machine hands back; `fast.merge_shards` joins them), with
every score in `--out/pick.json`; `--model-dir` also writes it there as a model folder.

    python -m relight_core.training.pick --val val.npz --init models/default --out $OUT runs/a/model runs/b/model
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, load_model
from relight_core.devices import resolve_device
from relight_core.tokenizer import build_tokenizer
from relight_core.training.fast import sampled_quality, selection_score, write_shards
from relight_core.training.pack import load_pack


def candidates(models: list[Path], init: Path | None) -> dict[str, dict[str, torch.Tensor]]:
    """Name → fp32 state dict: each model, their mean (≥ 2 models), their mean with `init`, `init`."""
    states = {str(m): {k: v.float() for k, v in load_file(str(m / DIT_FILE)).items()} for m in models}
    names = list(states)

    def mean(parts: list[dict]) -> dict:
        return {k: sum(p[k] for p in parts) / len(parts) for k in parts[0]}

    if len(names) > 1:
        states["mean"] = mean([states[n] for n in names])
    if init is not None:
        start = {k: v.float() for k, v in load_file(str(init / DIT_FILE)).items()}
        states["mean with init"] = mean([states[n] for n in names] + [start])
        states["init"] = start
    return states


def pick(models: list[Path], val: Path, out: Path, init: Path | None = None, items: int = 128,
         device: str = "auto", model_dir: Path | None = None) -> dict:
    """Score the candidates on `val`, write the best to `out` (see the module docstring); returns
    {"best": name, "scores": {name: {relit, albedo, floor, margin}}}."""
    if not models:
        raise ValueError("no model folder to pick from")
    dev = resolve_device(None if device == "auto" else device)
    spec, dit, _ = load_model(models[0], dev)
    if spec.tokenizer.get("type") != "pixel":
        raise ValueError(f"{models[0]} is not a pixel-tokenizer model; pick scores the default model's kind")
    tokenizer = build_tokenizer(spec.tokenizer)
    pack = load_pack(val, dev)
    scores, states = {}, candidates(models, init)
    for name, state in states.items():
        dit.load_state_dict({k: v.to(dev) for k, v in state.items()})
        scores[name] = sampled_quality(dit.eval(), pack, tokenizer, items, spec.steps, dev.type == "cuda",
                                       spec.residual)
        print(name, scores[name], flush=True)
    best = max(scores, key=lambda n: (selection_score(scores[n]), n == "init"))
    state = {k: v.to(torch.bfloat16).contiguous() for k, v in states[best].items()}
    config = json.loads((models[0] / CONFIG_FILE).read_text())
    config.setdefault("notes", {})["picked"] = {"from": best, "val": scores[best], "val_items": min(items, len(pack["rgb"]))}
    out.mkdir(parents=True, exist_ok=True)
    (out / CONFIG_FILE).write_text(json.dumps(config, indent=2))
    write_shards(state, out)
    if model_dir is not None:
        model_dir.mkdir(parents=True, exist_ok=True)
        save_file(state, model_dir / DIT_FILE)
        (model_dir / CONFIG_FILE).write_text(json.dumps(config, indent=2))
    result = {"best": best, "scores": scores}
    (out / "pick.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("models", type=Path, nargs="+", help="model folders (a run's <out>/model)")
    parser.add_argument("--val", type=Path, required=True, help="the validation pack (fast --val-pack's)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--init", type=Path, help="the model folder the runs started from")
    parser.add_argument("--items", type=int, default=128)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--model-dir", type=Path, help="also write the pick here as a model folder")
    args = parser.parse_args(argv)
    present = [m for m in args.models if (m / DIT_FILE).is_file()]
    for missing in sorted(set(args.models) - set(present)):
        print(f"skipping {missing}: no {DIT_FILE} there (the run did not finish)")
    if not args.val.is_file():
        parser.error(f"no pack at {args.val}")
    if args.init is not None and not (args.init / DIT_FILE).is_file():
        parser.error(f"--init {args.init} holds no {DIT_FILE}; give the model folder the runs started from")
    try:
        result = pick(present, args.val, args.out, args.init, args.items, args.device, args.model_dir)
    except ValueError as error:
        parser.error(str(error))
    print("best", result["best"])


if __name__ == "__main__":
    main()
