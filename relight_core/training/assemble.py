"""A model folder from parts: how one model runs, with another DiT's weights or refiners swapped in.

    python -m relight_core.training.assemble --like models/default --dit runs/gpu-round --out /tmp/cand
    python -m relight_core.training.assemble --like /tmp/cand --refiner runs/a/refiner.safetensors \\
        --relit-refiner runs/b/refiner.safetensors --bf16 --out /tmp/new

A GPU round hands back a DiT (as ≤ 15 MB shards + config.json, `fast.write_shards`, or a model folder) whose
config is the DiT's alone; the model ships with refiners, copies, filters and gains around it. `--like` is the
model whose config.json and refiners the new folder keeps; `--dit` swaps in the DiT weights (its config's
"dit" must be the same network; its notes go under notes.dit_round), `--refiner` / `--relit-refiner` swap in a
refiner's weights for that slot (the slot's config stays: the weights must fit it). `--bf16` stores every
weight in bf16 (how the default model ships). The folder is loaded once before the command returns, so a
part that does not fit is one sentence, not a broken model. Calibrate afterwards (`training.calibrate
--write`, `--strengths`): the gains, filters and strengths were fitted to the parts before.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, ModelSpec, load_model, load_refiner, resolve_model
from relight_core.errors import InputError
from relight_core.refiner import REFINER_SLOTS


def _weights(path: Path) -> dict[str, torch.Tensor]:
    """A safetensors file's tensors, or ValueError in one sentence for one that cannot be read."""
    try:
        return load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise ValueError(f"{path} is not a readable safetensors file ({exc})") from None


def dit_weights(source: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(state dict, config.json) of a model folder or a folder of `dit-shard-*.safetensors` + config.json."""
    config_path = source / CONFIG_FILE
    if not config_path.is_file():
        raise ValueError(f"--dit {source} holds no {CONFIG_FILE}; give a model folder or a GPU round's shards with theirs")
    files = [source / DIT_FILE] if (source / DIT_FILE).is_file() else sorted(source.glob("dit-shard-*.safetensors"))
    if not files:
        raise ValueError(f"--dit {source} holds neither {DIT_FILE} nor dit-shard-*.safetensors")
    state: dict[str, torch.Tensor] = {}
    for path in files:
        state.update(_weights(path))
    return state, json.loads(config_path.read_text())


def _network(config: dict):
    """The DiT a config.json describes (`DiTConfig`, so that 1 and 1.0 or a list and a tuple compare alike), or None."""
    try:
        return ModelSpec.from_json(config).dit
    except (ValueError, KeyError, TypeError):
        return None


def assemble(like: Path, out: Path, dit: Path | None = None, refiners: dict[str, Path] | None = None,
             bf16: bool = False) -> Path:
    """The model folder `out` (see the module docstring); returns it."""
    refiners = refiners or {}
    config = json.loads((like / CONFIG_FILE).read_text())
    for slot, path in refiners.items():
        if not config.get(slot):
            raise ValueError(f"{like} has no \"{slot}\" in its {CONFIG_FILE}, so there is no slot for {path}")
        if not path.is_file():
            raise ValueError(f"no refiner weights at {path}")
    if dit is not None:
        state, dit_config = dit_weights(dit)
        if (_network(dit_config) != _network(config)
                or (dit_config.get("tokenizer") or {}) != (config.get("tokenizer") or {})):
            raise ValueError(f"--dit {dit} is another network than {like}'s (its config's \"dit\" or \"tokenizer\" "
                             "differ); a model's refiners and settings carry over only to the same DiT")
        config.setdefault("notes", {})["dit_round"] = dit_config.get("notes", {})
    else:
        state = _weights(like / DIT_FILE)
    if out.resolve() == like.resolve():
        raise ValueError("--out must be a new folder, not --like's")
    out.mkdir(parents=True, exist_ok=True)

    def stored(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: (v.to(torch.bfloat16) if bf16 and v.is_floating_point() else v).contiguous() for k, v in tensors.items()}

    save_file(stored(state), out / DIT_FILE)
    for slot, file in REFINER_SLOTS.items():
        if not config.get(slot):
            continue
        source = refiners.get(slot, like / file)
        if bf16 or slot in refiners:
            save_file(stored(_weights(source)), out / file)
        else:
            shutil.copyfile(source, out / file)
    (out / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    spec, directory = resolve_model(out)
    try:
        load_model(out)
        for slot in REFINER_SLOTS:
            load_refiner(spec, directory, slot=slot)
    except InputError as error:
        raise ValueError(f"the assembled folder {out} does not load: {error}") from None
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--like", type=Path, required=True, help="the model folder whose config and refiners are kept")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--dit", type=Path, help="a model folder or a GPU round's shards + config.json: its DiT weights")
    parser.add_argument("--refiner", type=Path, help="weights for the \"refiner\" slot (refiner.safetensors of a refine run)")
    parser.add_argument("--relit-refiner", type=Path, help="weights for the \"relit_refiner\" slot")
    parser.add_argument("--bf16", action="store_true", help="store every weight in bf16")
    args = parser.parse_args(argv)
    if not (args.like / CONFIG_FILE).is_file() or (args.dit is None and not (args.like / DIT_FILE).is_file()):
        parser.error(f"--like {args.like} is not a model folder ({CONFIG_FILE}, and {DIT_FILE} unless --dit gives one)")
    refiners = {slot: path for slot, path in (("refiner", args.refiner), ("relit_refiner", args.relit_refiner)) if path}
    try:
        out = assemble(args.like, args.out, args.dit, refiners, args.bf16)
    except (ValueError, OSError) as error:
        parser.error(str(error))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
