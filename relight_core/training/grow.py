"""Make a trained model deeper without changing what it computes, to train on from there.

After every `every` blocks of the DiT a copy of the block just before it is inserted with the two
weights that write into the residual stream — the attention's `out_proj` and the MLP's `fc2` — set
to zero. A block adds `gate · h` to its input, and `h` is exactly zero when those weights are, so the
grown network returns the same output as the original for every input (the shared AdaLN-LoRA term
keeps the new blocks' gates non-zero, so both zeroed weights get a gradient on the first step and the
new blocks start learning at once). Copying the neighbour, rather than a random init, starts the new
blocks' queries, keys and MLP inputs at the scale the trained stream has.

Used when a model has stopped improving at its size (docs/QUALITY.md): the deeper network starts at
the old one's quality instead of from scratch, which on 2 CPU cores would take days to catch up.

    python -m relight_core.training.grow --model models/default --out ~/.cache/unirelight-studio/init-d12 --every 2
    python -m relight_core.training.fast ... --init ~/.cache/unirelight-studio/init-d12 --depth 12
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, resolve_model
from relight_core.errors import InputError

ZEROED = ("self_attn.out_proj.weight", "cross_attn.out_proj.weight", "mlp.fc2.weight")


def grown_order(depth: int, every: int) -> list[tuple[int, bool]]:
    """(source block, is a new zero-output copy) for each block of the grown stack."""
    if every < 1:
        raise InputError(f"--every takes a count of blocks, 1 or more, not {every}.")
    order = []
    for i in range(depth):
        order.append((i, False))
        if (i + 1) % every == 0:
            order.append((i, True))
    return order


def grow_state(state: dict[str, torch.Tensor], depth: int, every: int) -> tuple[dict[str, torch.Tensor], int]:
    """A DiT state dict with a zero-output copy inserted after every `every` of its `depth` blocks."""
    out = {k: v for k, v in state.items() if not k.startswith("blocks.")}
    order = grown_order(depth, every)
    for index, (source, fresh) in enumerate(order):
        prefix = f"blocks.{source}."
        names = [k for k in state if k.startswith(prefix)]
        if not names:
            raise InputError(f"The weights have no block {source}, but the config says depth {depth}; "
                             "grow a complete model folder.")
        for name in names:
            rest = name[len(prefix):]
            value = state[name].clone()
            if fresh and rest in ZEROED:
                value.zero_()
            out[f"blocks.{index}.{rest}"] = value
    return out, len(order)


def grow_model(model: str | Path, out: str | Path, every: int = 2) -> tuple[Path, int]:
    """Write the grown copy of a model folder (config.json with the new depth + dit.safetensors);
    returns (the folder, its depth)."""
    spec, directory = resolve_model(model)
    if directory is None:
        raise InputError(f"'{model}' is a preset without weights; grow a trained model folder.")
    config = json.loads((directory / CONFIG_FILE).read_text())
    try:
        weights = load_file(str(directory / DIT_FILE))
    except Exception as exc:  # missing, truncated or not safetensors
        raise InputError(f"Cannot read {directory / DIT_FILE} ({type(exc).__name__}); "
                         "copy the complete model folder.") from exc
    state, depth = grow_state(weights, spec.dit.depth, every)
    config["dit"]["depth"] = depth
    config["notes"] = {"grown": f"depth {spec.dit.depth} → {depth}: a zero-output copy after every {every} blocks "
                                "(relight_core.training.grow)",
                       "grown_from": str(model), "previous_notes": config.get("notes")}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in state.items()}, str(out / DIT_FILE))
    (out / CONFIG_FILE).write_text(json.dumps(config, indent=2, ensure_ascii=False) + "\n")
    return out, depth


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="a trained model folder (or 'default')")
    parser.add_argument("--out", required=True, type=Path, help="the folder to write the grown model to")
    parser.add_argument("--every", type=int, default=2, help="insert a new block after every N blocks")
    args = parser.parse_args(argv)
    try:
        out, depth = grow_model(args.model, args.out, args.every)
    except InputError as exc:
        parser.exit(2, f"error: {exc}\n")
    print(f"wrote {out} (depth {depth})")


if __name__ == "__main__":
    main()
